"""Material parameters: the model names, per-element moduli and fibers (docs/model.md §3).

:func:`material_params` derives the moduli from E and ν and validates its
input; :class:`MaterialParams` holds them as read-only per-element arrays.
Moduli are in kPa.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    fiber : (M, 2) or (M, 3) float
        Unit fiber direction ``a0`` in the reference frame. A 2-component
        fiber lies in the x-y plane: the 3-D kernels use ``(a0, 0)`` (the
        fiber of a layer, ``(cos θ, sin θ, 0)``). The 2-D kernels need a
        2-component fiber.
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
        fiber = np.asarray(self.fiber)
        if fiber.ndim != 2 or fiber.shape[1] not in (2, 3):
            raise ValueError(f"MaterialParams.fiber must have shape (M, 2) or (M, 3), got {fiber.shape}")
        set_(self, "fiber", _readonly(fiber, (M, fiber.shape[1]), "fiber"))
        set_(self, "tension_only", bool(self.tension_only))
        # Contiguous fiber components and products, reused by every 2-D call
        # (None for 3-component fibers, which the 2-D kernels reject).
        fib = None
        if fiber.shape[1] == 2:
            a = np.ascontiguousarray(self.fiber[:, 0])
            b = np.ascontiguousarray(self.fiber[:, 1])
            fib = tuple(_ro(x) for x in (a, b, a * a, a * b, b * b))
        set_(self, "_fib", fib)
        # The fiber as the 3-D kernels take it, (M, 3) C-contiguous (an in-plane one as (a0, 0)): made once here,
        # not on every 3-D gradient (the copy cost a few % of a slab's gradient)
        fiber3 = np.zeros((M, 3))
        fiber3[:, :fiber.shape[1]] = self.fiber
        set_(self, "_fiber3", fiber3)

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
    fiber : (M, 2), (2,), (M, 3) or (3,) array, or None
        Fiber direction in the reference frame; normalised here. A single
        vector is shared by all elements. Two components: an in-plane fiber,
        usable in 2-D and 3-D (see :class:`MaterialParams`); three: 3-D
        only. ``None`` is allowed for the non-fiber models (stored as (1, 0)).
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
        if fib.ndim != 2 or fib.shape[1] not in (2, 3):
            raise ValueError(
                f"fiber must have shape (M, 2), (2,), (M, 3) or (3,), got {np.shape(fiber)}"
            )
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
    fib = np.broadcast_to(fib, (M, fib.shape[1]))

    if not np.all(np.isfinite(E)) or np.any(E <= 0.0):
        raise ValueError("E_kPa must be finite and > 0")
    if not np.all(np.isfinite(nu_a)) or np.any(nu_a <= -1.0) or np.any(nu_a >= 0.5):
        raise ValueError("nu must satisfy -1 < nu < 0.5 (nu = 0.5 gives an infinite bulk modulus)")
    if not np.all(np.isfinite(eta)) or np.any(eta < 0.0):
        raise ValueError("eta_kPa must be finite and >= 0")
    norm = np.hypot(fib[:, 0], fib[:, 1])
    if fib.shape[1] == 3:
        norm = np.hypot(norm, fib[:, 2])
    if not np.all(np.isfinite(norm)) or np.any(norm <= 0.0):
        raise ValueError("fiber directions must be finite and non-zero")

    mu = E / (2.0 * (1.0 + nu_a))
    kappa = E / (3.0 * (1.0 - 2.0 * nu_a))
    lam = E * nu_a / ((1.0 + nu_a) * (1.0 - 2.0 * nu_a))
    if model != "neo_hookean_fiber":
        eta = np.zeros(M)
    return MaterialParams(model, mu, kappa, lam, eta, fib / norm[:, None], tension_only)


def _check_F(F, params, dims=(2, 3)) -> np.ndarray:
    """``F`` as float64, checked to be (M, d, d) with d in ``dims`` and M matching ``params``.

    2-D F also needs a 2-component fiber in ``params``.
    """
    F = np.asarray(F, dtype=np.float64)
    if F.ndim != 3 or F.shape[1] != F.shape[2] or F.shape[1] not in dims:
        shapes = " or ".join(f"(M, {d}, {d})" for d in dims)
        raise ValueError(f"F must have shape {shapes}, got {F.shape}")
    if F.shape[0] != params.mu.shape[0]:
        raise ValueError(f"F has {F.shape[0]} elements but params has {params.mu.shape[0]}")
    if F.shape[1] == 2 and params.fiber.shape[1] != 2:
        raise ValueError(
            "2-D (plane-strain) F needs (M, 2) fibers, params has fibers of shape "
            f"{params.fiber.shape}"
        )
    return F

