"""Full 3-D kernels: Ψ, P and the tangent for ``F`` of shape (M, 3, 3) (docs/model.md §3).

Called through :func:`scissor_cli.mechanics.materials.evaluate` (and the
other public kernels) for ``F`` of shape ``(M, 3, 3)``; used by 3-D
tetrahedral (P1) elements. Definitions: ``J = det F``, ``I1 = tr(FᵀF)``,
``Ī1 = J^(-2/3) I1``, ``I4 = a0ᵀ FᵀF a0`` with the unit reference fiber
``a0`` (M, 3); a 2-component fiber ``a0`` is read as ``(a0, 0)`` (the
fiber of a layer, ``(cos θ, sin θ, 0)``). ``vec(F) = F.reshape(M, 9)``
(row-major: entry ``3 i + j`` is ``F_ij``); P is (M, 3, 3) and the
tangent (M, 9, 9), both in kPa; Ψ in kPa = µJ/mm³.

Closed forms (``f = vec F``, ``c = vec cof F``, ``cof F = J F^(-T)``
whose rows are ``F_1 × F_2, F_2 × F_0, F_0 × F_1`` for the rows ``F_i`` of
F, ``g = J^(-2/3)``)::

    P   = μ g F + s cof F,            s = κ (J − 1) − μ g I1 / (3 J)
    d²Ψ = μ g I + s H − (2/3)(μ g/J)(f cᵀ + c fᵀ) + (κ + (5/9) μ g I1/J²) c cᵀ
    H = d²J/df²,   H[3i+j, 3k+l] = ε_ikm ε_jln F_mn   (linear in F)
    fiber, v = F a0, t = 2η (I4 − 1):
    P  += t v a0ᵀ,   d²Ψ += t kron(I3, a0 a0ᵀ) + 4η w wᵀ,  w = vec(v a0ᵀ)
    linear, ε = sym(F − I):
    P = 2μ ε + λ tr(ε) I,   d²Ψ[3i+j, 3k+l] = μ (δ_ik δ_jl + δ_il δ_jk) + λ δ_ij δ_kl

These are the 2-D plane-strain formulas with the 3-D cofactor; for
``F = diag(F2, 1)`` both give the same Ψ, the in-plane block of P and
the in-plane 4x4 block of the tangent. Everything is vectorised over the
elements with stacked arrays; every tangent is exactly symmetric (both
entries of a symmetric pair are computed by the same operations).

Inverted elements follow the 2-D policy: ``psi = +inf`` where ``J <= 0``
(or where the arithmetic overflows or F holds NaN), P and C computed with
J clipped to ``J_FLOOR`` in the singular factors.

:func:`_evaluate_projected_solid` projects the whole tangent with a batched
``eigh``, not per energy term as the 2-D closed forms do: it returns
``proj(C_iso + C_fiber)``, the PSD matrix nearest to C (Frobenius norm),
rather than ``proj(C_iso) + proj(C_fiber)``. The two coincide for
``"neo_hookean"`` (one term) and wherever every term is PSD.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.mechanics.materials.params import J_FLOOR
from scissor_cli.mechanics.materials.psd import _project_psd_scaled

_LEVI = np.zeros((3, 3, 3))
_LEVI[0, 1, 2] = _LEVI[1, 2, 0] = _LEVI[2, 0, 1] = 1.0
_LEVI[0, 2, 1] = _LEVI[2, 1, 0] = _LEVI[1, 0, 2] = -1.0

#: ``d²J/dvec(F)²`` is linear in F: ``(F.reshape(M, 9) @ _HESS_DET).reshape(M, 9, 9)``.
_HESS_DET = np.einsum("ikm,jln->mnijkl", _LEVI, _LEVI).reshape(9, 81)

_I3 = np.eye(3)
#: Linear-model tangent pieces: ``C = μ _LIN_MU + λ _LIN_LAM`` (9, 9).
_LIN_MU = (np.einsum("ik,jl->ijkl", _I3, _I3) + np.einsum("il,jk->ijkl", _I3, _I3)).reshape(9, 9)
_LIN_LAM = np.einsum("ij,kl->ijkl", _I3, _I3).reshape(9, 9)
_DIAG9 = np.arange(9)


def _cross(a, b) -> np.ndarray:
    """Row-wise cross product of two (M, 3) stacks."""
    return np.stack([
        a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
        a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
        a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
    ], axis=-1)


def _det(F, cof0) -> np.ndarray:
    """``J = F_0 · (F_1 × F_2)`` from the first cofactor row ``cof0`` (M, 3)."""
    return F[:, 0, 0] * cof0[:, 0] + F[:, 0, 1] * cof0[:, 1] + F[:, 0, 2] * cof0[:, 2]


def jacobian_det_3d(F) -> np.ndarray:
    """``J = det F`` for F (M, 3, 3); exactly the J that :func:`_eval_solid` uses."""
    return _det(F, _cross(F[:, 1], F[:, 2]))


def _fiber3(params) -> np.ndarray:
    """The (M, 3) fibers; 2-component fibers get a zero z component."""
    a = params.fiber
    if a.shape[1] == 2:
        a = np.concatenate([a, np.zeros((a.shape[0], 1))], axis=1)
    return a


def _eval_solid(F, params, order):
    """Ψ (M,), P (M, 3, 3) and C (M, 9, 9) for 3-D F; see the module docstring.

    ``F`` is a checked float64 (M, 3, 3) array; the caller silences
    floating-point warnings. P is None for ``order < 1``, C for ``order < 2``.
    The result of each row depends only on that row (not on the memory
    layout of F or on the other rows).
    """
    # einsum's summation order follows the strides: one C-contiguous copy
    # makes the results independent of the caller's layout.
    F = np.ascontiguousarray(F)
    if params.model == "linear":
        return _eval_linear_3d(F, params, order)
    M = F.shape[0]
    fiber = params.model == "neo_hookean_fiber"
    mu, kappa = params.mu, params.kappa
    cof = np.stack([_cross(F[:, 1], F[:, 2]), _cross(F[:, 2], F[:, 0]), _cross(F[:, 0], F[:, 1])], axis=1)
    J = _det(F, cof[:, 0])
    I1 = np.einsum("eij,eij->e", F, F)
    Jc = np.maximum(J, J_FLOOR)
    alpha = mu * np.exp(-2.0 / 3.0 * np.log(Jc))  # μ J^(-2/3)
    iJ = 1.0 / Jc
    psi = 0.5 * (alpha * I1 - 3.0 * mu + kappa * (J - 1.0) ** 2)
    if fiber:
        a = _fiber3(params)
        v = np.einsum("eij,ej->ei", F, a)  # F a0
        I4m1 = np.einsum("ei,ei->e", v, v) - 1.0
        eta = params.eta * (I4m1 > 0.0) if params.tension_only else params.eta
        psi += 0.5 * eta * I4m1 * I4m1
    psi[~(J > 0.0)] = np.inf
    psi[np.isnan(psi)] = np.inf  # overflow (|F| ~ 1e154) gives inf·0
    if order == 0:
        return psi, None, None

    s = kappa * (J - 1.0) - alpha * I1 * iJ / 3.0
    P = alpha[:, None, None] * F + s[:, None, None] * cof
    if fiber:
        t = 2.0 * eta * I4m1
        P += t[:, None, None] * v[:, :, None] * a[:, None, :]
    if order == 1:
        return psi, P, None

    beta = -2.0 / 3.0 * alpha * iJ
    gamma = kappa + 5.0 / 9.0 * alpha * I1 * iJ * iJ
    # The tangent is assembled in component-major layout H (9, 9, M), so
    # every operation runs over the elements on contiguous rows (much faster
    # than broadcasting over (M, 9, 9) with inner length 9); one transposed
    # copy gives the (M, 9, 9) result. Every term is symmetric entry by
    # entry (H[a, b] and H[b, a] get the same operations), so C is exactly
    # symmetric.
    fT = np.ascontiguousarray(F.reshape(M, 9).T)  # vec F, (9, M)
    cT = np.ascontiguousarray(cof.reshape(M, 9).T)  # vec cof F
    H = fT[:, None, :] * cT[None, :, :]  # f cᵀ
    H += np.swapaxes(H, 0, 1)  # + c fᵀ (numpy buffers the overlapping operand)
    H *= beta
    tmp = cT[:, None, :] * cT[None, :, :]  # c cᵀ
    tmp *= gamma
    H += tmp
    np.matmul(_HESS_DET.T, fT, out=tmp.reshape(81, M))  # d²J/df²
    tmp *= s
    H += tmp
    H[_DIAG9, _DIAG9] += alpha
    if fiber:
        aT = np.ascontiguousarray(a.T)  # (3, M)
        wT = (v.T[:, None, :] * aT[None, :, :]).reshape(9, M)  # vec(v a0ᵀ)
        np.multiply(wT[:, None, :], wT[None, :, :], out=tmp)
        tmp *= 4.0 * eta
        H += tmp
        # t kron(I3, a0 a0ᵀ): the block t a0 a0ᵀ on the three diagonal 3x3 blocks.
        taa = t * (aT[:, None, :] * aT[None, :, :])
        H5 = H.reshape(3, 3, 3, 3, M)
        for i in range(3):
            H5[i, :, i, :] += taa
    C = np.empty((M, 9, 9))
    np.copyto(C.reshape(M, 81), H.reshape(81, M).T)
    return psi, P, C


def _eval_linear_3d(F, params, order):
    """Small-strain model in 3-D: ``Ψ = μ ε:ε + λ/2 (tr ε)²``, ``ε = sym(F − I)``."""
    mu, lam = params.mu, params.lam
    eps = 0.5 * (F + np.swapaxes(F, 1, 2)) - _I3
    tr = eps[:, 0, 0] + eps[:, 1, 1] + eps[:, 2, 2]
    psi = mu * np.einsum("eij,eij->e", eps, eps) + 0.5 * lam * tr * tr
    if order == 0:
        return psi, None, None
    P = 2.0 * mu[:, None, None] * eps + (lam * tr)[:, None, None] * _I3
    if order == 1:
        return psi, P, None
    C = (mu[:, None] * _LIN_MU.reshape(81) + lam[:, None] * _LIN_LAM.reshape(81)).reshape(-1, 9, 9)
    return psi, P, C


def _evaluate_projected_solid(F, params):
    """Ψ, P and a PSD tangent (M, 9, 9) for 3-D F; the caller silences warnings.

    ``"linear"``: the constant PSD tangent, unchanged. Nonlinear models:
    :func:`_project_psd_scaled` of the exact tangent (batched ``eigh``),
    so rows whose tangent is already PSD keep it bit for bit, every row is
    finite and PSD, and invalid rows (``psi = +inf``) get the projection of
    their clipped, meaningless tangent (0 where it is not finite).
    """
    psi, P, C = _eval_solid(F, params, 2)
    if params.model == "linear":
        return psi, P, C
    return psi, P, _project_psd_scaled(C)
