"""Compiled (numba) loops of the nodal element (`mechanics.nodal`, docs/model.md §21).

The nodal element's state, gradient and tangent touch every element and
every node at each Newton step. Each is one loop over the elements or the
nodes here, in both dimensions (d = F.shape[1]), instead of whole-array
numpy temporaries (F's cofactors, determinants, einsum, bincount): the
same sums in the same order as those where the order was defined (the
scatters: bit for bit), otherwise equal to round-off. The 3-D gradient,
which the needle's chord steps and every line search ask for most, is
fused into three passes over the mesh in `mechanics.nodal_gradient`.

The nodes' material Ψ_dev(F̄_a) reuses the element loops' closed forms:
`compiled._stress` / `_tangent` (2-D, the tangent projected per energy
term as there) and `compiled3d._stress` / `_tangent` / `project_matrix`
(3-D). As those loops do, `averaged_material` hands a node it cannot take
(J̄ ≤ J_FLOOR, a non-finite term) back to the caller, whose numpy path owns
the policy for inverted and absurd deformations. numba's on-disk cache
keys on this file alone: after editing those closed forms (or J_FLOOR),
touch this file too, or its cached loops keep the old ones.

Arrays: F (M, d, d) or F̄ (N, d, d); corners (d+1, M) and grad_rows
(d+1, d, M) as in `fem.FEOperators`; B (N, dN) in CSR (indptr, indices,
data) with `nodal.NodalVolume`'s pattern.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from scissor_cli.mechanics import compiled, compiled3d
from scissor_cli.mechanics.materials.params import J_FLOOR

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def _cofactor(F, e, c):
    """cof F_e = det(F_e) F_e⁻ᵀ (d, d) into c; returns det F_e, expanded along the first row (finite for singular
    F_e)."""
    if F.shape[1] == 2:
        c[0, 0], c[0, 1] = F[e, 1, 1], -F[e, 1, 0]
        c[1, 0], c[1, 1] = -F[e, 0, 1], F[e, 0, 0]
        return F[e, 0, 0] * F[e, 1, 1] - F[e, 0, 1] * F[e, 1, 0]
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            c[i, j] = F[e, i1, j1] * F[e, i2, j2] - F[e, i1, j2] * F[e, i2, j1]
    return F[e, 0, 0] * c[0, 0] + F[e, 0, 1] * c[0, 1] + F[e, 0, 2] * c[0, 2]


@njit(**_JIT)
def nodal_state(F, corners, grad_rows, volume, rest_volume, kappa, linear, J, pressure, element_pressure, dv):
    """The nodal state at deformation gradients F (M, d, d) into J (N,), pressure (N,) kPa, element_pressure (M,)
    kPa and dv (M, d+1, d) mm² (all overwritten).

    v_e = V_e det F_e and ∂v_e/∂x_b = V_e cof(F_e) ∇N_b, or with `linear`
    V_e (1 + tr(F_e − I)) and V_e ∇N_b; J_a = Σ_{e∋a} v_e / ((d+1) V_a)
    summed element by element (bincount's order), p_a = κ_a (J_a − 1),
    p̄_e the mean of its corners' p_a. volume (M,), rest_volume (N,) mm³
    (times h in 2-D), kappa (N,) kPa.
    """
    M, d = F.shape[0], F.shape[1]
    n = d + 1
    c = np.empty((d, d))
    J[:] = 0.0  # the current nodal volumes v_a first
    for e in range(M):
        V = volume[e]
        if linear:
            tr = 0.0
            for i in range(d):
                tr += F[e, i, i]
            v = V * (1.0 + tr - d)
            for b in range(n):
                for i in range(d):
                    dv[e, b, i] = grad_rows[b, i, e] * V
        else:
            v = V * _cofactor(F, e, c)
            for b in range(n):
                for i in range(d):
                    s = 0.0
                    for j in range(d):
                        s += c[i, j] * grad_rows[b, j, e]
                    dv[e, b, i] = s * V
        share = v / n
        for b in range(n):
            J[corners[b, e]] += share
    for a in range(J.shape[0]):
        J[a] = J[a] / rest_volume[a]
        pressure[a] = kappa[a] * (J[a] - 1.0)
    for e in range(M):
        s = 0.0
        for b in range(n):
            s += pressure[corners[b, e]]
        element_pressure[e] = s / n


@njit(**_JIT)
def pressure_forces(corners, dv, element_pressure, out):
    """out (dN,) mN = Σ_e p̄_e ∂v_e/∂x, from dv (M, d+1, d) and p̄ (M,); out zeroed first."""
    d = dv.shape[2]
    out[:] = 0.0
    for e in range(dv.shape[0]):
        p = element_pressure[e]
        for b in range(dv.shape[1]):
            node = corners[b, e]
            for i in range(d):
                out[d * node + i] += dv[e, b, i] * p


@njit(**_JIT)
def b_values(dv, b_slot, out):
    """B's data out (nnz,): entry b_slot[e, (a (d+1) + b) d + i] gets ∂v_e/∂x_bi / (d+1) for each corner a of e,
    element by element; out zeroed first. dv (M, d+1, d)."""
    M, n, d = dv.shape
    out[:] = 0.0
    for e in range(M):
        k = 0
        for _ in range(n):
            for b in range(n):
                for i in range(d):
                    out[b_slot[e, k]] += dv[e, b, i] / n
                    k += 1


@njit(**_JIT)
def pressure_hessians(F, grad_rows, scale, Ke):
    """Ke[pair, e] = scale_e Σ_jl ∂N_a/∂X_j Q(F_e)[(i,j),(k,l)] ∂N_b/∂X_l (Q = ∂²det F/∂F²) for the packed pairs
    (p = d a + i ≤ q = d b + k), every entry of Ke (P, M) written.

    With g_a = ∇N_a the block (a, b) is scale ε_ikm (F (g_a × g_b))_m in 3-D
    and scale ε_ik (g_a × g_b) in 2-D. Pair by pair, each over all elements:
    Ke's rows are then written in order (element by element its entries lie M apart).
    """
    M, d = F.shape[0], F.shape[1]
    n = d * (d + 1)
    row = 0
    for p in range(n):
        a, i = p // d, p % d
        for q in range(p, n):
            b, k = q // d, q % d
            if i == k:
                for e in range(M):
                    Ke[row, e] = 0.0
            elif d == 2:
                sign = 1.0 if i == 0 else -1.0
                for e in range(M):
                    cross = grad_rows[a, 0, e] * grad_rows[b, 1, e] - grad_rows[a, 1, e] * grad_rows[b, 0, e]
                    Ke[row, e] = scale[e] * cross * sign
            else:
                m = 3 - i - k
                sign = 1.0 if (k - i) % 3 == 1 else -1.0  # ε_ikm: +1 for (0,1,2) and its cyclic shifts
                for e in range(M):
                    c0 = grad_rows[a, 1, e] * grad_rows[b, 2, e] - grad_rows[a, 2, e] * grad_rows[b, 1, e]
                    c1 = grad_rows[a, 2, e] * grad_rows[b, 0, e] - grad_rows[a, 0, e] * grad_rows[b, 2, e]
                    c2 = grad_rows[a, 0, e] * grad_rows[b, 1, e] - grad_rows[a, 1, e] * grad_rows[b, 0, e]
                    fm = F[e, m, 0] * c0 + F[e, m, 1] * c1 + F[e, m, 2] * c2
                    Ke[row, e] = scale[e] * sign * fm
            row += 1


@njit(**_JIT)
def averaged(indptr, indices, b_rest, rest_volume, x, F):
    """F̄_a[i, j] += Σ_b x_b[i] B_lin[a, (b, j)] / V_a over row a's entries (entry s: dof r, node r // d, j = r % d);
    x (N, d) mm, F (N, d, d)."""
    d = F.shape[1]
    for a in range(indptr.shape[0] - 1):
        inv = 1.0 / rest_volume[a]
        for s in range(indptr[a], indptr[a + 1]):
            r = indices[s]
            b, j = r // d, r % d
            w = b_rest[s] * inv
            for i in range(d):
                F[a, i, j] += x[b, i] * w


@njit(**_JIT)
def averaged_transpose(indptr, indices, b_rest, rest_volume, stress, out):
    """out[d b + i] += Σ_j stress_a[i, j] B_lin[a, (b, j)] / V_a: the transpose of `averaged`; stress (N, d, d),
    out (dN,)."""
    d = stress.shape[1]
    for a in range(indptr.shape[0] - 1):
        inv = 1.0 / rest_volume[a]
        for s in range(indptr[a], indptr[a + 1]):
            r = indices[s]
            b, j = r // d, r % d
            w = b_rest[s] * inv
            for i in range(d):
                out[d * b + i] += stress[a, i, j] * w


@njit(**_JIT)
def coupling_product(indptr, indices, data, weight, v, out):
    """out (dN,) = Bᵀ diag(weight) B v for B (N, dN) in CSR, weight (N,), v (dN,); out zeroed first. Row by row,
    as scipy's B @ v and (B.T) @ y sum."""
    out[:] = 0.0
    for a in range(indptr.shape[0] - 1):
        s = 0.0
        for t in range(indptr[a], indptr[a + 1]):
            s += data[t] * v[indices[t]]
        s = weight[a] * s
        for t in range(indptr[a], indptr[a + 1]):
            out[indices[t]] += data[t] * s


@njit(**_JIT)
def count_pairs(indptr, indices, dof_index, upper):
    """The number of two-ring pairs `fill_pairs` lists."""
    count = 0
    for a in range(indptr.shape[0] - 1):
        kept = 0
        for t in range(indptr[a], indptr[a + 1]):
            if dof_index[indices[t]] >= 0:
                kept += 1
        count += kept * (kept + 1) // 2 if upper else kept * kept
    return count


@njit(**_JIT)
def fill_pairs(indptr, indices, dof_index, upper, rows, cols):
    """Rows and cols (dof_index's numbering) of each node's pairs of kept dofs (entries s ≤ t of its row if upper)."""
    k = 0
    for a in range(indptr.shape[0] - 1):
        for s in range(indptr[a], indptr[a + 1]):
            p = dof_index[indices[s]]
            if p < 0:
                continue
            for t in range(s if upper else indptr[a], indptr[a + 1]):
                q = dof_index[indices[t]]
                if q < 0:
                    continue
                rows[k] = p
                cols[k] = q
                k += 1


@njit(**_JIT)
def add_pairs(b_matrix, weight, rest_volume, tangent, dof_index, upper, slot, out, data_range):
    """The pairs of `fill_pairs`, in its order, added into out at slot: those landing in out's data_range (d0, d1)
    (whole rows: `fem.SparsePattern.data_cuts`), so runs of rows may be added at once. b_matrix: B's CSR
    (indptr, indices, data) and its rest values b_rest. Pair (s, t) (entry s = dof (b, i), t = (c, k) of row a)
    gets w_a B_as B_at + Σ_jl ḡ_ab[j] C_a[d i + j, d k + l] ḡ_ac[l], with ḡ_ab[j] = B_lin[a, (b, j)] / V_a found
    at s − i + j (a node's d dofs are consecutive in its row).

    Row s's contraction with C_a is formed once (r[k, l]); the row's
    columns are then walked node by node, so a column's coordinate k is its
    place in the node's group: no integer division in the innermost loop. A
    row s's pairs all land in one row of out (the first is (s, s) or (s, lo)), so
    a row landing elsewhere is only counted past.
    """
    indptr, indices, data, b_rest = b_matrix
    d0, d1 = data_range
    d = 3 if tangent.shape[1] == 9 else 2
    r = np.empty((d, d))
    k = 0
    for a in range(indptr.shape[0] - 1):
        w = weight[a]
        inv2 = 1.0 / (rest_volume[a] * rest_volume[a])
        lo, hi = indptr[a], indptr[a + 1]
        for s in range(lo, hi):
            if dof_index[indices[s]] < 0:
                continue
            start = s if upper else lo
            if not d0 <= slot[k] < d1:  # another run's row: its pairs counted past
                for t in range(start, hi):
                    if dof_index[indices[t]] >= 0:
                        k += 1
                continue
            ws = w * data[s]
            i = indices[s] % d
            s0 = s - i
            for kk in range(d):
                for m in range(d):
                    acc = 0.0
                    for j in range(d):
                        acc += b_rest[s0 + j] * tangent[a, d * i + j, d * kk + m]
                    r[kk, m] = acc * inv2
            t0 = start - indices[start] % d
            while t0 < hi:
                for kk in range(d):
                    t = t0 + kk
                    if t < start or dof_index[indices[t]] < 0:
                        continue
                    acc = ws * data[t]
                    for m in range(d):
                        acc += r[kk, m] * b_rest[t0 + m]
                    out[slot[k]] += acc
                    k += 1
                t0 += d


@njit(**_JIT)
def averaged_material_2d(F, V, material, tension_only, order, project, psi, P, C):
    """Ψ V_a (N,) µJ, P V_a (N, 2, 2) and (order 2) C V_a (N, 4, 4) (projected per term if asked) at F̄ (N, 2, 2)
    into psi, P, C; returns -1, or the first node it cannot take. material: `compiled._material`'s."""
    mu, kappa, eta, fa, fb = material
    H = np.zeros((4, 4))
    for node in range(F.shape[0]):
        f0, f1, f2, f3 = F[node, 0, 0], F[node, 0, 1], F[node, 1, 0], F[node, 1, 1]
        psi_a, p00, p01, p10, p11, J, alpha, s, iJ, v0, v1, I4m1, eta_eff = compiled._stress(
            f0, f1, f2, f3, mu[node], kappa[node], eta[node], fa[node], fb[node], tension_only)
        if not (J > J_FLOOR and math.isfinite(psi_a + p00 + p01 + p10 + p11)):
            return node
        w = V[node]
        psi[node] = psi_a * w
        P[node, 0, 0], P[node, 0, 1], P[node, 1, 0], P[node, 1, 1] = p00 * w, p01 * w, p10 * w, p11 * w
        if order < 2:
            continue
        compiled._tangent(H, (f0, f1, f2, f3), kappa[node], (alpha, s, iJ, v0, v1, I4m1, eta_eff),
                          (fa[node], fb[node]), project)
        finite = 0.0
        for p in range(4):
            for q in range(p, 4):
                C[node, p, q] = H[p, q] * w
                C[node, q, p] = H[p, q] * w
                finite += H[p, q]
        if not math.isfinite(finite):
            return node
    return -1


@njit(**_JIT)
def averaged_material_3d(F, V, material, tension_only, hd_pattern, order, project, psi, P, C):
    """Ψ V_a (N,) µJ, P V_a (N, 3, 3) and (order 2) C V_a (N, 9, 9) (PSD-projected if asked, `project_matrix`) at
    F̄ (N, 3, 3) into psi, P, C; returns -1, or the first node it cannot take. material: `compiled3d._material`'s;
    hd_pattern: `compiled3d.DET_HESSIAN`."""
    mu, kappa, eta, fiber = material
    hd_index, hd_sign = hd_pattern
    f, c, p, a = np.empty(9), np.empty(9), np.empty(9), np.empty(3)
    T, L, A = np.empty((9, 9)), np.empty((9, 9)), np.empty((9, 9))
    for node in range(F.shape[0]):
        for i in range(3):
            for j in range(3):
                f[3 * i + j] = F[node, i, j]
        a[0], a[1], a[2] = fiber[node, 0], fiber[node, 1], fiber[node, 2]
        psi_a, J, alpha, s, iJ, I4m1, eta_eff, v0, v1, v2 = compiled3d._stress(
            f, c, a, mu[node], kappa[node], eta[node], tension_only, p)
        if not compiled3d._takes(psi_a, p, J):
            return node
        w = V[node]
        psi[node] = psi_a * w
        for i in range(3):
            for j in range(3):
                P[node, i, j] = p[3 * i + j] * w
        if order < 2:
            continue
        I1 = 0.0
        for q in range(9):
            I1 += f[q] * f[q]
        compiled3d._tangent(T, f, c, a, (alpha, s, iJ, I1, I4m1, eta_eff, v0, v1, v2), kappa[node], hd_index,
                            hd_sign)
        finite = 0.0
        for i in range(9):
            for j in range(9):
                finite += T[i, j]
        if not math.isfinite(finite):
            return node
        if project:
            compiled3d.project_matrix(T, L, A)
        for i in range(9):
            for j in range(9):
                C[node, i, j] = T[i, j] * w
    return -1


def averaged_material(F: np.ndarray, V: np.ndarray, params, order: int, project: bool) -> tuple | None:
    """(Ψ V (N,) µJ, P V (N, d, d) mN·mm (None for order 0), C V (N, d², d²) mN·mm (None below order 2; with
    `project` always, PSD-projected)) of the material `params` (N nodes) at F̄ (N, d, d), V (N,) mm³; None where
    the numpy path must answer: the `linear` model (its constant tangent), or a node with J̄ ≤ J_FLOOR or a
    non-finite term."""
    d = F.shape[1]
    if params.model == "linear" or (d == 2 and params._fib is None):
        return None
    order = 2 if project else order
    N = F.shape[0]
    F = np.ascontiguousarray(F, dtype=np.float64)
    psi, P = np.empty(N), np.empty((N, d, d))
    C = np.empty((N if order == 2 else 0, d * d, d * d))
    if d == 2:
        material, tension_only = compiled._material(params)
        bad = averaged_material_2d(F, V, material, tension_only, order, bool(project), psi, P, C)
    else:
        material, tension_only = compiled3d._material(params)
        bad = averaged_material_3d(F, V, material, tension_only, compiled3d.DET_HESSIAN, order, bool(project), psi,
                                   P, C)
    if bad >= 0:
        return None
    return psi, P if order >= 1 else None, C if order == 2 else None
