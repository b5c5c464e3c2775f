"""Hyperelastic material models for 2-D plane-strain P1 elements (MODEL.md §3).

Units: stresses and moduli in kPa; energy densities in kPa = µJ/mm³ (multiply
by ``h * A_e`` in mm³ to get the element energy in µJ).

Conventions
-----------
* ``F`` is a stack of deformation gradients, shape ``(M, 2, 2)``,
  ``F[e, i, j] = dx_i/dX_j``.
* ``vec(F)`` is row-major: ``[F00, F01, F10, F11]``; tangents are
  ``(M, 4, 4)`` in that ordering, ``C[e] = d²Ψ/dvec(F)²`` (symmetric).
* Plane strain: ``F3 = diag(F, 1)``, ``J = det F``, ``I1 = tr(FᵀF) + 1``,
  ``Ī1 = J^(-2/3) I1``, ``I4 = a0ᵀ FᵀF a0``.

Models
------
* ``"linear"``: ``ε = sym(F − I)``, ``Ψ = μ ε:ε + λ/2 (tr ε)²`` with the
  Lamé ``λ = E ν / ((1+ν)(1−2ν)) = κ − 2μ/3``. Defined for every F (it is
  not rotation invariant — by design of small-strain theory).
* ``"neo_hookean"``: ``Ψ = μ/2 (Ī1 − 3) + κ/2 (J − 1)²``.
* ``"neo_hookean_fiber"``: the above ``+ η/2 (I4 − 1)²``; with
  ``tension_only`` the fiber term acts only where ``I4 > 1`` (its tangent
  jumps across ``I4 = 1``).

At ``F = I`` all models have zero energy and zero stress, and the
neo-Hookean tangent equals the linear one (small-strain consistency).

The neo-Hookean tangent is indefinite in much of the working range (its
twist eigenvalue ``μ g + s`` is ≈ 0 and negative under compression; the
fiber term is indefinite in fiber compression). For Newton's method
:func:`evaluate_projected` returns Ψ, P and a PSD surrogate tangent built
from closed-form eigensystems of each energy term (no ``eigh``);
:func:`project_psd` is the general (slower) batched projection of any
symmetric stack.

Closed forms used (``f = vec F``, ``c = vec cof F = [F11, −F10, −F01, F00]``,
``g = J^(-2/3)``)::

    P   = μ g F + s cof F,            s = κ (J − 1) − μ g I1 / (3 J)
    d²Ψ = μ g I + s Q − (2/3)(μ g/J)(f cᵀ + c fᵀ) + (κ + (5/9) μ g I1/J²) c cᵀ
    fiber, v = F a0, t = 2η (I4 − 1):
    P  += t v a0ᵀ,   d²Ψ += t kron(I2, a0 a0ᵀ) + 4η w wᵀ,  w = vec(v a0ᵀ)

where ``Q = d²J/df²`` (+1 at (0,3),(3,0), −1 at (1,2),(2,1)).

Inverted elements
-----------------
The nonlinear models are undefined for ``J <= 0``. There ``energy_density``
returns ``+inf`` (never NaN); stress and tangent are computed with J clipped
to ``J_FLOOR`` in the singular factors so they stay finite, but they are
meaningless. Callers must check ``jacobian_det(F) > 0`` (the solvers do) or
test ``np.isinf(psi)``. For ``0 < J < J_FLOOR`` all three outputs are those
at ``J_FLOOR`` (finite and huge). Rows whose arithmetic overflows
(``|F|`` around 1e154 or more) or whose F holds NaN also get ``psi = +inf``;
their P and C may then be inf/NaN. No floating-point warnings are ever
emitted. The ``linear`` model has no invalid region (NaN in gives NaN out).

Performance
-----------
The nonlinear models work on ``(M,)`` component rows with elementwise numpy
ufuncs writing into a per-thread scratch buffer that is reused across calls
(43 rows of the largest M seen, ≈3.4 MB at M = 10 000; 63 rows once
:func:`evaluate_projected` has been called). On this Firecracker
VM a first touch of freshly allocated memory costs ~4 µs per 4 KiB page,
which made the naive version (≈60 fresh (M,) temporaries per call) 3–5x
slower than its arithmetic; the scratch buffer removes that. Only the
returned arrays are new. Call :func:`release_workspace` to free the buffer.

``evaluate(F, params, order)`` for M = 10 000 random F near I, 2-core dev
machine (Firecracker VM), numpy 2.4, ``time.perf_counter``, median of 300
calls, two runs (ranges are run-to-run noise):

    ==================  ===========  ===========  ===========
    model               order 0      order 1      order 2
    ==================  ===========  ===========  ===========
    linear              0.07-0.10ms  0.16-0.36ms  0.25-0.30ms
    neo_hookean         0.21-0.22ms  0.32-0.34ms  0.68 ms
    neo_hookean_fiber   0.28-0.34ms  0.47-0.48ms  0.79-1.0 ms
    ==================  ===========  ===========  ===========

With a caller that keeps the previous results alive and allocates its own
(M,) temporaries between calls (closer to an ADMM loop), order 2 for
neo_hookean_fiber takes 1.0-1.25 ms. M = 64 000, order 2: 2.3-2.9 ms
(linear), 6.8-7.7 ms (neo_hookean_fiber). About 0.13 ms per 10 000 elements
of order 2 is the final transposed copy into the (M, 4, 4) output; exp/log
for J^(-2/3) is another ~0.13 ms.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

__all__ = [
    "MODELS",
    "J_FLOOR",
    "MaterialParams",
    "material_params",
    "energy_density",
    "stress",
    "tangent",
    "evaluate",
    "evaluate_projected",
    "project_psd",
    "jacobian_det",
    "release_workspace",
]

MODELS: tuple[str, ...] = ("linear", "neo_hookean", "neo_hookean_fiber")

#: Smallest J used in the singular factors (J^(-2/3), 1/J, 1/J²) so that
#: stress and tangent stay finite for (nearly) inverted elements.
J_FLOOR: float = 1e-12


def _readonly(a, shape, name) -> np.ndarray:
    a = np.array(a, dtype=np.float64, copy=True, order="C")
    if a.shape != shape:
        raise ValueError(f"MaterialParams.{name} must have shape {shape}, got {a.shape}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class MaterialParams:
    """Per-element material parameters for ``M`` elements.

    Attributes
    ----------
    model : str
        ``"linear"``, ``"neo_hookean"`` or ``"neo_hookean_fiber"``.
    mu : (M,) float, kPa
        Shear modulus ``E / (2(1+ν))``.
    kappa : (M,) float, kPa
        Bulk modulus ``E / (3(1−2ν))``.
    lam : (M,) float, kPa
        Lamé ``λ = E ν / ((1+ν)(1−2ν)) = κ − 2μ/3``; used by ``linear``.
    eta : (M,) float, kPa
        Fiber strength; zeros unless ``model == "neo_hookean_fiber"``.
    fiber : (M, 2) float
        Unit fiber direction ``a0`` in the reference frame.
    tension_only : bool
        Fiber term only where ``I4 > 1``.

    Prefer :func:`material_params`, which derives μ, κ, λ from E and ν,
    normalises the fiber and validates everything; the constructor itself
    only checks the model name and the shapes. Arrays are stored as read-only float64 copies; build a
    new instance (or use :meth:`take`) instead of editing. ``eq=False``:
    instances compare and hash by identity.
    """

    model: str
    mu: np.ndarray
    kappa: np.ndarray
    lam: np.ndarray
    eta: np.ndarray
    fiber: np.ndarray
    tension_only: bool = False

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(
                f"unknown material model {self.model!r}; allowed values: {', '.join(MODELS)}"
            )
        mu = np.asarray(self.mu)
        if mu.ndim != 1:
            raise ValueError(f"MaterialParams.mu must have shape (M,), got {mu.shape}")
        M = mu.shape[0]
        set_ = object.__setattr__
        for name in ("mu", "kappa", "lam", "eta"):
            set_(self, name, _readonly(getattr(self, name), (M,), name))
        set_(self, "fiber", _readonly(self.fiber, (M, 2), "fiber"))
        set_(self, "tension_only", bool(self.tension_only))
        # Contiguous fiber components and products, reused by every call.
        a = np.ascontiguousarray(self.fiber[:, 0])
        b = np.ascontiguousarray(self.fiber[:, 1])
        set_(self, "_fib", tuple(_ro(x) for x in (a, b, a * a, a * b, b * b)))

    @property
    def n_elements(self) -> int:
        """Number of elements ``M``."""
        return int(self.mu.shape[0])

    def take(self, idx) -> "MaterialParams":
        """Parameters of a subset of elements (index array or boolean mask)."""
        return MaterialParams(
            self.model,
            self.mu[idx],
            self.kappa[idx],
            self.lam[idx],
            self.eta[idx],
            self.fiber[idx],
            self.tension_only,
        )


def _ro(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def material_params(
    model: str,
    E_kPa,
    nu,
    eta_kPa,
    fiber,
    tension_only: bool = False,
) -> MaterialParams:
    """Build :class:`MaterialParams` for ``M`` elements from E, ν, η, a0.

    Parameters
    ----------
    model : str
        One of :data:`MODELS`; anything else raises ``ValueError``.
    E_kPa : float or (M,) array, kPa
        Young's modulus (> 0), per element or shared.
    nu : float or (M,) array
        Poisson's ratio, ``-1 < ν < 0.5``.
    eta_kPa : float or (M,) array or None, kPa
        Fiber strength (>= 0). Stored as zeros unless the model is
        ``"neo_hookean_fiber"``; ``None`` means 0.
    fiber : (M, 2) or (2,) array, or None
        Fiber direction in the reference frame; normalised here. A single
        (2,) vector is shared by all elements. ``None`` is allowed for the
        non-fiber models (stored as (1, 0)).
    tension_only : bool
        Apply the fiber term only where ``I4 > 1``.

    ``M`` is the common broadcast length of the array arguments (1 if all
    are scalars / a single vector).
    """
    if model not in MODELS:
        raise ValueError(
            f"unknown material model {model!r}; allowed values: {', '.join(MODELS)}"
        )
    E = np.asarray(E_kPa, dtype=np.float64)
    nu_a = np.asarray(nu, dtype=np.float64)
    eta = np.asarray(0.0 if eta_kPa is None else eta_kPa, dtype=np.float64)
    if fiber is None:
        if model == "neo_hookean_fiber":
            raise ValueError("model 'neo_hookean_fiber' needs a fiber direction")
        fib = np.array([[1.0, 0.0]])
    else:
        fib = np.asarray(fiber, dtype=np.float64)
        if fib.ndim == 1:
            fib = fib[None, :]
        if fib.ndim != 2 or fib.shape[1] != 2:
            raise ValueError(f"fiber must have shape (M, 2) or (2,), got {np.shape(fiber)}")
    for name, a in (("E_kPa", E), ("nu", nu_a), ("eta_kPa", eta)):
        if a.ndim > 1:
            raise ValueError(f"{name} must be a scalar or a 1-D array, got shape {a.shape}")
    try:
        (M,) = np.broadcast_shapes(E.shape, nu_a.shape, eta.shape, fib.shape[:1])
    except ValueError:
        raise ValueError(
            "material arrays have incompatible lengths: "
            f"E {E.shape}, nu {nu_a.shape}, eta {eta.shape}, fiber {fib.shape}"
        ) from None

    E = np.broadcast_to(E, (M,))
    nu_a = np.broadcast_to(nu_a, (M,))
    eta = np.broadcast_to(eta, (M,))
    fib = np.broadcast_to(fib, (M, 2))

    if not np.all(np.isfinite(E)) or np.any(E <= 0.0):
        raise ValueError("E_kPa must be finite and > 0")
    if not np.all(np.isfinite(nu_a)) or np.any(nu_a <= -1.0) or np.any(nu_a >= 0.5):
        raise ValueError("nu must satisfy -1 < nu < 0.5 (nu = 0.5 gives an infinite bulk modulus)")
    if not np.all(np.isfinite(eta)) or np.any(eta < 0.0):
        raise ValueError("eta_kPa must be finite and >= 0")
    norm = np.hypot(fib[:, 0], fib[:, 1])
    if not np.all(np.isfinite(norm)) or np.any(norm <= 0.0):
        raise ValueError("fiber directions must be finite and non-zero")

    mu = E / (2.0 * (1.0 + nu_a))
    kappa = E / (3.0 * (1.0 - 2.0 * nu_a))
    lam = E * nu_a / ((1.0 + nu_a) * (1.0 - 2.0 * nu_a))
    if model != "neo_hookean_fiber":
        eta = np.zeros(M)
    return MaterialParams(model, mu, kappa, lam, eta, fib / norm[:, None], tension_only)


# --------------------------------------------------------------------------
# scratch memory
# --------------------------------------------------------------------------


class _Workspace(threading.local):
    buf: np.ndarray | None = None


_WS = _Workspace()


def _scratch(rows: int, M: int) -> np.ndarray:
    """A (rows, M) view of this thread's reusable scratch buffer.

    Reusing one buffer (grown to the largest M seen) keeps the evaluation on
    already-mapped pages; see the module docstring for why that matters.
    """
    buf = _WS.buf
    if buf is None or buf.shape[0] < rows or buf.shape[1] < M:
        r = max(rows, 0 if buf is None else buf.shape[0])
        m = max(M, 0 if buf is None else buf.shape[1])
        buf = np.empty((r, m))
        _WS.buf = buf
    return buf[:rows, :M]


def release_workspace() -> None:
    """Free this thread's scratch buffer (it is re-created on demand)."""
    _WS.buf = None


# --------------------------------------------------------------------------
# evaluation
# --------------------------------------------------------------------------


def jacobian_det(F) -> np.ndarray:
    """``J = det F`` for a stack ``F`` of shape (M, 2, 2); returns (M,)."""
    F = np.asarray(F, dtype=np.float64)
    return F[:, 0, 0] * F[:, 1, 1] - F[:, 0, 1] * F[:, 1, 0]


def energy_density(F, params: MaterialParams) -> np.ndarray:
    """Strain-energy density Ψ(F), shape (M,), kPa (= µJ/mm³).

    ``+inf`` where ``J <= 0`` for the nonlinear models.
    """
    return evaluate(F, params, order=0)[0]


def stress(F, params: MaterialParams) -> np.ndarray:
    """First Piola–Kirchhoff stress ``P = dΨ/dF``, shape (M, 2, 2), kPa."""
    return evaluate(F, params, order=1)[1]


def tangent(F, params: MaterialParams) -> np.ndarray:
    """Tangent ``d²Ψ/dvec(F)²``, shape (M, 4, 4), kPa; symmetric, not PSD-projected."""
    return evaluate(F, params, order=2)[2]


def evaluate(F, params: MaterialParams, order: int = 2):
    """Energy density, stress and tangent, sharing intermediate work.

    Parameters
    ----------
    F : (M, 2, 2) array
        Deformation gradients.
    params : MaterialParams
        With ``params.n_elements == M``.
    order : {0, 1, 2}
        0: energy only; 1: energy and stress; 2: all three.

    Returns
    -------
    psi : (M,) kPa (+inf where J <= 0, nonlinear models)
    P : (M, 2, 2) kPa, or None if ``order < 1``
    C : (M, 4, 4) kPa, C-contiguous, or None if ``order < 2``

    The returned arrays are new (never views of internal scratch memory).
    """
    F = _check_F(F, params)
    if order not in (0, 1, 2):
        raise ValueError(f"order must be 0, 1 or 2, got {order!r}")
    # Overflow for absurd F (|F| ~ 1e154) must not warn; it yields inf/NaN rows
    # that the callers' J and finiteness checks reject.
    with np.errstate(all="ignore"):
        if params.model == "linear":
            return _eval_linear(F, params, order)
        return _eval_neo_hookean(F, params, order)


def _check_F(F, params) -> np.ndarray:
    F = np.asarray(F, dtype=np.float64)
    if F.ndim != 3 or F.shape[1:] != (2, 2):
        raise ValueError(f"F must have shape (M, 2, 2), got {F.shape}")
    if F.shape[0] != params.mu.shape[0]:
        raise ValueError(f"F has {F.shape[0]} elements but params has {params.mu.shape[0]}")
    return F


def _eval_linear(F, params, order):
    mu = params.mu
    lam = params.lam
    e00 = F[:, 0, 0] - 1.0
    e11 = F[:, 1, 1] - 1.0
    e01x2 = F[:, 0, 1] + F[:, 1, 0]  # 2 ε01
    tr = e00 + e11
    psi = mu * (e00 * e00 + e11 * e11 + 0.5 * e01x2 * e01x2) + 0.5 * lam * tr * tr
    if order == 0:
        return psi, None, None
    P = np.empty(F.shape)
    ltr = lam * tr
    P[:, 0, 0] = 2.0 * mu * e00 + ltr
    P[:, 1, 1] = 2.0 * mu * e11 + ltr
    shear = mu * e01x2
    P[:, 0, 1] = shear
    P[:, 1, 0] = shear
    if order == 1:
        return psi, P, None
    C = np.zeros((F.shape[0], 4, 4))
    d = 2.0 * mu + lam
    C[:, 0, 0] = d
    C[:, 3, 3] = d
    C[:, 0, 3] = lam
    C[:, 3, 0] = lam
    C[:, 1, 1] = mu
    C[:, 2, 2] = mu
    C[:, 1, 2] = mu
    C[:, 2, 1] = mu
    return psi, P, C


# Scratch rows used by _eval_neo_hookean: 0-3 F components, 4-7 their
# squares, 8-23 tangent (row 4i+j = C_ij), 24-27 stress (row 2i+j = P_ij),
# 28-42 intermediates. After an order-2 evaluation (what _project_rows
# relies on): 30 μ g, 32 s, 33 γ = κ + (5/9) μ g I1/J²,
# 34 F00 F11, 35 F01 F10, and for the fiber model 38-39 v = F a0,
# 40 I4 − 1, 41 t = 2 η_eff (I4 − 1), 42 4 η_eff; 24-29, 31, 36, 37 are free.
_N_ROWS = 43


def _addmul(target, x, y, tmp):
    np.multiply(x, y, out=tmp)
    target += tmp


def _submul(target, x, y, tmp):
    np.multiply(x, y, out=tmp)
    target -= tmp


def _eval_neo_hookean(F, params, order, keep_rows=False):
    """Ψ, P and C of the neo-Hookean models (see :func:`evaluate`).

    With ``keep_rows`` (order 2 only) the tangent is not copied out: the
    third result is the (``_N_ROWS``, M) scratch view itself, whose rows hold
    the tangent and the intermediates listed at ``_N_ROWS``. It is valid
    until the next call that uses the scratch buffer.
    """
    M = F.shape[0]
    fiber = params.model == "neo_hookean_fiber"
    mu = params.mu
    kappa = params.kappa
    mul, add, sub = np.multiply, np.add, np.subtract

    S = _scratch(_N_ROWS, M)
    Fr = S[0:4]
    f0, f1, f2, f3 = Fr
    sq0, sq1, sq2, sq3 = S[4:8]
    H = S[8:24]
    Pr = S[24:28]
    J, I1, alpha, iJ, s, aIJ, p03, p12, t1, t2, v0, v1, I4m1, teta, e4 = S[28:43]

    # One transposed copy gives contiguous component rows, so every later
    # op runs on unit-stride data.
    np.copyto(Fr.T, F.reshape(M, 4))
    mul(f0, f3, out=p03)
    mul(f1, f2, out=p12)
    sub(p03, p12, out=J)
    mul(f0, f0, out=sq0)
    mul(f1, f1, out=sq1)
    mul(f2, f2, out=sq2)
    mul(f3, f3, out=sq3)
    add(sq0, sq1, out=I1)
    I1 += sq2
    I1 += sq3
    I1 += 1.0
    # J.max() < inf also routes overflowed/NaN rows to the slow path below.
    all_valid = M == 0 or (J.min() > 0.0 and J.max() < np.inf)

    np.maximum(J, J_FLOOR, out=iJ)
    # exp(log(.)) beats np.power and np.cbrt for J^(-2/3) on this numpy build.
    np.log(iJ, out=alpha)
    alpha *= -2.0 / 3.0
    np.exp(alpha, out=alpha)
    alpha *= mu  # μ J^(-2/3)
    np.reciprocal(iJ, out=iJ)  # 1 / max(J, J_FLOOR)

    psi = mul(alpha, I1)
    mul(mu, 3.0, out=t1)
    psi -= t1
    sub(J, 1.0, out=s)  # J - 1 for now; becomes s in the stress block
    mul(s, s, out=t1)
    t1 *= kappa
    psi += t1
    psi *= 0.5

    if fiber:
        a, b, aa, ab, bb = params._fib
        mul(f0, a, out=v0)  # v = F a0
        _addmul(v0, f1, b, t1)
        mul(f2, a, out=v1)
        _addmul(v1, f3, b, t1)
        mul(v0, v0, out=I4m1)
        _addmul(I4m1, v1, v1, t1)
        I4m1 -= 1.0
        if params.tension_only:
            mul(params.eta, I4m1 > 0.0, out=teta)
        else:
            np.copyto(teta, params.eta)
        mul(I4m1, I4m1, out=t1)
        t1 *= teta
        t1 *= 0.5
        psi += t1

    if not all_valid:
        psi[~(J > 0.0)] = np.inf
        psi[np.isnan(psi)] = np.inf  # overflow (|F| ~ 1e154) gives inf·0
    if order == 0:
        return psi, None, None

    # s = κ (J - 1) - μ g I1 / (3 J);  P = μ g F + s cof F
    s *= kappa
    mul(alpha, I1, out=aIJ)
    aIJ *= iJ
    mul(aIJ, 1.0 / 3.0, out=t1)
    s -= t1
    P00, P01, P10, P11 = Pr
    mul(alpha, f0, out=P00)
    _addmul(P00, s, f3, t1)
    mul(alpha, f1, out=P01)
    mul(s, f2, out=t1)
    P01 -= t1
    mul(alpha, f2, out=P10)
    mul(s, f1, out=t1)
    P10 -= t1
    mul(alpha, f3, out=P11)
    _addmul(P11, s, f0, t1)
    if fiber:
        mul(teta, 4.0, out=e4)  # 4 η_eff, for the tangent
        teta *= I4m1
        teta *= 2.0  # t = 2 η_eff (I4 - 1)
        mul(teta, v0, out=t2)  # P += t v a0ᵀ
        _addmul(P00, t2, a, t1)
        _addmul(P01, t2, b, t1)
        mul(teta, v1, out=t2)
        _addmul(P10, t2, a, t1)
        _addmul(P11, t2, b, t1)
    P = np.empty((M, 2, 2))
    np.copyto(P.reshape(M, 4), Pr.T)
    if order == 1:
        return psi, P, None

    # β = -(2/3) μ g / J,  γ = κ + (5/9) μ g I1 / J²  (J, aIJ rows reused)
    beta = J
    mul(alpha, iJ, out=beta)
    beta *= -2.0 / 3.0
    gamma = aIJ
    gamma *= iJ
    gamma *= 5.0 / 9.0
    gamma += kappa
    d = I1  # free scratch from here on, like iJ
    tmp = iJ
    # C_ii: α ± 2β (F00 F11 | F01 F10) + γ c_i²
    mul(beta, p03, out=d)
    d *= 2.0
    d += alpha
    mul(gamma, sq3, out=H[0])
    H[0] += d
    mul(gamma, sq0, out=H[15])
    H[15] += d
    mul(beta, p12, out=d)
    d *= -2.0
    d += alpha
    mul(gamma, sq2, out=H[5])
    H[5] += d
    mul(gamma, sq1, out=H[10])
    H[10] += d
    # u = β (F01 F11 - F00 F10): C01 = u - γ F10 F11, C23 = -u - γ F00 F01
    mul(f1, f3, out=d)
    mul(f0, f2, out=tmp)
    d -= tmp
    d *= beta
    mul(f2, f3, out=H[1])
    H[1] *= gamma
    sub(d, H[1], out=H[1])
    mul(f0, f1, out=H[11])
    H[11] *= gamma
    H[11] += d
    np.negative(H[11], out=H[11])
    # w = β (F10 F11 - F00 F01): C02 = w - γ F01 F11, C13 = -w - γ F00 F10
    mul(f2, f3, out=d)
    mul(f0, f1, out=tmp)
    d -= tmp
    d *= beta
    mul(f1, f3, out=H[2])
    H[2] *= gamma
    sub(d, H[2], out=H[2])
    mul(f0, f2, out=H[7])
    H[7] *= gamma
    H[7] += d
    np.negative(H[7], out=H[7])
    # C03 = s + β (F00² + F11²) + γ F00 F11;  C12 = -s - β (F01² + F10²) + γ F01 F10
    add(sq0, sq3, out=d)
    d *= beta
    d += s
    mul(gamma, p03, out=H[3])
    H[3] += d
    add(sq1, sq2, out=d)
    d *= beta
    d += s
    mul(gamma, p12, out=H[6])
    H[6] -= d

    if fiber:
        # t kron(I, a aᵀ) + 4η w wᵀ, w = vec(v aᵀ): per 2x2 block (rows of F)
        # the block is k a aᵀ with k0 = t + 4η v0², k1 = t + 4η v1², k01 = 4η v0 v1.
        _fiber_block(H, _addmul, v0, v1, e4, teta, aa, ab, bb, d, tmp)

    if keep_rows:
        return psi, P, S
    return psi, P, _tangent_from_rows(H)


def _tangent_from_rows(H) -> np.ndarray:
    """(M, 4, 4) tangents from the upper-triangle rows H (16, M): mirror, then one transposed copy."""
    for lower, upper in ((4, 1), (8, 2), (9, 6), (12, 3), (13, 7), (14, 11)):
        np.copyto(H[lower], H[upper])
    C = np.empty((H.shape[1], 4, 4))
    np.copyto(C.reshape(-1, 16), H.T)
    return C


def _fiber_block(H, accumulate, v0, v1, c, d, aa, ab, bb, k, tmp):
    """H ±= (c v vᵀ + d I) ⊗ a aᵀ on the upper-triangle rows (16, M), v = F a0.

    The fiber tangent (c = 4η, d = t) and its negative part (c = (n2 − n1)/I4,
    d = n1) have this form; `accumulate` is _addmul or _submul; k, tmp scratch rows.
    """
    for (i, j), rows in (((0, 0), (0, 1, 5)), ((1, 1), (10, 11, 15))):
        np.multiply((v0, v1)[i], (v0, v1)[j], out=k)
        k *= c
        k += d
        for row, w in zip(rows, (aa, ab, bb)):
            accumulate(H[row], k, w, tmp)
    np.multiply(v0, v1, out=k)
    k *= c
    for row, w in zip((2, 3, 6, 7), (aa, ab, ab, bb)):
        accumulate(H[row], k, w, tmp)


# --------------------------------------------------------------------------
# analytic per-term PSD projection of the tangent
# --------------------------------------------------------------------------

#: Scratch rows used by _project_rows beyond the _N_ROWS of _eval_neo_hookean.
_N_PROJ_ROWS = 20

_TINY = float(np.finfo(np.float64).tiny)


def evaluate_projected(F, params: MaterialParams):
    """Energy density, stress and a PSD-projected tangent in one pass.

    Returns ``(psi, P, C_proj)``: ``psi`` and ``P`` are bit-for-bit those of
    ``evaluate(F, params, 2)``; ``C_proj`` (M, 4, 4) is symmetric positive
    semidefinite, a new C-contiguous array. It is meant for Newton's method
    in place of ``project_psd(evaluate(F, params, 2)[2])`` and is more
    than 10x cheaper (no eigendecomposition, no Python loop over elements).

    The projection is done **per energy term**, with closed-form
    eigensystems (Smith, de Goes & Kim 2019, "Analytic eigensystems for
    isotropic distortion energies"; Kim, de Goes & Smith 2019, "Anisotropic
    elasticity for inversion-safety and element rehabilitation"):
    ``C_proj = proj(C_iso) + proj(C_fiber)``, where ``proj`` clamps negative
    eigenvalues to 0. A sum of PSD matrices is PSD, so this is a valid
    Newton surrogate, but it is *not* the projection of the sum
    ``proj(C_iso + C_fiber)`` (that is what :func:`project_psd` computes):
    where the fiber term is indefinite (compressed fiber) the two differ.
    For ``"neo_hookean"`` (a single term) the two coincide up to round-off.

    * ``"linear"``: C is constant and PSD; ``evaluate(F, params, 2)`` is
      returned unchanged.
    * Isotropic neo-Hookean term, with ``F = U diag(σ1, σ2) Vᵀ`` (U, V
      rotations, σ1 >= σ2 > 0), ``g = J^(-2/3)``, ``S = σ1² + σ2² + 1``,
      ``s = κ (J − 1) − μ g S / (3 J)`` (the cofactor factor of P). Four
      orthonormal eigenmatrices of ``d²Ψ/dvec(F)²``:

      - twist ``U [[0,−1],[1,0]] Vᵀ/√2``, ``λ = (Ψ_1+Ψ_2)/(σ1+σ2) = μ g + s``
        (≈ 0 and negative in compression: the common case);
      - flip ``U [[0,1],[1,0]] Vᵀ/√2``, ``λ = (Ψ_1−Ψ_2)/(σ1−σ2) = μ g − s``
        (closed form, no 0/0 at σ1 = σ2);
      - two scaling modes ``U diag(z) Vᵀ``, z the eigenvectors of the 2x2
        Hessian of Ψ(σ1, σ2). Written in the basis ``r = U Vᵀ/√2`` (the
        polar rotation: dilation) and ``d = U diag(1,−1) Vᵀ/√2``, that
        block is ``[[m + h, a], [a, m − h]]`` with
        ``m = (Ψ_11+Ψ_22)/2 = μ g (5 S (S−1)/(18 J²) − 1/3) + κ (S−1)/2``,
        ``h = Ψ_12 = μ g (2 − 4 (S−1))/(9 J) + κ (2J − 1)``,
        ``a = (Ψ_11−Ψ_22)/2 = −(σ1² − σ2²) γ/2``,
        ``γ = κ + (5/9) μ g S/J²``; its negative part is taken in closed
        form (no eigenvectors needed).

    * Fiber term ``η/2 (I4 − 1)²`` (``"neo_hookean_fiber"``), ``v = F a0``,
      ``t = 2η (I4 − 1)``: on span{e_i ⊗ a0} it is ``t I + 4η v vᵀ``, with
      eigenvalue ``t`` along ``v⊥ ⊗ a0`` and ``t + 4η I4 = 2η (3 I4 − 1)``
      along ``v̂ ⊗ a0``; zero elsewhere. With ``tension_only`` it is zero
      where ``I4 <= 1``. Negative only in fiber compression (``I4 < 1``).

    Implementation: ``C_proj = C − Σ_k min(λ_k, 0) e_k e_kᵀ`` over both
    terms, so wherever every term is already PSD, ``C_proj`` is ``C``
    bit-for-bit. Everything is written in the rotation / reflection parts
    of F (``F = Q rot(ω) + R refl(ρ)``, ``σ1,2 = Q ± R``), which needs no
    trigonometric functions and only one square root per element.

    Invalid rows (psi = +inf: ``J <= 0``, overflow, NaN in F), rows with
    ``0 < J <= J_FLOOR`` and rows whose closed forms overflow (``|F|``
    far beyond any physical value) get :func:`project_psd` of their (clipped,
    meaningless) tangent from :func:`evaluate`, or 0 where that is not
    finite; so ``C_proj`` is finite and PSD in every row and no
    floating-point warning is emitted. Callers must still check
    ``jacobian_det(F) > 0`` / ``np.isinf(psi)`` as for :func:`evaluate`.

    Timing (M = 15 708, F = I + 0.1 N(0,1), E in 5-50 kPa, ν = 0.45, η = 10
    kPa, 2-core Firecracker dev VM, ``time.perf_counter``, median of 30
    calls, two runs): 1.9-2.4 ms here against 27-29 ms for
    ``evaluate(F, p, 2)`` + ``project_psd`` (≈ 60 % of those elements are
    indefinite and go through the batched ``eigh``); ``evaluate`` alone
    takes 1.0-1.3 ms. The extra scratch rows grow the shared workspace to
    ``_N_ROWS + _N_PROJ_ROWS`` = 63 rows of M.
    """
    return _evaluate_projected(F, params, clamp=True)


def _evaluate_projected(F, params, clamp=True):
    """:func:`evaluate_projected`; ``clamp=False`` is a testing hook.

    With ``clamp=False`` the subtracted "negative parts" are the whole
    eigen-terms ``λ_k e_k e_kᵀ``, so for valid rows the returned matrix is
    ``C`` minus its own analytic reconstruction, i.e. ≈ 0: this checks the
    closed forms of the fast path against :func:`evaluate`'s tangent.
    """
    F = _check_F(F, params)
    M = F.shape[0]
    with np.errstate(all="ignore"):
        if params.model == "linear":
            return _eval_linear(F, params, 2)
        rows = _N_ROWS + _N_PROJ_ROWS
        _scratch(rows, M)  # grow first, so the evaluation below uses this buffer
        psi, P, _ = _eval_neo_hookean(F, params, 2, keep_rows=True)
        S = _scratch(rows, M)
        bad = _project_rows(S, params, psi, clamp)
        C = _tangent_from_rows(S[8:24])
        if bad is not None:
            C[bad] = _fallback_projection(F[bad], params.take(bad))
    return psi, P, C


def _project_rows(S, params, psi, clamp):
    """Subtract the negative eigen-parts of each term from the tangent rows.

    ``S`` is the (``_N_ROWS + _N_PROJ_ROWS``, M) scratch view right after an
    order-2 ``_eval_neo_hookean(..., keep_rows=True)``; its tangent rows
    8-23 (upper triangle) are updated in place. Returns the indices of the
    rows that need :func:`_fallback_projection`, or None.
    """
    mul, add, sub = np.multiply, np.add, np.subtract
    minimum = np.minimum
    kappa = params.kappa
    f0, f1, f2, f3 = S[0:4]
    sq0, sq1, sq2, sq3 = S[4:8]
    H = S[8:24]
    alpha, s, gamma, p03, p12 = S[30], S[32], S[33], S[34], S[35]
    E, Hr, Fh, G = S[24:28]
    J, T2, iJ, t1, t2 = S[28], S[29], S[31], S[36], S[37]
    (Q2, R2, lt, ll, m, h, rad, l2, k1, c0,
     d1, d2, cc, cs, CC, CS, X, Y, Xp, Yp) = S[_N_ROWS:_N_ROWS + _N_PROJ_ROWS]

    sub(p03, p12, out=J)
    np.maximum(J, J_FLOOR, out=iJ)
    np.reciprocal(iJ, out=iJ)
    add(sq0, sq1, out=T2)  # tr FᵀF = σ1² + σ2² = I1 − 1
    T2 += sq2
    T2 += sq3
    # F = E I + Hr [[0,−1],[1,0]] + Fh diag(1,−1) + G [[0,1],[1,0]]
    #   = Q rot(ω) + R refl(ρ),  (E, Hr) = Q (cos ω, sin ω), (Fh, G) = R (cos ρ, sin ρ),
    # Q = (σ1+σ2)/2, R = (σ1−σ2)/2, rot(ω) = U Vᵀ, refl(ρ) = U diag(1,−1) Vᵀ.
    add(f0, f3, out=E)
    E *= 0.5
    sub(f2, f1, out=Hr)
    Hr *= 0.5
    sub(f0, f3, out=Fh)
    Fh *= 0.5
    add(f2, f1, out=G)
    G *= 0.5
    mul(E, E, out=Q2)
    _addmul(Q2, Hr, Hr, t1)
    mul(Fh, Fh, out=R2)
    _addmul(R2, G, G, t1)

    # Twist and flip eigenvalues: μg ± s.
    add(alpha, s, out=lt)
    sub(alpha, s, out=ll)
    # Scaling block [[m+h, a], [a, m−h]] in the (r, d) basis, a = −2QRγ.
    add(T2, 1.0, out=t1)  # I1
    t1 *= T2
    t1 *= iJ
    t1 *= iJ
    t1 *= 5.0 / 18.0
    t1 -= 1.0 / 3.0
    mul(alpha, t1, out=m)
    mul(kappa, T2, out=t1)
    t1 *= 0.5
    m += t1
    mul(T2, -4.0, out=h)
    h += 2.0
    h *= iJ
    h *= alpha
    h *= 1.0 / 9.0
    mul(J, 2.0, out=t1)
    t1 -= 1.0
    t1 *= kappa
    h += t1
    mul(Q2, R2, out=rad)  # rad = sqrt(h² + a²), a² = 4 Q² R² γ²
    mul(gamma, gamma, out=t1)
    rad *= t1
    rad *= 4.0
    mul(h, h, out=t1)
    rad += t1
    np.sqrt(rad, out=rad)

    # Negative parts. Block: with eigenvalues l1 >= l2 and n_i = min(l_i, 0),
    # N = n2 I + k1 (B − l2 I), k1 = (n1 − n2)/(l1 − l2) (0 if l1 = l2).
    sub(m, rad, out=l2)
    add(m, rad, out=k1)  # l1 for now
    if clamp:
        minimum(lt, 0.0, out=lt)
        minimum(ll, 0.0, out=ll)
        minimum(k1, 0.0, out=k1)
        minimum(l2, 0.0, out=c0)
    else:
        np.copyto(c0, l2)
    k1 -= c0  # n1 − n2
    mul(rad, 2.0, out=t1)
    np.maximum(t1, _TINY, out=t1)
    k1 /= t1
    mul(k1, l2, out=t1)
    c0 -= t1  # c0 = n2 − k1 l2;  N_rr = c0 + k1 (m+h), N_dd = c0 + k1 (m−h)
    # Halved coefficients of the (unit-free) outer products below:
    # d1 = (N_rr − n_twist)/2 and d2 = (N_dd − n_flip)/2, with
    # a_r = N_rr/2 = n_twist/2 + d1 and b_d = N_dd/2 = n_flip/2 + d2.
    add(m, h, out=d1)
    d1 *= k1
    d1 += c0
    d1 -= lt
    d1 *= 0.5
    sub(m, h, out=d2)
    d2 *= k1
    d2 += c0
    d2 -= ll
    d2 *= 0.5
    lt *= 0.5  # a_t
    ll *= 0.5  # b_l
    # cos²ω, cos ω sin ω and cos²ρ, cos ρ sin ρ (ρ undefined for R = 0: 45°,
    # where the block is isotropic in the reflection plane anyway).
    np.reciprocal(Q2, out=t1)
    mul(E, E, out=cc)
    cc *= t1
    mul(E, Hr, out=cs)
    cs *= t1
    np.maximum(R2, _TINY, out=t1)
    np.reciprocal(t1, out=t1)
    mul(Fh, Fh, out=CC)
    CC *= t1
    mul(Fh, G, out=CS)
    CS *= t1
    degenerate = R2 < _TINY
    np.copyto(CC, 0.5, where=degenerate)
    np.copyto(CS, 0.0, where=degenerate)
    # Rotation plane (r, twist): X = a_t + δ cos²ω, Y = a_t + δ sin²ω,
    # Z = δ cos ω sin ω with δ = d1; reflection plane (d, flip): X', Y', Z'
    # likewise with b_l, d2 and ρ.
    mul(d1, cc, out=X)
    add(lt, d1, out=Y)
    Y -= X
    X += lt
    cs *= d1  # Z
    mul(d2, CC, out=Xp)
    add(ll, d2, out=Yp)
    Yp -= Xp
    Xp += ll
    CS *= d2  # Z'
    # Cross terms N_rd (r dᵀ + d rᵀ), N_rd = k1 a = −2 k1 γ Q R; the Q R
    # cancels against cos ω cos ρ = E Fh / (Q R) etc.:
    # eu = −k1γ E Fh, ev = −k1γ Hr G, ep = −k1γ (E G − Hr Fh), eq = −k1γ (E G + Hr Fh).
    mul(k1, gamma, out=t1)
    np.negative(t1, out=t1)
    eu, ev, ep, eq = cc, CC, l2, m
    mul(E, Fh, out=eu)
    eu *= t1
    mul(Hr, G, out=ev)
    ev *= t1
    mul(E, G, out=t2)
    mul(Hr, Fh, out=h)
    sub(t2, h, out=ep)
    ep *= t1
    add(t2, h, out=eq)
    eq *= t1
    # Subtract N (upper triangle; row 4i+j = C_ij). With Z = cs, Z' = CS:
    #   N00 = X+X'+2eu  N01 = Z'−Z+ep  N02 = Z+Z'+eq  N03 = X−X'
    #   N11 = Y+Y'−2ev  N12 = Y'−Y     N13 = eq−Z−Z'
    #   N22 = Y+Y'+2ev  N23 = Z−Z'+ep  N33 = X+X'−2eu
    eu *= 2.0
    ev *= 2.0
    add(X, Xp, out=t2)
    H[0] -= t2
    H[0] -= eu
    H[15] -= t2
    H[15] += eu
    add(Y, Yp, out=t2)
    H[5] -= t2
    H[5] += ev
    H[10] -= t2
    H[10] -= ev
    sub(X, Xp, out=t2)
    H[3] -= t2
    sub(Yp, Y, out=t2)
    H[6] -= t2
    sub(CS, cs, out=t2)
    H[1] -= t2
    H[1] -= ep
    H[11] += t2
    H[11] -= ep
    add(cs, CS, out=t2)
    H[2] -= t2
    H[2] -= eq
    H[7] += t2
    H[7] -= eq

    if params.model == "neo_hookean_fiber":
        v0, v1, I4m1, teta, e4 = S[38:43]
        # Fiber block t I + 4η v vᵀ on span{e_i ⊗ a0}: eigenvalues t (v⊥) and
        # t + 4η I4 (v̂). Negative part nf1 I + (nf2 − nf1) v vᵀ / I4.
        if not clamp or (teta < 0.0).any():
            _, _, aa, ab, bb = params._fib
            nf1, nf2, q, I4 = X, Y, Xp, Yp
            add(I4m1, 1.0, out=I4)
            mul(e4, I4, out=nf2)
            nf2 += teta
            np.copyto(nf1, teta)
            if clamp:
                minimum(nf1, 0.0, out=nf1)
                minimum(nf2, 0.0, out=nf2)
            sub(nf2, nf1, out=q)
            np.maximum(I4, _TINY, out=I4)
            q /= I4
            _fiber_block(H, _submul, v0, v1, q, nf1, aa, ab, bb, t2, t1)

    # Rows to hand to the fallback: J <= J_FLOOR, psi = +inf, or anything
    # non-finite in the result (overflow of the closed forms).
    add(H[0], H[1], out=t1)
    for i in (2, 3, 5, 6, 7, 10, 11, 15):
        t1 += H[i]
    good = np.isfinite(t1)
    good &= J > J_FLOOR
    good &= psi < np.inf
    if good.all():
        return None
    return np.flatnonzero(~good)


def _fallback_projection(F, params) -> np.ndarray:
    """PSD projection of evaluate's tangent for rows the closed forms cannot take.

    Each matrix is scaled by its largest entry before :func:`project_psd`
    (the projection is positively homogeneous), so huge finite entries do
    not overflow inside ``eigh``; non-finite matrices become 0.
    """
    _, _, C = _eval_neo_hookean(F, params, 2)
    C[~np.isfinite(C).all(axis=(1, 2))] = 0.0
    scale = np.abs(C).max(axis=(1, 2))
    scale[scale == 0.0] = 1.0
    C /= scale[:, None, None]
    C = project_psd(C)
    C += np.swapaxes(C, 1, 2)  # eigh's V w Vᵀ is symmetric only to round-off
    C *= 0.5 * scale[:, None, None]
    C[~np.isfinite(C).all(axis=(1, 2))] = 0.0
    return C


def _eigensystem(F, params):
    """Reference analytic eigensystems of the two energy terms (for tests).

    Straightforward (allocating, σ-based) evaluation of the closed forms in
    the :func:`evaluate_projected` docstring, independent of its fast path.
    Nonlinear models and ``J > 0`` only (other rows give meaningless values).

    Returns
    -------
    lam_iso : (M, 4)
        Eigenvalues of the isotropic term's tangent: the two scaling modes
        (larger first), twist, flip.
    vec_iso : (M, 4, 4)
        ``vec_iso[e, k]`` is the unit eigenvector (as vec) of ``lam_iso[e, k]``.
    lam_fib : (M, 2)
        Fiber term eigenvalues ``t`` (along ``v⊥ ⊗ a0``) and ``t + 4η I4``
        (along ``v̂ ⊗ a0``); zero for ``"neo_hookean"`` and where
        ``tension_only`` switches the fiber off. The fiber term is zero on
        the orthogonal complement of these two vectors.
    vec_fib : (M, 2, 4)
    """
    if params.model == "linear":
        raise ValueError("_eigensystem is for the nonlinear models")
    F = _check_F(F, params)
    mu, kappa = params.mu, params.kappa
    with np.errstate(all="ignore"):
        f00, f01, f10, f11 = F[:, 0, 0], F[:, 0, 1], F[:, 1, 0], F[:, 1, 1]
        E, Hr = (f00 + f11) / 2, (f10 - f01) / 2
        Fh, G = (f00 - f11) / 2, (f10 + f01) / 2
        Q, R = np.hypot(E, Hr), np.hypot(Fh, G)
        s1, s2 = Q + R, Q - R
        cw, sw = E / Q, Hr / Q
        zero = R == 0.0
        cr = np.where(zero, 1.0, Fh / np.where(zero, 1.0, R))
        sr = np.where(zero, 0.0, G / np.where(zero, 1.0, R))
        rot = np.stack([cw, -sw, sw, cw], -1)  # vec(U Vᵀ)
        refl = np.stack([cr, sr, sr, -cr], -1)  # vec(U diag(1,−1) Vᵀ)
        D1, D2 = (rot + refl) / 2, (rot - refl) / 2  # vec(U diag(1,0) Vᵀ), vec(U diag(0,1) Vᵀ)
        twist = np.stack([-sw, -cw, cw, -sw], -1) / np.sqrt(2.0)
        flip = np.stack([-sr, cr, cr, sr], -1) / np.sqrt(2.0)

        J = s1 * s2
        g = J ** (-2.0 / 3.0)
        Sg = s1 * s1 + s2 * s2 + 1.0
        lam_twist = mu * g * (1.0 - Sg / (3 * J)) + kappa * (J - 1)
        lam_flip = mu * g * (Sg / (3 * J) + 1.0) - kappa * (J - 1)
        p11 = mu * g * (-1.0 / 3 + 5 * Sg / (9 * s1 * s1)) + kappa * s2 * s2
        p22 = mu * g * (-1.0 / 3 + 5 * Sg / (9 * s2 * s2)) + kappa * s1 * s1
        p12 = mu * g * (2 * Sg / (9 * J) - 2 * (s1 * s1 + s2 * s2) / (3 * J)) + kappa * (2 * J - 1)
        mean, rad = (p11 + p22) / 2, np.hypot((p11 - p22) / 2, p12)
        th = 0.5 * np.arctan2(2 * p12, p11 - p22)
        c, s = np.cos(th), np.sin(th)
        e1 = c[:, None] * D1 + s[:, None] * D2
        e2 = -s[:, None] * D1 + c[:, None] * D2
        lam_iso = np.stack([mean + rad, mean - rad, lam_twist, lam_flip], -1)
        vec_iso = np.stack([e1, e2, twist, flip], 1)

        a0 = params.fiber
        # v and I4 − 1 exactly as evaluate computes them (same tension_only switch).
        v = np.stack([f00 * a0[:, 0] + f01 * a0[:, 1], f10 * a0[:, 0] + f11 * a0[:, 1]], -1)
        I4m1 = v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] - 1.0
        I4 = I4m1 + 1.0
        eta = params.eta * (I4m1 > 0.0) if params.tension_only else params.eta
        t = 2 * eta * I4m1
        vh = v / np.sqrt(I4)[:, None]
        vp = np.stack([-vh[:, 1], vh[:, 0]], -1)
        lam_fib = np.stack([t, t + 4 * eta * I4], -1)
        vec_fib = np.stack([
            (vp[:, :, None] * a0[:, None, :]).reshape(-1, 4),
            (vh[:, :, None] * a0[:, None, :]).reshape(-1, 4),
        ], 1)
    return lam_iso, vec_iso, lam_fib, vec_fib


def project_psd(C, floor: float = 0.0) -> np.ndarray:
    """Batched symmetric PSD projection of ``C`` (M, k, k).

    Eigenvalues below ``floor`` are raised to ``floor`` (``np.linalg.eigh``
    on the stack, which reads the lower triangle, so ``C`` is assumed
    symmetric). Matrices whose smallest eigenvalue is already ``>= floor``
    are returned bit-for-bit unchanged; the result is always a new array.
    """
    C = np.asarray(C, dtype=np.float64)
    if C.ndim != 3 or C.shape[1] != C.shape[2]:
        raise ValueError(f"C must have shape (M, k, k), got {C.shape}")
    out = C.copy()
    if C.shape[0] == 0:
        return out
    # Only matrices that may have an eigenvalue below floor need the (costly,
    # batched) eigendecomposition: 4x4 ones that are clearly positive
    # definite, by Sylvester's criterion with a small shift, are skipped.
    maybe = ~_clearly_positive_definite(C, floor) if C.shape[1] == 4 else np.ones(C.shape[0], bool)
    if not maybe.any():
        return out
    w, V = np.linalg.eigh(C[maybe])
    bad = w[:, 0] < floor
    if bad.any():
        wb = np.maximum(w[bad], floor)
        Vb = V[bad]
        idx = np.flatnonzero(maybe)[bad]
        out[idx] = (Vb * wb[:, None, :]) @ np.swapaxes(Vb, 1, 2)
    return out


def _clearly_positive_definite(C: np.ndarray, floor: float) -> np.ndarray:
    """(M,) bool: C - (floor + δ) I is positive definite for each symmetric 4x4 C (leading minors > 0).

    δ = 1e-10 × the largest |entry| keeps round-off from passing a singular
    matrix; a False only sends the matrix to the exact eigendecomposition.
    """
    with np.errstate(all="ignore"):  # overflowing rows compare False and go to eigh
        shift = floor + 1e-10 * np.abs(C).max(axis=(1, 2))
        A = C - shift[:, None, None] * np.eye(4)
        a = [[A[:, i, j] for j in range(4)] for i in range(4)]
        m1 = a[0][0]
        m2 = a[0][0] * a[1][1] - a[0][1] * a[1][0]
        c00 = a[1][1] * a[2][2] - a[1][2] * a[2][1]
        c01 = a[1][0] * a[2][2] - a[1][2] * a[2][0]
        c02 = a[1][0] * a[2][1] - a[1][1] * a[2][0]
        m3 = a[0][0] * c00 - a[0][1] * c01 + a[0][2] * c02
        m4 = np.linalg.det(A)
        return (m1 > 0) & (m2 > 0) & (m3 > 0) & (m4 > 0)
