"""The nodal element: strain and volume averaged over each node's elements, so linear simplices neither lock
nor stiffen (docs/model.md §21).

Written as one energy, so Newton keeps an exact, symmetric tangent:

    U = α Σ_e V_e Ψ_dev(F_e) + (1 − α) Σ_a V_a Ψ_dev(F̄_a) + Σ_a V_a κ_a/2 (J_a − 1)²

* Ψ_dev is §3's energy without its volumetric term (κ = 0: isochoric and
  fiber; for `linear`, μ dev ε : dev ε).
* F̄_a = Σ_{e∋a} V_e F_e / ((d+1) V_a) is the node's averaged deformation
  gradient (Dohrmann et al. 2000's node-based uniform strain), V_a =
  Σ_{e∋a} V_e/(d+1) its rest volume; its material is the rest-volume average
  of the elements' (μ, η, the fiber).
* J_a = v_a / V_a with v_a = Σ_{e∋a} v_e/(d+1) and v_e = V_e det F_e the
  element's current volume (V_e (1 + tr(F_e − I)) for `linear`): Bonet &
  Burton (1998)'s averaged nodal volume, NiftySim's ANP tetrahedron. A
  piecewise-linear field can keep one volume per node where it could not
  keep one per element: that is the locking it removes.
* α (`ELEMENT_SHARE`) keeps a share of the element's own deviatoric energy:
  nodal averaging alone has soft, spurious modes and is too soft, the
  element alone too stiff (Puso & Solberg 2006 stabilise the same way); α
  was chosen by measurement against quadratic elements
  (benchmarks/bench_elements.py).

With p_a = κ_a (J_a − 1), p̄_e = Σ_{a∈e} p_a/(d+1) and P̄_a, C̄_a the stress
and tangent of Ψ_dev at F̄_a:

    ∇U_vol = Σ_e p̄_e ∂v_e/∂x,   ∇²U_vol = Σ_e p̄_e ∂²v_e/∂x² + Bᵀ diag(κ_a / V_a) B,   B_a· = ∂v_a/∂x,
    ∇U_avg = Σ_a (1−α) V_a Āᵀ_a P̄_a,   ∇²U_avg = Σ_a (1−α) V_a Āᵀ_a C̄_a Ā_a,   Ā_a = ∂ vec F̄_a / ∂x.

p̄_e ∂²v_e is element-local (packed like every element matrix); the rest
couples the two rings of elements around each node, all on one pattern:
node a's row of B holds the dofs of its patch, and Ā_a is the same row of
B at rest with the linear volume (∂N_b/∂X_j averaged: B_lin[a, (b, j)] =
V_a ∂F̄_a,ij/∂x_bi). `pairs` lists those dof pairs per node,
`fem.sparse_pattern` joins them to the elements', and compiled loops add
into their slots. ∂v_e/∂x = V_e cof(F_e) ∇N.

Arrays: positions x (N, d) mm; F (M, d, d); B's data (nnz,) in mm² (in 2-D
times the thickness) — B is (N, dN) in CSR with a fixed pattern; energies
µJ, forces mN, stiffness mN/mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numba import njit

from scissor_cli.mechanics import compiled, compiled3d, fem

_JIT = dict(cache=True, nogil=True, error_model="numpy")

#: the element kinds `Tissue` knows: `p1` (linear simplices, every term per element) and `nodal` (this module)
ELEMENTS: tuple[str, ...] = ("p1", "nodal")
#: α, the share of the deviatoric energy kept per element (the rest per node): in the flat bottom of the error
#: against quadratic elements over α, at each ν tried (benchmarks/bench_elements.py, its `share` table)
ELEMENT_SHARE = 0.5


@dataclass(frozen=True)
class NodalVolume:
    """The fixed structure of the nodal volume term on a mesh: rest volumes and B's sparsity.

    rest_volume (N,) mm³ (h·area in 2-D); b_indptr (N+1,), b_indices (nnz,)
    the CSR pattern of B (N, dN), each row's dofs sorted; b_slot (M, (d+1)² d)
    the position in B's data of element e's entry (row corner a, column
    corner b, coordinate i), in that order.
    """

    rest_volume: np.ndarray
    b_indptr: np.ndarray
    b_indices: np.ndarray
    b_slot: np.ndarray
    dim: int
    #: B's data at rest for the linear volume (nnz,): V_a times the averaged ∂N_b/∂X (the operator Ā of F̄)
    b_rest: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: α: the share of the deviatoric energy kept per element (`ELEMENT_SHARE`)
    element_share: float = ELEMENT_SHARE

    @property
    def n_nodes(self) -> int:
        return len(self.rest_volume)


def nodal_volume(ops: fem.FEOperators, element_share: float = ELEMENT_SHARE) -> NodalVolume:
    """The nodal structure of simplices `ops` (`fem.simplex_operators`), α = `element_share`."""
    d, M, N = ops.dim, len(ops.triangles), ops.n_nodes
    n = d + 1
    rest = np.bincount(ops.triangles.ravel(), weights=np.repeat(ops.volume / n, n), minlength=N)
    # entries (row node a, dof of corner b, coordinate i) of every element, then B's CSR pattern
    rows = np.repeat(ops.triangles, n * d, axis=1)  # (M, n·n·d): a varies slowest
    cols = np.tile(ops.elem_dofs, (1, n))  # (M, n·n·d): then b and i
    # (a square pattern of the larger side: B's rows are its first N)
    indptr, indices, slot = compiled.csr_pattern(rows.ravel().astype(np.int64), cols.ravel().astype(np.int64), d * N)
    structure = NodalVolume(rest, indptr[:N + 1].copy(), indices, slot.reshape(M, n * n * d), d)
    at_rest = NodalState(np.ones(N), np.zeros(N), np.zeros(M), volume_gradients(ops, None, linear=True))
    return NodalVolume(rest, structure.b_indptr, indices, structure.b_slot, d, b_data(ops, structure, at_rest),
                       element_share)


def volume_gradients(ops: fem.FEOperators, F: np.ndarray | None, linear: bool) -> np.ndarray:
    """∂v_e/∂x (M, d+1, d) mm² (times h in 2-D): V_e cof(F_e) ∇N_b, or V_e ∇N_b when `linear`."""
    g = ops.grad_n  # (M, d+1, d)
    if linear:
        return g * ops.volume[:, None, None]
    cof = cofactor(F)  # (M, d, d)
    return np.einsum("eij,ebj->ebi", cof, g) * ops.volume[:, None, None]


def cofactor(F: np.ndarray) -> np.ndarray:
    """cof F = det(F) F⁻ᵀ (M, d, d) in closed form (finite for singular F)."""
    if F.shape[1] == 2:
        return np.stack([np.stack([F[:, 1, 1], -F[:, 1, 0]], 1), np.stack([-F[:, 0, 1], F[:, 0, 0]], 1)], 1)
    c = np.empty_like(F)
    for i in range(3):
        for j in range(3):
            i1, i2, j1, j2 = (i + 1) % 3, (i + 2) % 3, (j + 1) % 3, (j + 2) % 3
            c[:, i, j] = F[:, i1, j1] * F[:, i2, j2] - F[:, i1, j2] * F[:, i2, j1]
    return c


def element_volumes(ops: fem.FEOperators, F: np.ndarray, linear: bool) -> np.ndarray:
    """Current element volumes v_e (M,) mm³ (times h in 2-D): V_e det F_e, or V_e (1 + tr(F_e − I))."""
    d = F.shape[1]
    if linear:
        return ops.volume * (1.0 + np.trace(F, axis1=1, axis2=2) - d)
    return ops.volume * np.linalg.det(F)


def nodal_kappa(ops: fem.FEOperators, kappa: np.ndarray, rest_volume: np.ndarray) -> np.ndarray:
    """κ_a (N,) kPa: the rest-volume average of the elements' κ (M,) around each node."""
    return nodal_average(ops, kappa, rest_volume)


def nodal_average(ops: fem.FEOperators, values: np.ndarray, rest_volume: np.ndarray) -> np.ndarray:
    """The rest-volume average around each node (N, ...) of per-element values (M, ...)."""
    n = ops.dim + 1
    weight = ops.volume / n
    flat = values.reshape(len(values), -1)
    out = np.column_stack([np.bincount(ops.triangles.ravel(), weights=np.repeat(flat[:, k] * weight, n),
                                       minlength=len(rest_volume)) for k in range(flat.shape[1])])
    return (out / rest_volume[:, None]).reshape((len(rest_volume),) + values.shape[1:])


def averaged_gradients(nodal: NodalVolume, x: np.ndarray) -> np.ndarray:
    """F̄ (N, d, d): each node's rest-volume average of its elements' F at positions x (N, d) (linear in x)."""
    F = np.zeros((nodal.n_nodes, nodal.dim, nodal.dim))
    _averaged(nodal.b_indptr, nodal.b_indices, nodal.b_rest, nodal.rest_volume, np.ascontiguousarray(x, float), F)
    return F


def averaged_forces(nodal: NodalVolume, stress: np.ndarray) -> np.ndarray:
    """Σ_a Āᵀ_a vec(stress_a) (dN,) for per-node stresses (N, d, d) already weighted by (1 − α) V_a."""
    out = np.zeros(nodal.dim * nodal.n_nodes)
    _averaged_transpose(nodal.b_indptr, nodal.b_indices, nodal.b_rest, nodal.rest_volume,
                        np.ascontiguousarray(stress, float), out)
    return out


@dataclass(frozen=True)
class NodalState:
    """The nodal term at one x: J_a (N,), p_a = κ_a (J_a − 1) (N,) kPa, p̄_e (M,) kPa, ∂v_e/∂x (M, d+1, d)."""

    J: np.ndarray
    pressure: np.ndarray
    element_pressure: np.ndarray
    dv: np.ndarray

    def take(self, elements: np.ndarray) -> "NodalState":
        """The element quantities of a subset of the elements (E,); the nodal ones whole."""
        return NodalState(self.J, self.pressure, self.element_pressure[elements], self.dv[elements])


def nodal_state(ops: fem.FEOperators, nodal: NodalVolume, kappa_a: np.ndarray, F: np.ndarray,
                linear: bool) -> NodalState:
    """The nodal volumes, pressures and element volume gradients at deformation gradients F (M, d, d)."""
    n = ops.dim + 1
    v = element_volumes(ops, F, linear)
    v_a = np.bincount(ops.triangles.ravel(), weights=np.repeat(v / n, n), minlength=nodal.n_nodes)
    J = v_a / nodal.rest_volume
    p = kappa_a * (J - 1.0)
    p_bar = p[ops.triangles].sum(axis=1) / n
    return NodalState(J, p, p_bar, volume_gradients(ops, F, linear))


def energy(nodal: NodalVolume, kappa_a: np.ndarray, state: NodalState) -> float:
    """U_vol (µJ)."""
    return float(0.5 * np.dot(nodal.rest_volume * kappa_a, (state.J - 1.0) ** 2))


def gradient(ops: fem.FEOperators, state: NodalState) -> np.ndarray:
    """∇U_vol (dN,) mN: Σ_e p̄_e ∂v_e/∂x."""
    d = ops.dim
    return fem.scatter_vector(ops, (state.dv * state.element_pressure[:, None, None]).reshape(-1, d * (d + 1)))


def element_hessians(ops: fem.FEOperators, F: np.ndarray, state: NodalState, linear: bool) -> np.ndarray:
    """p̄_e ∂²v_e/∂x², packed (P, M) mN/mm: V_e p̄_e Gᵀ Q(F_e) G with Q = ∂²det F/∂F² (zero for `linear`).

    In closed form (`_pressure_hessians`): with g_a = ∇N_a, the block (a, b) is V_e p̄_e ε_ikm (F (g_a × g_b))_m
    in 3-D and V_e p̄_e ε_ik (g_a × g_b) in 2-D.
    """
    d = ops.dim
    Ke = np.zeros((len(fem.pairs_for(d)), len(ops.triangles)))
    if not linear:
        _pressure_hessians(np.ascontiguousarray(F, float), ops.grad_rows, ops.volume * state.element_pressure, Ke)
    return Ke


def det_hessian(F: np.ndarray) -> np.ndarray:
    """Q = ∂²det F / ∂vec F² (M, d², d²), vec row-major (in 3-D Q[(i,j),(k,l)] = Σ_mn ε_ikm ε_jln F_mn): the
    reference `_pressure_hessians` is checked against."""
    M, d = F.shape[0], F.shape[1]
    if d == 2:
        Q = np.zeros((M, 4, 4))
        Q[:, 0, 3] = Q[:, 3, 0] = 1.0
        Q[:, 1, 2] = Q[:, 2, 1] = -1.0
        return Q
    index, sign = compiled3d.DET_HESSIAN
    return np.where(index >= 0, sign * F.reshape(M, 9)[:, np.maximum(index, 0)], 0.0)


@njit(**_JIT)
def _pressure_hessians(F, grad_rows, scale, Ke):
    """Ke[pair, e] = scale_e Σ_jl ∂N_a/∂X_j Q(F_e)[(i,j),(k,l)] ∂N_b/∂X_l for the packed pairs
    (p = d a + i ≤ q = d b + k)."""
    M = F.shape[0]
    d = F.shape[1]
    n = d * (d + 1)
    for e in range(M):
        w = scale[e]
        row = 0
        for p in range(n):
            a, i = p // d, p % d
            for q in range(p, n):
                b, k = q // d, q % d
                if i == k:
                    Ke[row, e] = 0.0
                elif d == 2:
                    cross = grad_rows[a, 0, e] * grad_rows[b, 1, e] - grad_rows[a, 1, e] * grad_rows[b, 0, e]
                    Ke[row, e] = w * cross if i == 0 else -w * cross
                else:
                    c0 = grad_rows[a, 1, e] * grad_rows[b, 2, e] - grad_rows[a, 2, e] * grad_rows[b, 1, e]
                    c1 = grad_rows[a, 2, e] * grad_rows[b, 0, e] - grad_rows[a, 0, e] * grad_rows[b, 2, e]
                    c2 = grad_rows[a, 0, e] * grad_rows[b, 1, e] - grad_rows[a, 1, e] * grad_rows[b, 0, e]
                    m = 3 - i - k
                    fm = F[e, m, 0] * c0 + F[e, m, 1] * c1 + F[e, m, 2] * c2
                    sign = 1.0 if (k - i) % 3 == 1 else -1.0  # ε_ikm: +1 for (0,1,2) and its cyclic shifts
                    Ke[row, e] = w * sign * fm
                row += 1


def b_data(ops: fem.FEOperators, nodal: NodalVolume, state: NodalState) -> np.ndarray:
    """B's data (nnz,): row a, column (b, i) holds Σ_{e∋a,b} ∂v_e/∂x_bi / (d+1)."""
    n = ops.dim + 1
    per_row = (state.dv.reshape(len(state.dv), -1) / n)  # (M, n·d): the same for each row corner a
    return np.bincount(nodal.b_slot.ravel(), weights=np.tile(per_row, (1, n)).ravel(), minlength=len(nodal.b_indices))


def b_matrix(nodal: NodalVolume, data: np.ndarray) -> sp.csr_matrix:
    """B (N, dN) as a CSR matrix."""
    return sp.csr_matrix((data, nodal.b_indices, nodal.b_indptr), shape=(nodal.n_nodes, nodal.dim * nodal.n_nodes))


def coupling_times(nodal: NodalVolume, data: np.ndarray, weight: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bᵀ diag(weight) B v (dN,) for a full vector v (dN,); weight (N,) = κ_a / V_a."""
    B = b_matrix(nodal, data)
    return B.T @ (weight * (B @ v))


def pairs(nodal: NodalVolume, dof_index: np.ndarray, upper: bool) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (in dof_index's numbering) of every entry the two-ring coupling adds, in `add_tangent`'s order.

    dof_index (dN,) as for `fem.sparse_pattern` (−1 drops a dof); `upper`
    keeps each row's pairs with row ≤ column once. Each node a adds the
    (n_a)² products of its row's kept dofs.
    """
    count = _count_pairs(nodal.b_indptr, nodal.b_indices, dof_index, upper)
    rows, cols = np.empty(count, np.int64), np.empty(count, np.int64)
    _fill_pairs(nodal.b_indptr, nodal.b_indices, dof_index, upper, rows, cols)
    return rows, cols


def add_tangent(nodal: NodalVolume, data: np.ndarray, weight: np.ndarray, tangent: np.ndarray,
                dof_index: np.ndarray, upper: bool, slot: np.ndarray, out: np.ndarray) -> None:
    """The two-ring part of the tangent into the CSR data `out` of a joined pattern, pair k of `pairs` at slot[k]:
    weight_a B_ap B_aq (the volume; B's data `data`, weight (N,) = κ_a / V_a) + (Āᵀ_a C_a Ā_a)_pq (the averaged
    strain; tangents (N, d², d²) already weighted by (1 − α) V_a)."""
    _add_pairs(nodal.b_indptr, nodal.b_indices, data, weight, nodal.b_rest, nodal.rest_volume,
               np.ascontiguousarray(tangent, float), dof_index, upper, slot, out)


@njit(**_JIT)
def _count_pairs(indptr, indices, dof_index, upper):
    count = 0
    for a in range(indptr.shape[0] - 1):
        kept = 0
        for t in range(indptr[a], indptr[a + 1]):
            if dof_index[indices[t]] >= 0:
                kept += 1
        count += kept * (kept + 1) // 2 if upper else kept * kept
    return count


@njit(**_JIT)
def _fill_pairs(indptr, indices, dof_index, upper, rows, cols):
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
def _averaged(indptr, indices, b_rest, rest_volume, x, F):
    """F̄_a[i, j] = Σ_b x_b[i] B_lin[a, (b, j)] / V_a over row a's entries (entry s: dof r, node r // d, j = r % d)."""
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
def _averaged_transpose(indptr, indices, b_rest, rest_volume, stress, out):
    """out[d b + i] += Σ_j stress_a[i, j] B_lin[a, (b, j)] / V_a: the transpose of `_averaged`."""
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
def _add_pairs(indptr, indices, data, weight, b_rest, rest_volume, tangent, dof_index, upper, slot, out):
    """The pairs of `_fill_pairs`, in its order. Pair (s, t) (entry s = dof (b, i), t = (c, k) of row a) gets
    w_a B_as B_at + Σ_jl ḡ_ab[j] C_a[d i + j, d k + l] ḡ_ac[l], with ḡ_ab[j] = B_lin[a, (b, j)] / V_a found at
    s − i + j (a node's d dofs are consecutive in its row). Row s's contraction with C_a is formed once
    (r[k, l]); each pair then costs d + 1 products."""
    d = int(round(np.sqrt(tangent.shape[1])))
    r = np.empty((d, d))
    k = 0
    for a in range(indptr.shape[0] - 1):
        w = weight[a]
        inv2 = 1.0 / (rest_volume[a] * rest_volume[a])
        for s in range(indptr[a], indptr[a + 1]):
            if dof_index[indices[s]] < 0:
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
            for t in range(s if upper else indptr[a], indptr[a + 1]):
                if dof_index[indices[t]] < 0:
                    continue
                kk = indices[t] % d
                t0 = t - kk
                acc = ws * data[t]
                for m in range(d):
                    acc += r[kk, m] * b_rest[t0 + m]
                out[slot[k]] += acc
                k += 1
