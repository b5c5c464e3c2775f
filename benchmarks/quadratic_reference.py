"""The quadratic-element reference of the element studies (docs/model.md §21): an independent scikit-fem solve.

Linear elasticity (plane strain in 2-D) on scissor's own mesh with 6-node
triangles or 10-node tetrahedra (scikit-fem's P2, the same straight-sided
simplices), the same held and cup nodes: a node scissor holds is held here,
and so is the midpoint of every edge whose two ends it holds (component by
component, at their mean displacement: a cup moves its patch rigidly). Nothing of scissor's
mechanics is used, so the comparison is between two codes, not one code
with itself. Loaded by benchmarks/bench_elements.py and the element tests
(tests/test_elements.py) as a module; needs the `bench` or `test` extra.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
    u[free] = _cholesky_solve(A, b)
    at_points = np.column_stack([part.probes(points.T) @ u[index]
                                 for part, index in zip(basis.split_bases(), basis.split_indices())])
    return u[basis.nodal_dofs.T].T.copy(), at_points


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


def _cholesky_solve(A, b: np.ndarray) -> np.ndarray:
    """A⁻¹ b for the symmetric positive definite A (CHOLMOD through cvxopt: SuperLU takes minutes at 3-D sizes)."""
    import cvxopt
    from cvxopt import cholmod

    A = A.tocoo()
    lower = A.row >= A.col
    M = cvxopt.spmatrix(A.data[lower], A.row[lower].astype(int), A.col[lower].astype(int), A.shape)
    x = cvxopt.matrix(np.asarray(b, float).reshape(-1, 1))
    cholmod.linsolve(M, x)
    return np.array(x).ravel()
