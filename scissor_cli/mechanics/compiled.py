"""Compiled (numba) element loops of the 2-D layer: energy, gradient and stiffness in one pass (docs/model.md §2–3).

The numpy kernels (`fem`, `materials`) are the reference and serve every
case; these loops are the hot path of the 2-D plane-strain neo-Hookean
models (with or without fibers), where a solver asks for the gradient or
the stiffness of the same few thousand triangles thousands of times. numpy
spends most of such a call in the overhead of about a hundred whole-array
operations; one compiled loop over the elements reads each triangle once
and keeps every intermediate in registers (docs/performance.md has the
measurements).

The closed forms are those of `materials.plane_strain` (Ψ, P, the tangent)
and `materials.plane_strain_projection` (the per-term PSD projection),
term for term in the same order, so results equal the numpy path to
round-off (the tests compare them). Degrees of freedom, packed element
matrices (21, M) and the scatter order are those of `fem`.

Every loop reports the first element it cannot take — J ≤ J_FLOOR, or a
non-finite result — and then the caller uses the numpy path, which owns
the policy for inverted and absurd elements (`materials` docstring). So
these loops never decide what an inverted element means.

Compiled on first use and cached on disk next to this file (numba's
`cache=True`), so only the first process after an install pays the
compile time (a few seconds).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from scissor_cli.mechanics.materials.params import J_FLOOR
from scissor_cli.mechanics.materials.plane_strain_projection import _TINY

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def _deformation(x, corners, grad_rows, e):
    """F = [f0 f1; f2 f3] of element e from positions x (N, 2)."""
    i0, i1, i2 = corners[0, e], corners[1, e], corners[2, e]
    x0, x1, x2 = x[i0, 0], x[i1, 0], x[i2, 0]
    y0, y1, y2 = x[i0, 1], x[i1, 1], x[i2, 1]
    f0 = x0 * grad_rows[0, 0, e] + x1 * grad_rows[1, 0, e] + x2 * grad_rows[2, 0, e]
    f1 = x0 * grad_rows[0, 1, e] + x1 * grad_rows[1, 1, e] + x2 * grad_rows[2, 1, e]
    f2 = y0 * grad_rows[0, 0, e] + y1 * grad_rows[1, 0, e] + y2 * grad_rows[2, 0, e]
    f3 = y0 * grad_rows[0, 1, e] + y1 * grad_rows[1, 1, e] + y2 * grad_rows[2, 1, e]
    return f0, f1, f2, f3


@njit(**_JIT)
def _stress(f0, f1, f2, f3, mu, kappa, eta, a, b, tension_only):
    """Ψ (kPa), P (4 components, row-major, kPa) and the shared terms (α, s, 1/J, v0, v1, I4−1, η_eff) of one
    element."""
    J = f0 * f3 - f1 * f2
    I1 = f0 * f0 + f1 * f1 + f2 * f2 + f3 * f3 + 1.0
    iJ = 1.0 / max(J, J_FLOOR)
    alpha = math.exp(math.log(max(J, J_FLOOR)) * (-2.0 / 3.0)) * mu  # μ J^(-2/3)
    Jm1 = J - 1.0
    psi = 0.5 * (alpha * I1 - mu * 3.0 + Jm1 * Jm1 * kappa)
    s = Jm1 * kappa - alpha * I1 * iJ * (1.0 / 3.0)
    p00 = alpha * f0 + s * f3
    p01 = alpha * f1 - s * f2
    p10 = alpha * f2 - s * f1
    p11 = alpha * f3 + s * f0
    v0 = f0 * a + f1 * b
    v1 = f2 * a + f3 * b
    I4m1 = v0 * v0 + v1 * v1 - 1.0
    eta_eff = eta * (I4m1 > 0.0) if tension_only else eta
    if eta_eff != 0.0:
        psi += I4m1 * I4m1 * eta_eff * 0.5
        t = eta_eff * I4m1 * 2.0
        p00 += t * v0 * a
        p01 += t * v0 * b
        p10 += t * v1 * a
        p11 += t * v1 * b
    return psi, p00, p01, p10, p11, J, alpha, s, iJ, v0, v1, I4m1, eta_eff


@njit(**_JIT)
def energy_gradient_2d(x, corners, grad_rows, volume, material, tension_only, out):
    """U (µJ) and ∇U written into out (2N,) mN; returns (U, -1), or (nan, e) for the first element e it cannot take.

    material: (μ, κ, η (M,) kPa, the fiber's (a, b) components (M,)) per element (`_material`).
    """
    mu, kappa, eta, fa, fb = material
    out[:] = 0.0
    U = 0.0
    for e in range(corners.shape[1]):
        f0, f1, f2, f3 = _deformation(x, corners, grad_rows, e)
        psi, p00, p01, p10, p11, J, _, _, _, _, _, _, _ = _stress(
            f0, f1, f2, f3, mu[e], kappa[e], eta[e], fa[e], fb[e], tension_only)
        if not (J > J_FLOOR and math.isfinite(psi + p00 + p01 + p10 + p11)):
            return math.nan, e
        V = volume[e]
        U += psi * V
        p00 *= V
        p01 *= V
        p10 *= V
        p11 *= V
        for c in range(3):
            n = corners[c, e]
            gx, gy = grad_rows[c, 0, e], grad_rows[c, 1, e]
            out[2 * n] += p00 * gx + p01 * gy
            out[2 * n + 1] += p10 * gx + p11 * gy
    return U, -1


@njit(**_JIT)
def _fiber_block(H, c, d, v0, v1, aa, ab, bb, sign):
    """H ±= (c v vᵀ + d I) ⊗ a aᵀ on the tangent's upper triangle H (4, 4)."""
    k = (v0 * v0 * c + d) * sign
    H[0, 0] += k * aa
    H[0, 1] += k * ab
    H[1, 1] += k * bb
    k = (v1 * v1 * c + d) * sign
    H[2, 2] += k * aa
    H[2, 3] += k * ab
    H[3, 3] += k * bb
    k = v0 * v1 * c * sign
    H[0, 2] += k * aa
    H[0, 3] += k * ab
    H[1, 2] += k * ab
    H[1, 3] += k * bb


@njit(**_JIT)
def _tangent(H, F, kappa, terms, fiber, project):
    """The tangent's upper triangle into H (4, 4), kPa, PSD-projected per energy term if asked.

    F: (f0, f1, f2, f3) the deformation gradient's entries; terms: (α, s, 1/J, v0, v1, I4 − 1, η_eff) from
    `_stress`; fiber: its (a, b).
    """
    f0, f1, f2, f3 = F
    alpha, s, iJ, v0, v1, I4m1, eta_eff = terms
    a, b = fiber
    I1 = f0 * f0 + f1 * f1 + f2 * f2 + f3 * f3 + 1.0
    p03, p12 = f0 * f3, f1 * f2
    beta = alpha * iJ * (-2.0 / 3.0)
    gamma = alpha * I1 * iJ * iJ * (5.0 / 9.0) + kappa
    d = beta * p03 * 2.0 + alpha
    H[0, 0] = gamma * (f3 * f3) + d
    H[3, 3] = gamma * (f0 * f0) + d
    d = beta * p12 * (-2.0) + alpha
    H[1, 1] = gamma * (f2 * f2) + d
    H[2, 2] = gamma * (f1 * f1) + d
    u = (f1 * f3 - f0 * f2) * beta
    H[0, 1] = u - f2 * f3 * gamma
    H[2, 3] = -(f0 * f1 * gamma + u)
    w = (f2 * f3 - f0 * f1) * beta
    H[0, 2] = w - f1 * f3 * gamma
    H[1, 3] = -(f0 * f2 * gamma + w)
    H[0, 3] = gamma * p03 + ((f0 * f0 + f3 * f3) * beta + s)
    H[1, 2] = gamma * p12 - ((f1 * f1 + f2 * f2) * beta + s)
    t = eta_eff * I4m1 * 2.0
    aa, ab, bb = a * a, a * b, b * b
    if eta_eff != 0.0:
        _fiber_block(H, eta_eff * 4.0, t, v0, v1, aa, ab, bb, 1.0)
    if not project:
        return
    # Negative parts of the isotropic term's eigensystem (plane_strain_projection, same steps).
    J = p03 - p12
    T2 = f0 * f0 + f1 * f1 + f2 * f2 + f3 * f3
    E, Hr, Fh, G = (f0 + f3) * 0.5, (f2 - f1) * 0.5, (f0 - f3) * 0.5, (f2 + f1) * 0.5
    Q2, R2 = E * E + Hr * Hr, Fh * Fh + G * G
    lt, ll = min(alpha + s, 0.0), min(alpha - s, 0.0)
    m = alpha * ((T2 + 1.0) * T2 * iJ * iJ * (5.0 / 18.0) - 1.0 / 3.0) + kappa * T2 * 0.5
    h = (T2 * -4.0 + 2.0) * iJ * alpha * (1.0 / 9.0) + (J * 2.0 - 1.0) * kappa
    rad = math.sqrt(Q2 * R2 * (gamma * gamma) * 4.0 + h * h)
    l2 = m - rad
    c0 = min(l2, 0.0)
    k1 = (min(m + rad, 0.0) - c0) / max(rad * 2.0, _TINY)
    c0 -= k1 * l2
    d1 = ((m + h) * k1 + c0 - lt) * 0.5
    d2 = ((m - h) * k1 + c0 - ll) * 0.5
    lt *= 0.5
    ll *= 0.5
    iq = 1.0 / Q2
    cc, cs = E * E * iq, E * Hr * iq
    if R2 < _TINY:
        CC, CS = 0.5, 0.0
    else:
        ir = 1.0 / max(R2, _TINY)
        CC, CS = Fh * Fh * ir, Fh * G * ir
    X = d1 * cc
    Y = lt + d1 - X
    X += lt
    Z = cs * d1
    Xp = d2 * CC
    Yp = ll + d2 - Xp
    Xp += ll
    Zp = CS * d2
    t1 = -(k1 * gamma)
    eu, ev = E * Fh * t1 * 2.0, Hr * G * t1 * 2.0
    ep, eq = (E * G - Hr * Fh) * t1, (E * G + Hr * Fh) * t1
    H[0, 0] = H[0, 0] - (X + Xp) - eu
    H[3, 3] = H[3, 3] - (X + Xp) + eu
    H[1, 1] = H[1, 1] - (Y + Yp) + ev
    H[2, 2] = H[2, 2] - (Y + Yp) - ev
    H[0, 3] -= X - Xp
    H[1, 2] -= Yp - Y
    H[0, 1] = H[0, 1] - (Zp - Z) - ep
    H[2, 3] = H[2, 3] + (Zp - Z) - ep
    H[0, 2] = H[0, 2] - (Z + Zp) - eq
    H[1, 3] = H[1, 3] + (Z + Zp) - eq
    if t < 0.0:  # the fiber term is indefinite only in fiber compression
        I4 = I4m1 + 1.0
        nf1 = min(t, 0.0)
        nf2 = min(eta_eff * 4.0 * I4 + t, 0.0)
        _fiber_block(H, (nf2 - nf1) / max(I4, _TINY), nf1, v0, v1, aa, ab, bb, -1.0)


@njit(**_JIT)
def element_stiffness_2d(x, corners, grad_rows, volume, material, tension_only, project, Ke, grad):
    """Packed element Hessians into Ke (21, M), mN/mm (`fem.element_matrices` order); (-1, U), or (the first
    element it cannot take, nan).

    material: as `energy_gradient_2d`'s.

    K_e[2a+i, 2b+k] = V Σ_jl ∂N_a/∂X_j C[2i+j, 2k+l] ∂N_b/∂X_l. With grad of
    size 2N (not 0), ∇U goes into it and U is returned, as
    `energy_gradient_2d` computes them (the same sums in the same order):
    the tangent predictor needs both at one x, and the stress is at hand.
    """
    mu, kappa, eta, fa, fb = material
    with_grad = grad.size > 0
    if with_grad:
        grad[:] = 0.0
    U = 0.0
    H = np.zeros((4, 4))
    T = np.empty((4, 3, 2))
    for e in range(corners.shape[1]):
        f0, f1, f2, f3 = _deformation(x, corners, grad_rows, e)
        psi, p00, p01, p10, p11, J, alpha, s, iJ, v0, v1, I4m1, eta_eff = _stress(
            f0, f1, f2, f3, mu[e], kappa[e], eta[e], fa[e], fb[e], tension_only)
        if not (J > J_FLOOR and math.isfinite(psi)):
            return e, math.nan
        if with_grad:
            if not math.isfinite(psi + p00 + p01 + p10 + p11):
                return e, math.nan
            V = volume[e]
            U += psi * V
            for c in range(3):
                nc = corners[c, e]
                gx, gy = grad_rows[c, 0, e], grad_rows[c, 1, e]
                grad[2 * nc] += p00 * V * gx + p01 * V * gy
                grad[2 * nc + 1] += p10 * V * gx + p11 * V * gy
        _tangent(H, (f0, f1, f2, f3), kappa[e], (alpha, s, iJ, v0, v1, I4m1, eta_eff), (fa[e], fb[e]), project)
        for r in range(4):  # mirror the upper triangle
            for c in range(r):
                H[r, c] = H[c, r]
        # T[r, b, k] = Σ_l C[r, 2k+l] ∂N_b/∂X_l
        for r in range(4):
            for bn in range(3):
                g0, g1 = grad_rows[bn, 0, e], grad_rows[bn, 1, e]
                T[r, bn, 0] = H[r, 0] * g0 + H[r, 1] * g1
                T[r, bn, 1] = H[r, 2] * g0 + H[r, 3] * g1
        V = volume[e]
        n = 0
        finite = 0.0
        for p in range(6):
            an, i = p // 2, p % 2
            ga0, ga1 = grad_rows[an, 0, e] * V, grad_rows[an, 1, e] * V
            for q in range(p, 6):
                bn, k = q // 2, q % 2
                val = ga0 * T[2 * i, bn, k] + ga1 * T[2 * i + 1, bn, k]
                Ke[n, e] = val
                finite += val
                n += 1
        if not math.isfinite(finite):
            return e, math.nan
    return -1, U


@njit(**_JIT)
def scatter_packed(Ke, entries, slot, out, entry_range, data_range):
    """out[slot[k]] += Ke.flat[entries[k]] for k in entry_range (k0, k1) (`fem.SparsePattern.assemble`), out's
    data_range (d0, d1), where those land, zeroed first.

    Over every run, the same sums in the same order as np.bincount(slot,
    Ke.flat[entries]), without its gathered copy of the entries.
    """
    out[data_range[0]:data_range[1]] = 0.0
    flat = Ke.ravel()
    for k in range(entry_range[0], entry_range[1]):
        out[slot[k]] += flat[entries[k]]


@njit(**_JIT)
def csr_pattern(rows, cols, size):
    """The CSR pattern of entries (rows, cols) (E,) on a (size, size) matrix (`fem.sparse_pattern`).

    Returns indptr (size+1,), indices (nnz,) int32 (sorted in each row) and
    slot (E,): the position of each entry's (row, col) in indices — what
    np.unique of the keys row·size + col with return_inverse gives, from two
    stable counting sorts (by column, then by row) instead of a sort of every key.
    """
    n = rows.shape[0]
    by_col = _counting_order(cols, np.arange(n), size)
    order = _counting_order(rows, by_col, size)
    indptr = np.zeros(size + 1, np.int64)
    indices = np.empty(n, np.int32)
    slot = np.empty(n, np.int64)
    nnz, last_row, last_col = 0, -1, -1
    for t in range(n):
        k = order[t]
        r, c = rows[k], cols[k]
        if r != last_row or c != last_col:
            indices[nnz] = c
            nnz += 1
            indptr[r + 1] = nnz
            last_row, last_col = r, c
        slot[k] = nnz - 1
    for r in range(size):  # rows without entries end where the row before them ends
        indptr[r + 1] = max(indptr[r + 1], indptr[r])
    return indptr, indices[:nnz].copy(), slot


@njit(**_JIT)
def _counting_order(key, within, size):
    """`within` (E,) (entry indices) reordered stably by key[entry] in [0, size)."""
    start = np.zeros(size + 1, np.int64)
    for t in range(within.shape[0]):
        start[key[within[t]] + 1] += 1
    for i in range(size):
        start[i + 1] += start[i]
    out = np.empty(within.shape[0], np.int64)
    for t in range(within.shape[0]):
        k = within[t]
        out[start[key[k]]] = k
        start[key[k]] += 1
    return out


@njit(**_JIT)
def jacobians_2d(x, corners, grad_rows):
    """J = det F (M,) of every element at positions x (N, 2) (`Tissue.jacobians`), bit for bit numpy's."""
    J = np.empty(corners.shape[1])
    for e in range(corners.shape[1]):
        f0, f1, f2, f3 = _deformation(x, corners, grad_rows, e)
        J[e] = f0 * f3 - f1 * f2
    return J


@njit(**_JIT)
def packed_times(Ke, corners, v, out):
    """out = Σ_e K_e v_e (dN,) for packed element matrices Ke (P, M) and v (dN,) (`fem.packed_times`), out zeroed
    first; d = corners.shape[0] − 1 (2: triangles, P = 21; 3: tetrahedra, P = 78).

    One pass over the elements instead of numpy's whole-array products and
    a bincount (the tangent predictor's K_fd δ_d, benchmarks/bench_forward.py;
    the needle loop's held response, benchmarks/bench_body_insertion.py).
    """
    d = corners.shape[0] - 1
    n_dof = d * (d + 1)
    out[:] = 0.0
    n = 0
    # pair by pair, each over all elements: Ke's rows are read in order (element by element, a tetrahedron's 78
    # entries lie M apart and the pass ran slower than numpy's)
    for p in range(n_dof):
        node_p, comp_p = p // d, p % d
        for q in range(p, n_dof):
            node_q, comp_q = q // d, q % d
            for e in range(corners.shape[1]):
                dp = d * corners[node_p, e] + comp_p
                dq = d * corners[node_q, e] + comp_q
                k = Ke[n, e]
                out[dp] += k * v[dq]
                if q != p:
                    out[dq] += k * v[dp]
            n += 1


@njit(**_JIT)
def max_feasible_step_2d(x, dx, corners, grad_rows):
    """The largest α ≥ 0 (inf if unbounded) keeping every det(F + α dF) > 0, x and dx (N, 2)
    (`Tissue.max_feasible_step`).

    det(F + α dF) = J + α b + α² a per element, its first positive root in
    the cancellation-free form.
    """
    best = math.inf
    for e in range(corners.shape[1]):
        f0, f1, f2, f3 = _deformation(x, corners, grad_rows, e)
        g0, g1, g2, g3 = _deformation(dx, corners, grad_rows, e)
        c = f0 * f3 - f1 * f2
        b = f0 * g3 + g0 * f3 - f1 * g2 - g1 * f2
        a = g0 * g3 - g1 * g2
        if abs(a) <= 1e-14 * (abs(b) + abs(c)):
            r = -c / b
            if r > 0.0 and r < best:
                best = r
            continue
        disc = b * b - 4.0 * a * c
        if not disc >= 0.0:
            continue
        q = -0.5 * (b + math.copysign(math.sqrt(disc), b))
        for r in (q / a, c / q):
            if r > 0.0 and r < best:
                best = r
    return best


# -- the entry points: None where the numpy path must answer ---------------------------------------------------------


def supports(ops, params) -> bool:
    """Whether these loops serve this element set and material: 2-D, a neo-Hookean model, in-plane fibers."""
    return ops.dim == 2 and params.model != "linear" and params._fib is not None


def _material(params) -> tuple:
    """(per-element (μ, κ, η, a, b), tension_only) as the loops take them."""
    a, b = params._fib[:2]
    return (params.mu, params.kappa, params.eta, a, b), params.tension_only


def energy_gradient(ops, params, x: np.ndarray) -> tuple[float, np.ndarray] | None:
    """U (µJ) and ∇U (2N,) mN at positions x (N, 2); None if an element has J ≤ J_FLOOR or a non-finite term."""
    grad = np.empty(2 * ops.n_nodes)
    U, bad = energy_gradient_2d(np.ascontiguousarray(x, dtype=np.float64), ops.corners, ops.grad_rows, ops.volume,
                                *_material(params), grad)
    return None if bad >= 0 else (float(U), grad)


def element_stiffness(ops, params, x: np.ndarray, project: bool) -> np.ndarray | None:
    """Packed element Hessians (21, M) mN/mm at x (N, 2), per-term PSD-projected if asked; None as above."""
    Ke = np.empty((21, ops.corners.shape[1]))
    bad, _ = element_stiffness_2d(np.ascontiguousarray(x, dtype=np.float64), ops.corners, ops.grad_rows, ops.volume,
                                  *_material(params), bool(project), Ke, np.empty(0))
    return None if bad >= 0 else Ke


def energy_gradient_stiffness(ops, params, x: np.ndarray, project: bool) -> tuple[float, np.ndarray, np.ndarray] | None:
    """U (µJ), ∇U (2N,) mN and the packed element Hessians (21, M) mN/mm at x (N, 2), in one pass; None as above.

    The same numbers as `energy_gradient` and `element_stiffness`, for one
    pass over the elements instead of two.
    """
    Ke = np.empty((21, ops.corners.shape[1]))
    grad = np.empty(2 * ops.n_nodes)
    bad, U = element_stiffness_2d(np.ascontiguousarray(x, dtype=np.float64), ops.corners, ops.grad_rows, ops.volume,
                                  *_material(params), bool(project), Ke, grad)
    return None if bad >= 0 else (float(U), grad, Ke)
