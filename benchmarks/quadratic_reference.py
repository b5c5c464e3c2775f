"""The quadratic-element reference of the element studies (docs/model.md §21): an independent scikit-fem solve.

Linear elasticity (plane strain in 2-D) on scissor's own mesh with 6-node
triangles or 10-node tetrahedra (scikit-fem's P2, the same straight-sided
simplices), the same held and cup nodes: a node scissor holds is held here,
and so is the midpoint of every edge whose two ends it holds (component by
component, at their mean displacement: a cup moves its patch rigidly). Nothing of scissor's
mechanics is used, so the comparison is between two codes, not one code
with itself.

Quadratic displacements alone lock too as ν → 1/2 (in 3-D a 10-node
tetrahedron's divergence has nearly as many constraints as the mesh has
unknowns), so `solve_mixed` gives the locking-free reference beside it:
Taylor–Hood, the same P2 displacements with a continuous P1 pressure
(Herrmann's mixed u–p form), its pressure solved by scipy's conjugate
gradients on the Schur complement with the displacement block's Cholesky
factor.
Loaded by benchmarks/bench_elements.py and the element tests
(tests/test_elements.py) as a module; needs the `bench` or `test` extra.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def mesh_and_held(tissue) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(nodes (N, d), cells (M, d+1), held (N, d) bool) of a scissor tissue: its mesh and the dofs it holds, as
    this module's solves take them."""
    held = np.zeros(tissue.rest.size, bool)
    held[tissue.dirichlet_dofs] = True
    return tissue.mesh.nodes, tissue.ops.triangles, held.reshape(-1, tissue.dim)


def solve_p2(nodes: np.ndarray, cells: np.ndarray, held: np.ndarray, displacement: np.ndarray,
             E_kPa: np.ndarray | float, nu: float, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P2 linear elasticity with the vertex dofs `held` (N, d) bool held at `displacement` (N, d) mm; E per
    element (M,) or one value, ν one value; plane strain in 2-D. Returns the displacements (N, d) mm of the
    vertices and (K, d) of `points` (K, d), the quadratic field evaluated there."""
    import skfem

    system = p2_system(nodes, cells, held, displacement, E_kPa, nu)
    basis, u = system.basis, system.u
    K = system.assemble()
    A, b, x, free = skfem.condense(K, np.zeros(K.shape[0]), x=u, D=system.held_dofs)
    u[free] = _cholesky(A)(b)
    return _at_vertices_and_points(basis, u, points)


def _at_vertices_and_points(basis, u: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The P2 field u (n_dofs,) mm at the mesh's vertices (N, d) and at `points` (K, d)."""
    at_points = np.column_stack([part.probes(points.T) @ u[index]
                                 for part, index in zip(basis.split_bases(), basis.split_indices())])
    return u[basis.nodal_dofs.T].copy(), at_points


#: the mixed solve's pressure: conjugate gradients on its Schur complement to this relative residual
MIXED_RTOL = 1e-12
MIXED_MAX_ITER = 500


@dataclass
class MixedSolve:
    """What `solve_mixed` did: the displacements (N, d) mm at the vertices and (K, d) at the points, the Schur
    complement's CG iterations, and the pressure (n_p,) kPa at the vertices."""

    vertices: np.ndarray
    at_points: np.ndarray
    iterations: int
    pressure: np.ndarray


def solve_mixed(nodes: np.ndarray, cells: np.ndarray, held: np.ndarray, displacement: np.ndarray,
                E_kPa: np.ndarray | float, nu: float, points: np.ndarray) -> MixedSolve:
    """Taylor–Hood (P2 displacements, continuous P1 pressure) linear elasticity, held as `solve_p2` holds.

    Herrmann's form: find u, p with
        ∫ 2μ ε(u):ε(v) + ∫ p div v = 0,   ∫ q div u − ∫ p q / λ = 0,
    the energy μ ε:ε + λ/2 (div u)² with p = λ div u, which stays well posed as λ → ∞: the pressure is
    one unknown a vertex, not a constraint a tetrahedron. With A the first form on the free dofs, B the
    divergence and C = ∫ p q / λ, the pressure solves (C + B A⁻¹ Bᵀ) p = B A⁻¹ f − g by scipy's conjugate
    gradients preconditioned with the pressure mass matrix weighted by 1/λ + 1/μ (spectrally equivalent to the
    Schur complement for every ν: the iterations do not grow as ν → 1/2), each iteration one solve with A's
    Cholesky factor; then A u = f − Bᵀ p. Raises RuntimeError when CG does not reach MIXED_RTOL.
    """
    from scipy.sparse.linalg import LinearOperator, cg, splu

    system = mixed_system(nodes, cells, held, displacement, E_kPa, nu)
    A, B, C, weighted_mass = system.assemble()
    u, held_dofs, free = system.p2.u, system.p2.held_dofs, system.free
    f = -(A[free][:, held_dofs] @ u[held_dofs])
    g = -(B[:, held_dofs] @ u[held_dofs])
    solve_A = _cholesky(A[free][:, free])
    B_free = B[:, free]
    n_p = B.shape[0]
    mass = splu(weighted_mass.tocsc())
    schur = LinearOperator((n_p, n_p), matvec=lambda q: C @ q + B_free @ solve_A(B_free.T @ q), dtype=float)
    preconditioner = LinearOperator((n_p, n_p), matvec=mass.solve, dtype=float)
    iterations = [0]

    def count(_):
        iterations[0] += 1

    p, info = cg(schur, B_free @ solve_A(f) - g, rtol=MIXED_RTOL, maxiter=MIXED_MAX_ITER, M=preconditioner,
                 callback=count)
    if info != 0:
        raise RuntimeError(f"the mixed solve's pressure did not converge in {MIXED_MAX_ITER} CG iterations")
    u[free] = solve_A(f - B_free.T @ p)
    vertices, at_points = _at_vertices_and_points(system.p2.basis, u, points)
    return MixedSolve(vertices, at_points, iterations[0], p)


@dataclass
class MixedSystem:
    """Taylor–Hood on a mesh (`solve_mixed`): the displacement part as `p2_system` makes it, the pressure's P1
    basis, its forms and E (kPa) as a P0 field; `free` (n_free,) the displacement dofs not held."""

    p2: P2System
    pressure: object
    forms: tuple
    free: np.ndarray

    def assemble(self):
        """(A (n_u, n_u) mN/mm, B (n_p, n_u), C (n_p, n_p), the preconditioner's weighted mass (n_p, n_p)): the
        shear form, the divergence, the pressure's compliance ∫ p q / λ and ∫ p q (1/λ + 1/μ). The E field is
        at the displacement basis's quadrature points, which the pressure basis shares (one mesh, one order)."""
        shear, divergence, compliance, weighted_mass = self.forms
        E = self.p2.e_field
        return (shear.assemble(self.p2.basis, E=E).tocsr(), divergence.assemble(self.p2.basis, self.pressure).tocsr(),
                compliance.assemble(self.pressure, E=E).tocsr(), weighted_mass.assemble(self.pressure, E=E).tocsr())


def mixed_system(nodes: np.ndarray, cells: np.ndarray, held: np.ndarray, displacement: np.ndarray,
                 E_kPa: np.ndarray | float, nu: float) -> MixedSystem:
    """The Taylor–Hood system of `solve_mixed` before it is solved (benchmarks/bench_elements.py times its cost)."""
    import skfem
    from skfem.helpers import div
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    p2 = p2_system(nodes, cells, held, displacement, E_kPa, nu)
    pressure = skfem.Basis(p2.basis.mesh, skfem.ElementTriP1() if nodes.shape[1] == 2 else skfem.ElementTetP1(),
                           intorder=2)
    lam1, mu1 = lame_parameters(1.0, nu)  # per unit E: the forms scale by E (λ and μ both ∝ E at one ν)

    @skfem.BilinearForm
    def shear(u, v, w):
        return w["E"] * linear_elasticity(0.0, mu1).form(u, v, w)

    @skfem.BilinearForm
    def divergence(u, q, w):
        return div(u) * q

    @skfem.BilinearForm
    def compliance(p, q, w):
        return p * q / (lam1 * w["E"])

    @skfem.BilinearForm
    def weighted_mass(p, q, w):
        return p * q * (1.0 / lam1 + 1.0 / mu1) / w["E"]

    free = np.setdiff1d(np.arange(p2.basis.N), p2.held_dofs)
    return MixedSystem(p2, pressure, (shear, divergence, compliance, weighted_mass), free)


@dataclass
class P2System:
    """P2 linear elasticity on a mesh: its basis, the stiffness form and E (kPa) as a P0 field it takes, the held
    dofs (H,) and their values in u (n_dofs,) mm, and each dof's node (n_dofs,): a vertex's index, or N + its
    edge's (facet's in 2-D)."""

    basis: object
    form: object
    e_field: object
    held_dofs: np.ndarray
    u: np.ndarray
    node_of_dof: np.ndarray

    def assemble(self):
        """K (n_dofs, n_dofs) in mN/mm (E in kPa, lengths in mm)."""
        return self.form.assemble(self.basis, E=self.e_field)


def p2_system(nodes: np.ndarray, cells: np.ndarray, held: np.ndarray, displacement: np.ndarray,
              E_kPa: np.ndarray | float, nu: float) -> P2System:
    """The P2 system of `solve_p2` before it is solved (benchmarks/bench_elements.py times its cost)."""
    import skfem
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    d = nodes.shape[1]
    if d == 2:
        mesh = skfem.MeshTri(nodes.T.copy(), cells.T.copy())
        element = skfem.ElementVector(skfem.ElementTriP2())
    else:
        mesh = skfem.MeshTet(nodes.T.copy(), cells.T.copy())
        element = skfem.ElementVector(skfem.ElementTetP2())
    basis = skfem.Basis(mesh, element, intorder=2)
    E = np.broadcast_to(np.asarray(E_kPa, float), (cells.shape[0],))
    lam1, mu1 = lame_parameters(1.0, nu)
    # E per element as a P0 field: the bilinear form scales by it
    e_field = skfem.Basis(mesh, skfem.ElementTriP0() if d == 2 else skfem.ElementTetP0(), intorder=2).interpolate(E)

    @skfem.BilinearForm
    def stiffness(u, v, w):
        return w["E"] * linear_elasticity(lam1, mu1).form(u, v, w)

    n_dofs = basis.N
    u = np.zeros(n_dofs)
    vertex_dofs = basis.nodal_dofs.T  # (N, d)
    fixed = [vertex_dofs[held]]
    u[vertex_dofs[held]] = displacement[held]
    edges = (mesh.facets if d == 2 else mesh.edges).T  # (n_edges, 2)
    edge_dofs = (basis.facet_dofs if d == 2 else basis.edge_dofs).T  # (n_edges, d)
    both = held[edges[:, 0]] & held[edges[:, 1]]  # (n_edges, d): a component held at both ends
    mid = 0.5 * (displacement[edges[:, 0]] + displacement[edges[:, 1]])
    fixed.append(edge_dofs[both])
    u[edge_dofs[both]] = mid[both]
    node_of_dof = np.empty(n_dofs, np.int64)
    node_of_dof[vertex_dofs] = np.arange(len(nodes))[:, None]
    node_of_dof[edge_dofs] = len(nodes) + np.arange(len(edges))[:, None]
    return P2System(basis, stiffness, e_field, np.concatenate(fixed), u, node_of_dof)


def _cholesky(A):
    """b ↦ A⁻¹ b for the symmetric positive definite A, factored once (CHOLMOD through cvxopt: SuperLU takes
    minutes at 3-D sizes)."""
    import cvxopt
    from cvxopt import cholmod

    A = A.tocoo()
    lower = A.row >= A.col
    M = cvxopt.spmatrix(A.data[lower], A.row[lower].astype(int), A.col[lower].astype(int), A.shape)
    factor = cholmod.symbolic(M)
    cholmod.numeric(M, factor)

    def solve(b: np.ndarray) -> np.ndarray:
        x = cvxopt.matrix(np.asarray(b, float).reshape(-1, 1))
        cholmod.solve(factor, x)
        return np.array(x).ravel()

    return solve
