"""Compiled (numba) element loops of the 3-D slab: energy, gradient and stiffness (exact or PSD-projected) in one pass
(docs/model.md §3, §13).

The 3-D twin of `mechanics.compiled`: the same closed forms as
`materials.solid3d` (Ψ, P, the exact tangent d²Ψ/dF²) evaluated per
tetrahedron with every intermediate in registers, then the packed 12x12
element matrix (78, M) in `fem.element_matrices`' order. numpy builds the
same numbers from whole-array passes over (9, 9, M) stacks, several times
slower (benchmarks/bench_slab_truth.py).

The PSD-projected tangent is projected per tetrahedron inside the loop
(`project_matrix`: the numpy path's rule, `materials.psd._project_psd_scaled`,
without its (M, 9, 9) stacks). As in 2-D, a loop hands the
first element it cannot take (J ≤ J_FLOOR, a non-finite term) back to the
caller, which then uses the numpy path and its policy for such elements.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from scissor_cli import runtime
from scissor_cli.mechanics.materials.params import J_FLOOR

_JIT = dict(cache=True, nogil=True, error_model="numpy")


def _det_hessian_table() -> tuple[np.ndarray, np.ndarray]:
    """d²J/dF_ij dF_pq = Σ_mn ε_ipm ε_jqn F_mn: for each (3i+j, 3p+q) the one index 3m+n (or -1) and its sign."""
    levi = np.zeros((3, 3, 3))
    levi[0, 1, 2] = levi[1, 2, 0] = levi[2, 0, 1] = 1.0
    levi[0, 2, 1] = levi[2, 1, 0] = levi[1, 0, 2] = -1.0
    index = -np.ones((9, 9), np.int64)
    sign = np.zeros((9, 9))
    for i in range(3):
        for j in range(3):
            for p in range(3):
                for q in range(3):
                    for m in range(3):
                        for n in range(3):
                            v = levi[i, p, m] * levi[j, q, n]
                            if v != 0.0:
                                index[3 * i + j, 3 * p + q], sign[3 * i + j, 3 * p + q] = 3 * m + n, v
    return index, sign


_HD_INDEX, _HD_SIGN = _det_hessian_table()
#: (index, sign) (9, 9): ∂²J/∂F² as a table on vec F (`nodal.det_hessian` reads it too)
DET_HESSIAN = (_HD_INDEX, _HD_SIGN)


@njit(**_JIT)
def _deformation(x, corners, grad_rows, e, f):
    """vec F (9,) of tetrahedron e into f, row-major, from positions x (N, 3) (`fem.deformation_gradients`' sums)."""
    for i in range(3):
        x0, x1, x2, x3 = x[corners[0, e], i], x[corners[1, e], i], x[corners[2, e], i], x[corners[3, e], i]
        for j in range(3):
            f[3 * i + j] = x0 * grad_rows[0, j, e] + x1 * grad_rows[1, j, e] + x2 * grad_rows[2, j, e] \
                + x3 * grad_rows[3, j, e]


@njit(**_JIT)
def _cofactor(f, c):
    """cof F = det(F) F⁻ᵀ as a vec (9,) into c, from vec F f (9,), both row-major; returns det F."""
    c[0] = f[4] * f[8] - f[5] * f[7]
    c[1] = f[5] * f[6] - f[3] * f[8]
    c[2] = f[3] * f[7] - f[4] * f[6]
    c[3] = f[7] * f[2] - f[8] * f[1]
    c[4] = f[8] * f[0] - f[6] * f[2]
    c[5] = f[6] * f[1] - f[7] * f[0]
    c[6] = f[1] * f[5] - f[2] * f[4]
    c[7] = f[2] * f[3] - f[0] * f[5]
    c[8] = f[0] * f[4] - f[1] * f[3]
    return f[0] * c[0] + f[1] * c[1] + f[2] * c[2]


@njit(**_JIT)
def _stress(f, c, a, mu, kappa, eta, tension_only, P):
    """Ψ (kPa) and P (9,) into P; the cofactor vec (9,) into c; returns (Ψ, J, α, s, 1/J, I4−1, η_eff, v0, v1, v2)."""
    J = _cofactor(f, c)
    I1 = 0.0
    for p in range(9):
        I1 += f[p] * f[p]
    Jc = max(J, J_FLOOR)
    alpha = mu * math.exp(-2.0 / 3.0 * math.log(Jc))
    iJ = 1.0 / Jc
    psi = 0.5 * (alpha * I1 - 3.0 * mu + kappa * (J - 1.0) ** 2)
    s = kappa * (J - 1.0) - alpha * I1 * iJ / 3.0
    for p in range(9):
        P[p] = alpha * f[p] + s * c[p]
    v0 = f[0] * a[0] + f[1] * a[1] + f[2] * a[2]
    v1 = f[3] * a[0] + f[4] * a[1] + f[5] * a[2]
    v2 = f[6] * a[0] + f[7] * a[1] + f[8] * a[2]
    I4m1 = v0 * v0 + v1 * v1 + v2 * v2 - 1.0
    eta_eff = eta * (I4m1 > 0.0) if tension_only else eta
    if eta_eff != 0.0:
        psi += 0.5 * eta_eff * I4m1 * I4m1
        t = 2.0 * eta_eff * I4m1
        for j in range(3):
            P[j] += t * v0 * a[j]
            P[3 + j] += t * v1 * a[j]
            P[6 + j] += t * v2 * a[j]
    return psi, J, alpha, s, iJ, I4m1, eta_eff, v0, v1, v2


@njit(**_JIT)
def _takes(psi, P, J):
    """Whether a term at J = det F with energy density psi (kPa) and stress P (9,) is one the loops take: J >
    J_FLOOR and every value finite (else the caller's numpy path and its policy answer)."""
    finite = psi
    for p in range(9):
        finite += P[p]
    return J > J_FLOOR and math.isfinite(finite)


@njit(**_JIT)
def jacobians_3d(x, corners, grad_rows):
    """J = det F (M,) of every tetrahedron at positions x (N, 3) (`Tissue.jacobians`): numpy's J, F₀ · (F₁ × F₂)."""
    J = np.empty(corners.shape[1])
    f = np.empty(9)
    for e in range(corners.shape[1]):
        _deformation(x, corners, grad_rows, e, f)
        J[e] = f[0] * (f[4] * f[8] - f[5] * f[7]) + f[1] * (f[5] * f[6] - f[3] * f[8]) \
            + f[2] * (f[3] * f[7] - f[4] * f[6])
    return J


@njit(**_JIT)
def feasibility_cubic_3d(x, dx, corners, grad_rows):
    """b, c, d and Fujiwara's root bound (each (M,)) of det(F + α dF) = J (1 + b α + c α² + d α³) for positions
    x and a direction dx (N, 3) (`fem.max_feasible_step_3d`'s coefficients and bound, in one pass without the
    (M, 3, 3) stacks of F and dF); J > 0 is the caller's to ensure."""
    M = corners.shape[1]
    b, c, d, bound = np.empty(M), np.empty(M), np.empty(M), np.empty(M)
    f, g, cf, cg = np.empty(9), np.empty(9), np.empty(9), np.empty(9)
    for e in range(M):
        _deformation(x, corners, grad_rows, e, f)
        _deformation(dx, corners, grad_rows, e, g)
        J = _cofactor(f, cf)
        det_g = _cofactor(g, cg)
        sb, sc = 0.0, 0.0
        for p in range(9):
            sb += cf[p] * g[p]
            sc += f[p] * cg[p]
        b[e], c[e], d[e] = sb / J, sc / J, det_g / J
        if not (math.isfinite(b[e]) and math.isfinite(c[e]) and math.isfinite(d[e])):
            bound[e] = np.inf  # non-finite coefficients: always solved
        elif b[e] >= 0.0 and c[e] >= 0.0 and d[e] >= 0.0:
            bound[e] = 0.0  # Descartes: no positive root
        else:
            bound[e] = 2.0 * max(max(abs(b[e]), math.sqrt(abs(c[e]))), np.cbrt(abs(0.5 * d[e])))
    return b, c, d, bound


@njit(**_JIT)
def energy_gradient_3d(x, corners, grad_rows, volume, material, tension_only, out, e0, e1):
    """U (µJ) and ∇U of elements e0 ≤ e < e1 written into out (3N,) mN; returns (U, -1), or (nan, e) for the first
    element e it cannot take.

    material: (μ, κ, η (M,) kPa, the unit fiber (M, 3)) per element (`_material`).
    """
    mu, kappa, eta, fiber = material
    out[:] = 0.0
    U = 0.0
    f, c, P, a = np.empty(9), np.empty(9), np.empty(9), np.empty(3)
    for e in range(e0, e1):
        _deformation(x, corners, grad_rows, e, f)
        a[0], a[1], a[2] = fiber[e, 0], fiber[e, 1], fiber[e, 2]
        psi, J = _stress(f, c, a, mu[e], kappa[e], eta[e], tension_only, P)[:2]
        if not _takes(psi, P, J):
            return math.nan, e
        U += psi * volume[e]
        _add_forces(out, P, volume[e], corners, grad_rows, e)
    return U, -1


@njit(**_JIT)
def _add_forces(out, P, V, corners, grad_rows, e):
    """out[3n+i] += V Σ_j P_ij ∂N_n/∂X_j over the four nodes n of tetrahedron e (`fem.element_forces`)."""
    for n in range(4):
        node = corners[n, e]
        g0, g1, g2 = grad_rows[n, 0, e], grad_rows[n, 1, e], grad_rows[n, 2, e]
        for i in range(3):
            out[3 * node + i] += V * (P[3 * i] * g0 + P[3 * i + 1] * g1 + P[3 * i + 2] * g2)


@njit(**_JIT)
def _tangent(C, f, c, a, J_terms, kappa, hd_index, hd_sign):
    """The exact tangent d²Ψ/dvecF² (9, 9), kPa, into C (`materials.solid3d` closed form)."""
    alpha, s, iJ, I1, I4m1, eta_eff, v0, v1, v2 = J_terms
    beta = -2.0 / 3.0 * alpha * iJ
    gamma = kappa + 5.0 / 9.0 * alpha * I1 * iJ * iJ
    w = np.empty(9)
    for j in range(3):
        w[j], w[3 + j], w[6 + j] = v0 * a[j], v1 * a[j], v2 * a[j]
    t = 2.0 * eta_eff * I4m1
    for p in range(9):
        for q in range(p, 9):
            val = beta * (f[p] * c[q] + c[p] * f[q]) + gamma * c[p] * c[q]
            m = hd_index[p, q]
            if m >= 0:
                val += s * hd_sign[p, q] * f[m]
            if p == q:
                val += alpha
            if eta_eff != 0.0:
                val += 4.0 * eta_eff * w[p] * w[q]
                if p // 3 == q // 3:
                    val += t * a[p % 3] * a[q % 3]
            C[p, q] = val
            C[q, p] = val


@njit(**_JIT)
def project_matrix(C, L, A):
    """C (k, k), symmetric and finite, replaced in place by its PSD projection: `materials.psd`'s rule, compiled.

    Scaled by its largest |entry| first. A matrix that a Cholesky factorisation of C/max|C| − 1e-10 I proves
    positive definite is left as it is without its eigendecomposition (most of the cost: LAPACK's per matrix);
    the others get it, and those with a negative eigenvalue are rebuilt from the clamped ones, exactly
    symmetric (0 if that overflows). L, A (k, k): scratch. The lower triangle is read, as by ``eigh``.
    """
    k = C.shape[0]
    big = 0.0
    for i in range(k):
        for j in range(k):
            big = max(big, abs(C[i, j]))
    if big == 0.0:
        return
    definite = True
    for j in range(k):
        s = C[j, j] / big - 1e-10
        for m in range(j):
            s -= L[j, m] * L[j, m]
        if not s > 0.0:
            definite = False
            break
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, k):
            t = C[i, j] / big
            for m in range(j):
                t -= L[i, m] * L[j, m]
            L[i, j] = t / L[j, j]
    if definite:
        return
    for i in range(k):
        for j in range(k):
            A[i, j] = C[max(i, j), min(i, j)] / big
    w, V = np.linalg.eigh(A)
    if w[0] >= 0.0:
        return
    finite = True
    for i in range(k):
        for j in range(i, k):
            s = 0.0
            for m in range(k):
                if w[m] > 0.0:
                    s += V[i, m] * w[m] * V[j, m]
            s *= big
            finite = finite and np.isfinite(s)
            C[i, j] = s
            C[j, i] = s
    if not finite:
        C[:, :] = 0.0


@njit(**_JIT)
def element_stiffness_3d(x, corners, grad_rows, volume, material, tension_only, hd_pattern, project, Ke, grad, e0, e1):
    """Packed Hessians of elements e0 ≤ e < e1 into Ke (78, M), mN/mm; (-1, U), or (the first element it cannot
    take, nan).

    material: as `energy_gradient_3d`'s; hd_pattern: (`_HD_INDEX`, `_HD_SIGN`). With `project` each
    tetrahedron's tangent C is PSD-projected first (`project_matrix`, the numpy path's rule).

    K_e[3a+i, 3b+k] = V Σ_jl ∂N_a/∂X_j C[3i+j, 3k+l] ∂N_b/∂X_l. With grad of
    size 3N (not 0), their ∇U goes into it and U is returned (one pass for both).
    """
    mu, kappa, eta, fiber = material
    hd_index, hd_sign = hd_pattern
    with_grad = grad.size > 0
    if with_grad:
        grad[:] = 0.0
    U = 0.0
    f, c, P, a = np.empty(9), np.empty(9), np.empty(9), np.empty(3)
    C = np.empty((9, 9))
    L, A = np.empty((9, 9)), np.empty((9, 9))
    T = np.empty((9, 4, 3))
    for e in range(e0, e1):
        _deformation(x, corners, grad_rows, e, f)
        a[0], a[1], a[2] = fiber[e, 0], fiber[e, 1], fiber[e, 2]
        psi, J, alpha, s, iJ, I4m1, eta_eff, v0, v1, v2 = _stress(f, c, a, mu[e], kappa[e], eta[e], tension_only, P)
        if not (J > J_FLOOR and math.isfinite(psi)):
            return e, math.nan
        V = volume[e]
        if with_grad:
            finite = psi
            for p in range(9):
                finite += P[p]
            if not math.isfinite(finite):
                return e, math.nan
            U += psi * V
            _add_forces(grad, P, V, corners, grad_rows, e)
        I1 = 0.0
        for p in range(9):
            I1 += f[p] * f[p]
        _tangent(C, f, c, a, (alpha, s, iJ, I1, I4m1, eta_eff, v0, v1, v2), kappa[e], hd_index, hd_sign)
        if project:
            finite = 0.0
            for p in range(9):
                for q in range(9):
                    finite += C[p, q]
            if not math.isfinite(finite):
                return e, math.nan
            project_matrix(C, L, A)
        # T[r, b, k] = Σ_l C[r, 3k+l] ∂N_b/∂X_l. Unrolled per dimension as in `compiled`: one loop generic in d
        # gave the same bits but was several times slower in 2-D (numba does not unroll a runtime d).
        for r in range(9):
            for bn in range(4):
                g0, g1, g2 = grad_rows[bn, 0, e], grad_rows[bn, 1, e], grad_rows[bn, 2, e]
                for k in range(3):
                    T[r, bn, k] = C[r, 3 * k] * g0 + C[r, 3 * k + 1] * g1 + C[r, 3 * k + 2] * g2
        n = 0
        finite = 0.0
        for p in range(12):
            an, i = p // 3, p % 3
            ga0, ga1, ga2 = grad_rows[an, 0, e] * V, grad_rows[an, 1, e] * V, grad_rows[an, 2, e] * V
            for q in range(p, 12):
                bn, k = q // 3, q % 3
                val = ga0 * T[3 * i, bn, k] + ga1 * T[3 * i + 1, bn, k] + ga2 * T[3 * i + 2, bn, k]
                Ke[n, e] = val
                finite += val
                n += 1
        if not math.isfinite(finite):
            return e, math.nan
    return -1, U


# -- the entry points: None where the numpy path must answer ---------------------------------------------------------


def supports(ops, params) -> bool:
    """Whether these loops serve this element set and material: tetrahedra, a neo-Hookean model."""
    return ops.dim == 3 and params.model != "linear"


def _material(params) -> tuple:
    """(per-element (μ, κ, η, fiber (M, 3)), tension_only) as the loops take them (an in-plane fiber as (a, b, 0))."""
    return (params.mu, params.kappa, params.eta, params._fiber3), params.tension_only


def energy_gradient(ops, params, x: np.ndarray) -> tuple[float, np.ndarray] | None:
    """U (µJ) and ∇U (3N,) mN at positions x (N, 3); None if an element has J ≤ J_FLOOR or a non-finite term.
    In `_stiffness_in_parts`'s parts: the same numbers as `energy_gradient_stiffness`'s."""
    cuts = runtime.part_bounds(ops.corners.shape[1])
    grads = np.empty((len(cuts) - 1, 3 * ops.n_nodes))
    x = np.ascontiguousarray(x, dtype=np.float64)
    common = (x, ops.corners, ops.grad_rows, ops.volume, *_material(params))
    results = runtime.in_parts(*[lambda k=k: energy_gradient_3d(*common, grads[k], cuts[k], cuts[k + 1])
                                 for k in range(len(cuts) - 1)])
    if any(bad >= 0 for _, bad in results):
        return None
    return float(sum(U for U, _ in results)), grads.sum(axis=0)


def element_stiffness(ops, params, x: np.ndarray, project: bool) -> np.ndarray | None:
    """Packed element Hessians (78, M) mN/mm at x (N, 3), exact or PSD-projected; None as above."""
    result = _stiffness_in_parts(ops, params, x, project, with_gradient=False)
    return None if result is None else result[2]


def energy_gradient_stiffness(ops, params, x: np.ndarray, project: bool) -> tuple[float, np.ndarray, np.ndarray] | None:
    """U (µJ), ∇U (3N,) mN and the packed element Hessians (78, M) at x (N, 3), in one pass; None as above."""
    return _stiffness_in_parts(ops, params, x, project, with_gradient=True)


def _stiffness_in_parts(ops, params, x, project, with_gradient):
    """`element_stiffness_3d` over runtime.MOST_THREADS equal runs of the elements (at once where the process has
    the threads: `runtime.in_parts`), each part's ∇U in its own vector and the parts' sums added in order, so the
    numbers do not depend on the threads: (U, ∇U, Ke), or None for an element it cannot take."""
    M = ops.corners.shape[1]
    cuts = runtime.part_bounds(M)
    K = len(cuts) - 1
    Ke = np.empty((78, M))
    grads = np.empty((K, 3 * ops.n_nodes if with_gradient else 0))
    x = np.ascontiguousarray(x, dtype=np.float64)
    common = (x, ops.corners, ops.grad_rows, ops.volume, *_material(params), (_HD_INDEX, _HD_SIGN), project, Ke)
    results = runtime.in_parts(*[lambda k=k: element_stiffness_3d(*common, grads[k], cuts[k], cuts[k + 1])
                                 for k in range(K)])
    if any(bad >= 0 for bad, _ in results):
        return None
    return float(sum(U for _, U in results)), grads.sum(axis=0) if with_gradient else None, Ke
