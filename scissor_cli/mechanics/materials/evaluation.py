"""The public material kernels: energy density, stress, tangent (docs/model.md §3).

Each function takes a stack of deformation gradients ``F`` of shape
``(M, d, d)`` and dispatches on d: d = 2 is plane strain
(:mod:`.plane_strain`, :mod:`.plane_strain_projection`), d = 3 full 3-D
(:mod:`.solid3d`). Tangents are ``(M, d², d²)`` in row-major ``vec(F)``
order. Units: Ψ in kPa = µJ/mm³, P and C in kPa.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.mechanics.materials.params import MaterialParams, _check_F
from scissor_cli.mechanics.materials.plane_strain import _eval_linear, _eval_neo_hookean
from scissor_cli.mechanics.materials.plane_strain_projection import _evaluate_projected
from scissor_cli.mechanics.materials.solid3d import (
    _eval_solid,
    _evaluate_projected_solid,
    jacobian_det_3d,
)


def jacobian_det(F) -> np.ndarray:
    """``J = det F`` for a stack ``F`` of shape (M, 2, 2) or (M, 3, 3); returns (M,).

    The same J (bit for bit) that :func:`evaluate` uses for its
    ``J <= 0`` test.
    """
    F = np.asarray(F, dtype=np.float64)
    if F.ndim == 3 and F.shape[1:] == (3, 3):
        with np.errstate(all="ignore"):
            return jacobian_det_3d(F)
    return F[:, 0, 0] * F[:, 1, 1] - F[:, 0, 1] * F[:, 1, 0]


def energy_density(F, params: MaterialParams) -> np.ndarray:
    """Strain-energy density Ψ(F), shape (M,), kPa (= µJ/mm³).

    ``+inf`` where ``J <= 0`` for the nonlinear models.
    """
    return evaluate(F, params, order=0)[0]


def stress(F, params: MaterialParams) -> np.ndarray:
    """First Piola–Kirchhoff stress ``P = dΨ/dF``, shape (M, d, d) like F, kPa."""
    return evaluate(F, params, order=1)[1]


def tangent(F, params: MaterialParams) -> np.ndarray:
    """Tangent ``d²Ψ/dvec(F)²``, shape (M, d², d²), kPa; symmetric, not PSD-projected."""
    return evaluate(F, params, order=2)[2]


def evaluate(F, params: MaterialParams, order: int = 2):
    """Energy density, stress and tangent, sharing intermediate work.

    Parameters
    ----------
    F : (M, d, d) array, d = 2 (plane strain) or 3
        Deformation gradients, ``F[e, i, j] = dx_i/dX_j``.
    params : MaterialParams
        With ``params.n_elements == M``; 2-D needs (M, 2) fibers, 3-D takes
        (M, 3) fibers or in-plane (M, 2) ones.
    order : {0, 1, 2}
        0: energy only; 1: energy and stress; 2: all three.

    Returns
    -------
    psi : (M,) kPa = µJ/mm³ (+inf where J <= 0, nonlinear models)
    P : (M, d, d) kPa, or None if ``order < 1``
    C : (M, d², d²) kPa, row-major ``vec(F)`` order, C-contiguous, or None
        if ``order < 2``

    The returned arrays are new (never views of internal scratch memory).
    See docs/model.md §3 for the models and their closed forms.
    """
    F = _check_F(F, params)
    if order not in (0, 1, 2):
        raise ValueError(f"order must be 0, 1 or 2, got {order!r}")
    # Overflow for absurd F (|F| ~ 1e154) must not warn; it yields inf/NaN rows
    # that the callers' J and finiteness checks reject.
    with np.errstate(all="ignore"):
        if F.shape[1] == 3:
            return _eval_solid(F, params, order)
        if params.model == "linear":
            return _eval_linear(F, params, order)
        return _eval_neo_hookean(F, params, order)


def evaluate_projected(F, params: MaterialParams):
    """Energy density, stress and a PSD-projected tangent in one pass.

    ``F`` is (M, d, d) with d = 2 or 3, as for :func:`evaluate`. Returns
    ``(psi, P, C_proj)``: ``psi`` (M,) and ``P`` (M, d, d) are bit-for-bit
    those of ``evaluate(F, params, 2)``; ``C_proj`` (M, d², d²), kPa, is
    symmetric positive semidefinite, a new C-contiguous array, meant for
    Newton's method. No Python loop over elements in either dimension.

    * ``"linear"``: C is constant and PSD; ``evaluate(F, params, 2)`` is
      returned unchanged.
    * d = 2, nonlinear models: each energy term (isotropic, fiber) is
      projected separately with closed-form eigensystems, ``C_proj =
      proj(C_iso) + proj(C_fiber)`` (see :mod:`.plane_strain_projection`),
      much cheaper than ``project_psd(evaluate(F, params, 2)[2])`` (no
      eigendecomposition). Wherever every term is already PSD, ``C_proj`` is
      ``C`` bit-for-bit.
    * d = 3, nonlinear models: the whole tangent is projected with a batched
      symmetric eigendecomposition (negative eigenvalues clamped to 0);
      where ``C`` is already PSD ``C_proj`` is ``C`` bit-for-bit (up to
      eigenvalues of order round-off below 0, which are clamped). Unlike
      d = 2 this is ``proj(C_iso + C_fiber)``, not ``proj(C_iso) +
      proj(C_fiber)``; the two coincide for ``"neo_hookean"`` and wherever
      every term is PSD. Cost: one batched 9x9 ``eigh`` per call.

    Invalid rows (psi = +inf: ``J <= 0``, overflow, NaN in F), rows with
    ``0 < J <= J_FLOOR`` and rows whose closed forms overflow get
    :func:`project_psd` of their (clipped, meaningless) tangent from
    :func:`evaluate`, or 0 where that is not finite; so ``C_proj`` is finite
    and PSD in every row and no floating-point warning is emitted. Callers
    must still check ``jacobian_det(F) > 0`` / ``np.isinf(psi)`` as for
    :func:`evaluate`.
    """
    F = _check_F(F, params)
    if F.shape[1] == 3:
        with np.errstate(all="ignore"):
            return _evaluate_projected_solid(F, params)
    return _evaluate_projected(F, params, clamp=True)
