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
  was chosen by measurement against the mixed u–p quadratic reference,
  which does not lock (benchmarks/bench_elements.py, its `share` table).

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

The loops over elements and nodes (the state, the gradient, B, the
nodes' material, the pairs) are compiled in `mechanics.nodal_compiled`;
this module holds the structure and the calls. In 3-D the whole gradient
is also one compiled call (`nodal_compiled.energy_gradient`), every term's
force as an element stress: P_e + Σ_{a∈e} P̄_a/(d+1) + p̄_e cof F_e.

Arrays: positions x (N, d) mm; F (M, d, d); B's data (nnz,) in mm² (in 2-D
times the thickness) — B is (N, dN) in CSR with a fixed pattern; energies
µJ, forces mN, stiffness mN/mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scissor_cli import runtime
from scissor_cli.mechanics import compiled, compiled3d, fem, materials, nodal_compiled

#: the element kinds `Tissue` knows: `p1` (linear simplices, every term per element) and `nodal` (this module)
ELEMENTS: tuple[str, ...] = ("p1", "nodal")
#: α, the share of the deviatoric energy kept per element (the rest per node), chosen against the mixed u–p
#: (Taylor–Hood) reference, which does not lock: over the dome's lesions, one cup and two, the share of those
#: tried with the smallest errors at the tissue's ν 0.45–0.49 that stays within the element's bounds at 0.499
#: (benchmarks/bench_elements.py, its `share` table; P2 alone locks at the larger ν and favoured a stiffer share)
ELEMENT_SHARE = 0.3


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
    # at rest with the linear volume ∂v_e/∂x = V_e ∇N: B's data is then B_lin
    at_rest = NodalState(np.ones(N), np.zeros(N), np.zeros(M), ops.grad_n * ops.volume[:, None, None])
    return NodalVolume(rest, structure.b_indptr, indices, structure.b_slot, d, b_data(ops, structure, at_rest),
                       element_share)


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
    nodal_compiled.averaged(nodal.b_indptr, nodal.b_indices, nodal.b_rest, nodal.rest_volume,
                            np.ascontiguousarray(x, float), F)
    return F


def averaged_forces(nodal: NodalVolume, stress: np.ndarray) -> np.ndarray:
    """Σ_a Āᵀ_a vec(stress_a) (dN,) for per-node stresses (N, d, d) already weighted by (1 − α) V_a."""
    out = np.zeros(nodal.dim * nodal.n_nodes)
    nodal_compiled.averaged_transpose(nodal.b_indptr, nodal.b_indices, nodal.b_rest, nodal.rest_volume,
                                      np.ascontiguousarray(stress, float), out)
    return out


def averaged_material(nodal: NodalVolume, params: materials.MaterialParams, x: np.ndarray, order: int,
                      project: bool = False) -> tuple:
    """Ψ_dev V_a (N,) µJ, P V_a (N, d, d) and C V_a (N, d², d²) (None beyond `order`; with `project` all three, C
    PSD-projected as the elements' tangents are) at the nodes' F̄ for positions x (N, d); params: the nodes'
    material (`Tissue.averaged_params`, already times 1 − α).

    In one compiled loop over the nodes (`nodal_compiled.averaged_material`)
    where it takes them; else the numpy kernels, whose policy for an
    inverted F̄ (Ψ = +inf) makes such a node infeasible like an element.
    """
    F = averaged_gradients(nodal, x)
    V = nodal.rest_volume
    fast = nodal_compiled.averaged_material(F, V, params, order, project)
    if fast is not None:
        return fast
    if project:
        psi, P, C = materials.evaluate_projected(F, params)
    else:
        psi, P, C = materials.evaluate(F, params, order=order)
    return psi * V, None if P is None else P * V[:, None, None], None if C is None else C * V[:, None, None]


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
    """The nodal volumes, pressures and element volume gradients at deformation gradients F (M, d, d): v_e = V_e
    det F_e (V_e (1 + tr(F_e − I)) when `linear`), ∂v_e/∂x = V_e cof(F_e) ∇N (V_e ∇N), one compiled pass
    (`nodal_compiled.nodal_state`)."""
    M, N, d = len(ops.triangles), nodal.n_nodes, ops.dim
    J, p, p_bar, dv = np.empty(N), np.empty(N), np.empty(M), np.empty((M, d + 1, d))
    nodal_compiled.nodal_state(np.ascontiguousarray(F, float), ops.corners, ops.grad_rows, ops.volume,
                               nodal.rest_volume, np.ascontiguousarray(kappa_a, float), bool(linear), J, p, p_bar, dv)
    return NodalState(J, p, p_bar, dv)


def energy(nodal: NodalVolume, kappa_a: np.ndarray, state: NodalState) -> float:
    """U_vol (µJ)."""
    return float(0.5 * np.dot(nodal.rest_volume * kappa_a, (state.J - 1.0) ** 2))


def gradient(ops: fem.FEOperators, state: NodalState) -> np.ndarray:
    """∇U_vol (dN,) mN: Σ_e p̄_e ∂v_e/∂x."""
    out = np.empty(ops.dim * ops.n_nodes)
    nodal_compiled.pressure_forces(ops.corners, state.dv, state.element_pressure, out)
    return out


def element_hessians(ops: fem.FEOperators, F: np.ndarray, state: NodalState, linear: bool) -> np.ndarray:
    """p̄_e ∂²v_e/∂x², packed (P, M) mN/mm: V_e p̄_e Gᵀ Q(F_e) G with Q = ∂²det F/∂F² (zero for `linear`), in
    closed form (`nodal_compiled.pressure_hessians`)."""
    P, M = len(fem.pairs_for(ops.dim)), len(ops.triangles)
    if linear:
        return np.zeros((P, M))
    Ke = np.empty((P, M))
    nodal_compiled.pressure_hessians(np.ascontiguousarray(F, float), ops.grad_rows,
                                     ops.volume * state.element_pressure, Ke)
    return Ke


def det_hessian(F: np.ndarray) -> np.ndarray:
    """Q = ∂²det F / ∂vec F² (M, d², d²), vec row-major (in 3-D Q[(i,j),(k,l)] = Σ_mn ε_ikm ε_jln F_mn): the
    reference `nodal_compiled.pressure_hessians` is checked against."""
    M, d = F.shape[0], F.shape[1]
    if d == 2:
        Q = np.zeros((M, 4, 4))
        Q[:, 0, 3] = Q[:, 3, 0] = 1.0
        Q[:, 1, 2] = Q[:, 2, 1] = -1.0
        return Q
    index, sign = compiled3d.DET_HESSIAN
    return np.where(index >= 0, sign * F.reshape(M, 9)[:, np.maximum(index, 0)], 0.0)


def b_data(ops: fem.FEOperators, nodal: NodalVolume, state: NodalState) -> np.ndarray:
    """B's data (nnz,): row a, column (b, i) holds Σ_{e∋a,b} ∂v_e/∂x_bi / (d+1)."""
    out = np.empty(len(nodal.b_indices))
    nodal_compiled.b_values(np.ascontiguousarray(state.dv, float), nodal.b_slot, out)
    return out


def coupling_times(nodal: NodalVolume, data: np.ndarray, weight: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bᵀ diag(weight) B v (dN,) for a full vector v (dN,); weight (N,) = κ_a / V_a."""
    out = np.empty(nodal.dim * nodal.n_nodes)
    nodal_compiled.coupling_product(nodal.b_indptr, nodal.b_indices, data, np.ascontiguousarray(weight, float),
                                    np.ascontiguousarray(v, float), out)
    return out


def pairs(nodal: NodalVolume, dof_index: np.ndarray, upper: bool) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (in dof_index's numbering) of every entry the two-ring coupling adds, in `add_tangent`'s order.

    dof_index (dN,) as for `fem.sparse_pattern` (−1 drops a dof); `upper`
    keeps each row's pairs with row ≤ column once. Each node a adds the
    (n_a)² products of its row's kept dofs.
    """
    count = nodal_compiled.count_pairs(nodal.b_indptr, nodal.b_indices, dof_index, upper)
    rows, cols = np.empty(count, np.int64), np.empty(count, np.int64)
    nodal_compiled.fill_pairs(nodal.b_indptr, nodal.b_indices, dof_index, upper, rows, cols)
    return rows, cols


def add_tangent(nodal: NodalVolume, data: np.ndarray, weight: np.ndarray, tangent: np.ndarray,
                dof_index: np.ndarray, pattern: fem.SparsePattern, out: np.ndarray) -> None:
    """The two-ring part of the tangent into the CSR data `out` of the joined pattern, pair k of `pairs` at
    pattern.extra_slot[k]: weight_a B_ap B_aq (the volume; B's data `data`, weight (N,) = κ_a / V_a) +
    (Āᵀ_a C_a Ā_a)_pq (the averaged strain; tangents (N, d², d²) already weighted by (1 − α) V_a). The pattern's
    runs of rows at once where the process has the threads (`runtime.in_parts`): each slot's sum in the serial
    order."""
    b_matrix = (nodal.b_indptr, nodal.b_indices, data, nodal.b_rest)
    tangent = np.ascontiguousarray(tangent, float)
    cuts = pattern.data_cuts
    runtime.in_parts(*[lambda k=k: nodal_compiled.add_pairs(b_matrix, weight, nodal.rest_volume, tangent, dof_index,
                                                            pattern.upper, pattern.extra_slot, out,
                                                            (cuts[k], cuts[k + 1])) for k in range(cuts.size - 1)])
