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
(43 rows of the largest M seen, ≈3.4 MB at M = 10 000). On this Firecracker
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
    F = np.asarray(F, dtype=np.float64)
    if F.ndim != 3 or F.shape[1:] != (2, 2):
        raise ValueError(f"F must have shape (M, 2, 2), got {F.shape}")
    if F.shape[0] != params.mu.shape[0]:
        raise ValueError(f"F has {F.shape[0]} elements but params has {params.mu.shape[0]}")
    if order not in (0, 1, 2):
        raise ValueError(f"order must be 0, 1 or 2, got {order!r}")
    # Overflow for absurd F (|F| ~ 1e154) must not warn; it yields inf/NaN rows
    # that the callers' J and finiteness checks reject.
    with np.errstate(all="ignore"):
        if params.model == "linear":
            return _eval_linear(F, params, order)
        return _eval_neo_hookean(F, params, order)


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
# 28-42 intermediates.
_N_ROWS = 43


def _addmul(target, x, y, tmp):
    np.multiply(x, y, out=tmp)
    target += tmp


def _eval_neo_hookean(F, params, order):
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
        k = d
        mul(v0, v0, out=k)
        k *= e4
        k += teta
        _addmul(H[0], k, aa, tmp)
        _addmul(H[1], k, ab, tmp)
        _addmul(H[5], k, bb, tmp)
        mul(v1, v1, out=k)
        k *= e4
        k += teta
        _addmul(H[10], k, aa, tmp)
        _addmul(H[11], k, ab, tmp)
        _addmul(H[15], k, bb, tmp)
        mul(v0, v1, out=k)
        k *= e4
        _addmul(H[2], k, aa, tmp)
        _addmul(H[3], k, ab, tmp)
        _addmul(H[6], k, ab, tmp)
        _addmul(H[7], k, bb, tmp)

    # Mirror the upper triangle, then one transposed copy into the output.
    np.copyto(H[4], H[1])
    np.copyto(H[8], H[2])
    np.copyto(H[9], H[6])
    np.copyto(H[12], H[3])
    np.copyto(H[13], H[7])
    np.copyto(H[14], H[11])
    C = np.empty((M, 4, 4))
    np.copyto(C.reshape(M, 16), H.T)
    return psi, P, C


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
