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

import numpy as np


def solve_p2(nodes: np.ndarray, cells: np.ndarray, held: np.ndarray, displacement: np.ndarray,
             E_kPa: np.ndarray | float, nu: float, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P2 linear elasticity with the vertex dofs `held` (N, d) bool held at `displacement` (N, d) mm; E per
    element (M,) or one value, ν one value; plane strain in 2-D. Returns the displacements (N, d) mm of the
    vertices and (K, d) of `points` (K, d), the quadratic field evaluated there."""
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

    K = stiffness.assemble(basis, E=e_field)
    n_dofs = K.shape[0]
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
    D = np.concatenate(fixed)
    A, b, x, free = skfem.condense(K, np.zeros(n_dofs), x=u, D=D)
    u[free] = _cholesky_solve(A, b)
    at_points = np.column_stack([part.probes(points.T) @ u[index]
                                 for part, index in zip(basis.split_bases(), basis.split_indices())])
    return u[vertex_dofs].T.copy(), at_points


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
