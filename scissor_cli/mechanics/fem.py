"""Linear simplex finite elements on all elements at once (docs/model.md §2, §13).

One code for both dimensions d ∈ {2, 3}: P1 triangles (the layer) and P1
tetrahedra (the slab of §13). Node positions are (N, d) arrays; degree of
freedom d·n + c is coordinate c of node n. Deformation gradients are
stacked (M, d, d) with F[e, i, j] = ∂x_i/∂X_j and vec(F) row-major
([F00, F01, F10, F11] in 2-D), so vec(F_e) = G_e x_e with the constant
(d², d(d+1)) matrix G_e and x_e = [x0, y0, (z0,) x1, ...]. Element
matrices are d(d+1) square: 6x6 (21 packed entries) in 2-D, 12x12 (78) in
3-D. The loops run over corners, coordinates and packed entries, never
over elements; in 2-D they do exactly the arithmetic of the former
triangle-only code (same operations, same order), so results are
bit-identical.

Sparse assembly goes through a `SparsePattern` computed once per mesh and
set of unknowns: element matrices are summed into CSR data by one compiled
loop (`compiled.scatter_packed`), never through a COO → CSR conversion in
the hot path.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from scissor_cli import runtime
from scissor_cli.mechanics import compiled
from scissor_cli.mesh.mesh import Mesh


@dataclass(frozen=True)
class FEOperators:
    triangles: np.ndarray  # (M, d+1) int64: the simplices (triangles in 2-D, tetrahedra in 3-D)
    area: np.ndarray  # (M,) mm² rest area in 2-D; mm³ rest volume in 3-D
    grad_n: np.ndarray  # (M, d+1, d) 1/mm, ∂N_a/∂X_j
    G: np.ndarray  # (M, d², d(d+1)) 1/mm, vec(F_e) = G_e x_e
    elem_dofs: np.ndarray  # (M, d(d+1)) int64
    thickness_mm: float  # 2-D: the layer's thickness; 3-D: 1.0 (volumes are real)
    n_nodes: int
    # Component-major copies for the hot loops: gathering and multiplying
    # contiguous (M,) rows is faster than strided columns of (M, 3, 2) (benchmarks/bench_forward.py).
    corners: np.ndarray  # (d+1, M) int64, triangles.T
    grad_rows: np.ndarray  # (d+1, d, M) 1/mm, grad_n.transpose(1, 2, 0)

    @property
    def dim(self) -> int:
        """d, the space dimension: 2 for triangles, 3 for tetrahedra."""
        return self.grad_n.shape[2]

    @cached_property
    def volume(self) -> np.ndarray:
        """Element volumes (M,) in mm³ (h·A_e in 2-D): energy density × volume = µJ; made once (every gradient
        reads it)."""
        return self.thickness_mm * self.area


def take_elements(ops: FEOperators, elements: np.ndarray) -> FEOperators:
    """The operators of a subset of the elements (E,) on the same nodes (`Tissue.stiffness_times_near`)."""
    return FEOperators(ops.triangles[elements], ops.area[elements], ops.grad_n[elements], ops.G[elements],
                       ops.elem_dofs[elements], ops.thickness_mm, ops.n_nodes,
                       np.ascontiguousarray(ops.corners[:, elements]),
                       np.ascontiguousarray(ops.grad_rows[..., elements]))


def build_operators(mesh: Mesh, thickness_mm: float) -> FEOperators:
    """The P1 operators of a triangle mesh (layer of thickness h)."""
    return simplex_operators(mesh.nodes, mesh.triangles, thickness_mm)


def simplex_operators(nodes: np.ndarray, cells: np.ndarray, thickness_mm: float = 1.0) -> FEOperators:
    """P1 operators of simplices: nodes (N, d) mm, cells (M, d+1) int64 positively oriented.

    d = 2: triangles of a layer of thickness h; d = 3: tetrahedra (pass 1.0).
    """
    if nodes.shape[1] == 3:
        return _tetrahedra_operators(nodes, cells)
    X = nodes[cells]  # (M, 3, 2)
    Dm = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]], axis=2)  # columns are edges
    det = Dm[:, 0, 0] * Dm[:, 1, 1] - Dm[:, 0, 1] * Dm[:, 1, 0]
    if np.any(det <= 0):
        raise ValueError(f"{int(np.sum(det <= 0))} mesh triangles are degenerate or clockwise")
    inv = np.empty_like(Dm)
    inv[:, 0, 0], inv[:, 1, 1] = Dm[:, 1, 1] / det, Dm[:, 0, 0] / det
    inv[:, 0, 1], inv[:, 1, 0] = -Dm[:, 0, 1] / det, -Dm[:, 1, 0] / det
    grad_n = np.empty((len(det), 3, 2))
    grad_n[:, 1:] = inv  # row k of Dm⁻¹ is ∇N_{k+1}
    grad_n[:, 0] = -inv[:, 0] - inv[:, 1]
    G = np.zeros((len(det), 4, 6))
    for i in range(2):  # G[e, 2i+j, 2a+i] = ∂N_a/∂X_j
        for j in range(2):
            G[:, 2 * i + j, i::2] = grad_n[:, :, j]
    elem_dofs = (2 * cells[:, :, None] + np.arange(2)).reshape(-1, 6)
    return FEOperators(
        cells, 0.5 * det, grad_n, G, elem_dofs, float(thickness_mm), len(nodes),
        np.ascontiguousarray(cells.T), np.ascontiguousarray(grad_n.transpose(1, 2, 0)),
    )


def _tetrahedra_operators(nodes: np.ndarray, cells: np.ndarray) -> FEOperators:
    X = nodes[cells]  # (M, 4, 3)
    Dm = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)  # columns are edges
    det = np.linalg.det(Dm)
    if np.any(det <= 0):
        raise ValueError(f"{int(np.sum(det <= 0))} mesh tetrahedra are degenerate or negatively oriented")
    inv = np.linalg.inv(Dm)
    M = len(det)
    grad_n = np.empty((M, 4, 3))
    grad_n[:, 1:] = inv  # row k of Dm⁻¹ is ∇N_{k+1}
    grad_n[:, 0] = -inv.sum(axis=1)
    G = np.zeros((M, 9, 12))
    for i in range(3):  # G[e, 3i+j, 3a+i] = ∂N_a/∂X_j
        for j in range(3):
            G[:, 3 * i + j, i::3] = grad_n[:, :, j]
    elem_dofs = (3 * cells[:, :, None] + np.arange(3)).reshape(-1, 12)
    return FEOperators(
        cells, det / 6.0, grad_n, G, elem_dofs, 1.0, len(nodes),
        np.ascontiguousarray(cells.T), np.ascontiguousarray(grad_n.transpose(1, 2, 0)),
    )


def deformation_gradients(ops: FEOperators, x: np.ndarray) -> np.ndarray:
    """F (M, d, d) of every element for node positions x (N, d).

    Plain arithmetic on contiguous rows of the d+1 vertices: faster than
    strided columns and than the equivalent einsum (benchmarks/bench_forward.py).
    """
    g = ops.grad_rows
    d = g.shape[1]
    F = np.empty((g.shape[2], d, d))
    for i in range(d):
        xi = np.ascontiguousarray(x[:, i])
        xs = [xi.take(ops.corners[a]) for a in range(d + 1)]
        for j in range(d):
            acc = xs[0] * g[0, j] + xs[1] * g[1, j] + xs[2] * g[2, j]
            for a in range(3, d + 1):
                acc += xs[a] * g[a, j]
            F[:, i, j] = acc
    return F


def element_forces(ops: FEOperators, P: np.ndarray) -> np.ndarray:
    """Element gradient vectors (M, d(d+1)) in mN from first Piola stresses P (M, d, d) in kPa."""
    g, vol = ops.grad_n, ops.volume
    d = g.shape[2]
    f = np.empty((len(g), d + 1, d))
    for i in range(d):  # f[e, a, i] = V Σ_j P_ij ∂N_a/∂X_j, plain arithmetic (einsum is slower here)
        Pi = [P[:, i, j] * vol for j in range(d)]
        for a in range(d + 1):
            acc = Pi[0] * g[:, a, 0] + Pi[1] * g[:, a, 1]
            for j in range(2, d):
                acc += Pi[j] * g[:, a, j]
            f[:, a, i] = acc
    return f.reshape(-1, d * (d + 1))


def packed_pairs(n: int) -> tuple:
    """The (p, q), p <= q, of a symmetric n x n element matrix, in packed order."""
    return tuple((p, q) for p in range(n) for q in range(p, n))


#: The 21 (p, q), p <= q, of a symmetric 6x6 element matrix, in its packed order.
PACKED_PAIRS = packed_pairs(6)
#: The 78 of a 12x12 tetrahedron matrix.
PACKED_PAIRS_3D = packed_pairs(12)


def pairs_for(dim: int) -> tuple:
    """The packed pairs of a d(d+1) element matrix."""
    return PACKED_PAIRS if dim == 2 else PACKED_PAIRS_3D


def element_matrices(ops: FEOperators, C: np.ndarray, scale: np.ndarray | None = None) -> np.ndarray:
    """Symmetric element matrices, packed: (P, M), Ke[k, e] = (K_e)[pairs_for(d)[k]], P = 21 or 78.

    K_e = scale_e G_eᵀ C_e G_e from tangents C (M, d², d²) in kPa, scale the
    element volumes by default (then mN/mm). Only the upper triangle, and
    component rows: with the gradients' structure (G_e has d nonzeros per
    column) this beats two batched matmuls in 2-D, and an
    upper-triangle assembly needs nothing else. K_e[da+i, db+k] =
    Σ_jl ∂N_a/∂X_j C[di+j, dk+l] ∂N_b/∂X_l.
    """
    M = C.shape[0]
    g = ops.grad_rows  # (d+1, d, M)
    d = g.shape[1]
    dd = d * d
    rows = np.ascontiguousarray(C.reshape(M, dd * dd).T)  # rows[d²r + c] = C[:, r, c]
    # T[r, b, k] = Σ_j C[r, dk+j] ∂N_b/∂X_j
    T = np.empty((dd, d + 1, d, M))
    tmp = np.empty(M)
    for r in range(dd):
        for k in range(d):
            for b in range(d + 1):
                np.multiply(rows[dd * r + d * k], g[b, 0], out=T[r, b, k])
                for j in range(1, d):
                    np.multiply(rows[dd * r + d * k + j], g[b, j], out=tmp)
                    T[r, b, k] += tmp
    gs = g * (ops.volume if scale is None else scale)
    pairs = pairs_for(d)
    Ke = np.empty((len(pairs), M))
    for n, (p, q) in enumerate(pairs):
        (a, i), (b, k) = divmod(p, d), divmod(q, d)
        np.multiply(gs[a, 0], T[d * i, b, k], out=Ke[n])
        for j in range(1, d):
            np.multiply(gs[a, j], T[d * i + j, b, k], out=tmp)
            Ke[n] += tmp
    return Ke


def unpack(Ke: np.ndarray) -> np.ndarray:
    """Packed element matrices (P, M) → full symmetric (M, n, n), n = 6 (P = 21) or 12 (P = 78)."""
    pairs = PACKED_PAIRS if Ke.shape[0] == len(PACKED_PAIRS) else PACKED_PAIRS_3D
    n_dof = pairs[-1][1] + 1
    full = np.empty((Ke.shape[1], n_dof, n_dof))
    for n, (p, q) in enumerate(pairs):
        full[:, p, q] = full[:, q, p] = Ke[n]
    return full


def packed_times(ops: FEOperators, Ke: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Σ_e K_e v_e (dN,) for packed element matrices Ke (P, M) and a full vector v (dN,)."""
    ve = v[ops.elem_dofs].T  # (d(d+1), M)
    out = np.zeros((ve.shape[0], Ke.shape[1]))
    for n, (p, q) in enumerate(pairs_for(ops.dim)):
        out[p] += Ke[n] * ve[q]
        if p != q:
            out[q] += Ke[n] * ve[p]
    return scatter_vector(ops, out.T)


def scatter_vector(ops: FEOperators, elem: np.ndarray) -> np.ndarray:
    """Sum element vectors (M, d(d+1)) into a global vector (dN,)."""
    return np.bincount(ops.elem_dofs.ravel(), weights=elem.ravel(), minlength=ops.dim * ops.n_nodes)


def lumped_mass(ops: FEOperators, density_kg_per_mm3: float) -> np.ndarray:
    """Lumped mass per degree of freedom (dN,) in kg: ρ V_e / (d+1) per vertex."""
    d = ops.dim
    per_elem = np.repeat(density_kg_per_mm3 * ops.volume / (d + 1.0), d * (d + 1)).reshape(-1, d * (d + 1))
    return scatter_vector(ops, per_elem)


def reduction_matrix(ops: FEOperators) -> sp.csr_matrix:
    """The sparse D (d²M, dN) with D x = [vec F_e] stacked (paper eq. 18–20)."""
    M, d = len(ops.triangles), ops.dim
    dd, n = d * d, d * (d + 1)
    rows = np.repeat(np.arange(dd * M).reshape(M, dd), n, axis=1)
    cols = np.broadcast_to(ops.elem_dofs[:, None, :], (M, dd, n)).reshape(M, dd * n)
    return sp.csr_matrix((ops.G.reshape(M, dd * n).ravel(), (rows.ravel(), cols.ravel())),
                         shape=(dd * M, d * ops.n_nodes))


@dataclass(frozen=True)
class SparsePattern:
    """Where each entry of the packed element matrices lands in a CSR matrix.

    `entries` selects the entries of the flattened packed (P, M) element
    matrices that belong to the matrix (free rows and columns only; an
    off-diagonal pair twice in a full pattern, once in an upper one),
    `slot` is the CSR data position of each selected entry. An `upper`
    pattern holds the upper triangle only (sorted CSR), which is what a
    Cholesky factorisation reads.
    """

    entries: np.ndarray  # (E,) int64 into the flattened (P*M,) packed data
    slot: np.ndarray  # (E,) int64 into csr data
    indptr: np.ndarray
    indices: np.ndarray
    shape: tuple[int, int]
    #: (K + 1,) bounds in csr data of K runs of whole rows with about equal entries, and (K + 1,) bounds in
    #: `entries` of the entries landing in each (`runtime.MOST_THREADS` runs; `entries` grouped by run, each
    #: group in element order): a run's rows are written by its part alone, so the parts may assemble at once,
    #: each slot's sum in the serial order
    data_cuts: np.ndarray
    entry_cuts: np.ndarray
    upper: bool = False
    #: (X,) int32 into csr data: where the entries of `sparse_pattern`'s `extra` land (the nodal element's
    #: coupling, `mechanics.nodal`; int32 halves what its loop streams); empty without
    extra_slot: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))

    def assemble(self, Ke: np.ndarray) -> sp.csr_matrix:
        """The CSR matrix of packed element matrices Ke (P, M), its runs of rows at once where the process has the
        threads (`runtime.in_parts`)."""
        data = np.empty(len(self.indices))
        Ke = np.ascontiguousarray(Ke, dtype=np.float64)
        e, d = self.entry_cuts, self.data_cuts
        runtime.in_parts(*[lambda k=k: compiled.scatter_packed(Ke, self.entries, self.slot, data, (e[k], e[k + 1]),
                                                               (d[k], d[k + 1])) for k in range(e.size - 1)])
        return self.matrix(data)

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """The CSR matrix of this pattern with data (nnz,).

        Its column indices are sorted by construction (`sparse_pattern` takes
        them sorted from `compiled.csr_pattern`), so the matrix says so: no O(nnz) check later.
        """
        K = sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape)
        K.has_sorted_indices = True
        return K


def sparse_pattern(ops: FEOperators, dof_index: np.ndarray | None = None, upper: bool = False,
                   extra: tuple[np.ndarray, np.ndarray] | None = None) -> SparsePattern:
    """Pattern of the matrix over the dofs with dof_index >= 0 (renumbered by it).

    dof_index (dN,) maps each global dof to its row in the reduced system, or
    -1 to drop it (Dirichlet dofs); None keeps every dof. `upper`: only the
    upper triangle (row <= column). `extra`: (rows, cols) (X,) of entries
    beyond the elements', already renumbered (upper ones when `upper`): the
    pattern holds them too and `extra_slot` says where each lands.
    """
    n = ops.dim * ops.n_nodes
    if dof_index is None:
        dof_index = np.arange(n)
    local = dof_index[ops.elem_dofs]  # (M, d(d+1))
    M = len(local)
    pairs = pairs_for(ops.dim)
    p, q = np.array(pairs).T
    # Element-major (M, P) arrays: the scatter then goes element by element, where an
    # element's entries land in the few rows of its nodes, close to the last
    # element's (pair-major order jumps across the whole matrix for every entry).
    # A slot gets at most one entry of an element, so its sum runs over the
    # elements in order whatever the order inside one.
    rows, cols = local[:, p], local[:, q]
    packed = np.arange(len(pairs))[None, :] * M + np.arange(M)[:, None]  # into the flattened (P, M) packed data
    if upper:
        rows, cols = np.minimum(rows, cols), np.maximum(rows, cols)
    else:  # the mirror image of every off-diagonal pair, beside the element's others
        off = p != q
        rows, cols = np.hstack([rows, cols[:, off]]), np.hstack([cols, rows[:, off]])
        packed = np.hstack([packed, packed[:, off]])
    rows, cols, packed = rows.ravel(), cols.ravel(), packed.ravel()
    keep = (rows >= 0) & (cols >= 0)
    size = int(dof_index.max()) + 1
    rows, cols = rows[keep].astype(np.int64), cols[keep].astype(np.int64)
    n_elem = len(rows)
    if extra is not None:
        rows, cols = np.concatenate([rows, extra[0]]), np.concatenate([cols, extra[1]])
    indptr, indices, slot = compiled.csr_pattern(rows, cols, size)
    entries, slot, extra_slot = packed[keep], slot[:n_elem], slot[n_elem:].astype(np.int32)
    # runs of whole rows with about equal entries; the element entries grouped by run, each group in its order
    data_cuts = indptr[np.searchsorted(indptr, runtime.part_bounds(int(indptr[-1])))]
    run = np.searchsorted(data_cuts[1:-1], slot, side="right")
    order = np.argsort(run, kind="stable")
    entry_cuts = np.searchsorted(run[order], np.arange(data_cuts.size))
    return SparsePattern(entries[order], slot[order], indptr, indices, (size, size), data_cuts.astype(np.int64),
                         entry_cuts.astype(np.int64), upper, extra_slot)


def max_feasible_step_3d(F: np.ndarray, dF: np.ndarray) -> float:
    """The largest α ≥ 0 (inf if unbounded) with det(F_e + α dF_e) > 0 for all e; F, dF (M, 3, 3).

    det(F + α dF) = J (1 + b α + c α² + d α³) is a cubic per element
    (b = tr(F⁻¹dF) = Σ cof(F)∘dF / J, c = Σ F∘cof(dF) / J, d = det dF / J).
    With β = 1/α it becomes the monic β³ + b β² + c β + d, whose roots are
    the eigenvalues of its companion matrix (batched): no division by a
    vanishing leading coefficient. The first sign change is at 1/β for the
    largest positive real root β. Roots with an imaginary part below
    1e-6·|β| count as real (a double root, where J only touches 0): that can
    only shorten the step, never let it invert. Needs J > 0 at α = 0.

    Only the largest β over all elements matters, so the eigenvalues are
    computed only where they can reach it: Fujiwara's bound
    2 max(|b|, |c|^½, |d/2|^⅓) on every root (0 where no coefficient is
    negative: Descartes, no positive root) ranks the elements: those with the
    largest bounds are solved first, then only those whose bound exceeds the
    β found. The same β as solving every element (each matrix's
    eigenvalues do not depend on the batch), at a fraction of the cost.

    The definition on F and dF stacks: `Tissue.max_feasible_step` takes the
    coefficients and bounds from one compiled pass over x and dx
    (`compiled3d.feasibility_cubic_3d`) into `first_sign_change`, and the
    tests compare the two.
    """
    b, c, d = _feasibility_cubic(F, dF)
    with np.errstate(all="ignore"):
        bound = 2.0 * np.maximum(np.maximum(np.abs(b), np.sqrt(np.abs(c))), np.cbrt(np.abs(0.5 * d)))
        bound[(b >= 0) & (c >= 0) & (d >= 0)] = 0.0
        bound[~np.isfinite(bound)] = np.inf  # non-finite coefficients: always solved
    return first_sign_change(b, c, d, bound)


def first_sign_change(b: np.ndarray, c: np.ndarray, d: np.ndarray, bound: np.ndarray) -> float:
    """`max_feasible_step_3d`'s α from each element's cubic coefficients b, c, d and root bound (all (M,)),
    whichever pass computed them (numpy above, or `compiled3d.feasibility_cubic_3d`)."""
    if bound.size > _FIRST_SOLVED:  # the largest bounds, in no order (a partition, not a sort: only the set matters)
        order = np.argpartition(-bound, _FIRST_SOLVED - 1)
    else:
        order = np.arange(bound.size)
    first = order[:_FIRST_SOLVED][bound[order[:_FIRST_SOLVED]] > 0]
    top = _largest_positive_root(b[first], c[first], d[first])
    rest = order[_FIRST_SOLVED:]
    rest = rest[bound[rest] * (1.0 + 1e-8) >= top]
    rest = rest[bound[rest] > 0]
    top = max(top, _largest_positive_root(b[rest], c[rest], d[rest]))
    return float("inf") if top <= 0 else 1.0 / top


#: elements whose cubic `max_feasible_step_3d` solves before it bounds the rest
_FIRST_SOLVED = 512


def _largest_positive_root(b: np.ndarray, c: np.ndarray, d: np.ndarray) -> float:
    """The largest positive (numerically) real root of β³ + b β² + c β + d over all rows (0 if none)."""
    if len(b) == 0:
        return 0.0
    comp = np.zeros((len(b), 3, 3))
    comp[:, 0, 0], comp[:, 0, 1], comp[:, 0, 2] = -b, -c, -d
    comp[:, 1, 0] = comp[:, 2, 1] = 1.0
    beta = np.linalg.eigvals(comp)  # (K, 3)
    real = np.abs(beta.imag) <= 1e-6 * np.maximum(np.abs(beta), 1e-300)
    br = np.where(real & (beta.real > 0), beta.real, 0.0)
    return float(br.max())


def _feasibility_cubic(F: np.ndarray, dF: np.ndarray) -> tuple:
    """b, c, d (M,) of det(F + α dF) = J (1 + b α + c α² + d α³); F, dF (M, 3, 3).

    Plain arithmetic on the nine components (J and det dF by their
    cofactors' first rows): faster than np.linalg.det and np.cross on (M, 3, 3) stacks.
    """
    f = [[np.ascontiguousarray(F[:, i, j]) for j in range(3)] for i in range(3)]
    g = [[np.ascontiguousarray(dF[:, i, j]) for j in range(3)] for i in range(3)]
    cof_f, cof_g = _cofactor_rows(f), _cofactor_rows(g)
    J = f[0][0] * cof_f[0][0] + f[0][1] * cof_f[0][1] + f[0][2] * cof_f[0][2]
    det_g = g[0][0] * cof_g[0][0] + g[0][1] * cof_g[0][1] + g[0][2] * cof_g[0][2]
    b = sum(cof_f[i][j] * g[i][j] for i in range(3) for j in range(3)) / J
    c = sum(f[i][j] * cof_g[i][j] for i in range(3) for j in range(3)) / J
    return b, c, det_g / J


def _cofactor_rows(a: list) -> list:
    """cof A as nested lists of component arrays, for A given as a[i][j] (M,) arrays."""
    def cross(u, v):
        return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]
    return [cross(a[1], a[2]), cross(a[2], a[0]), cross(a[0], a[1])]
