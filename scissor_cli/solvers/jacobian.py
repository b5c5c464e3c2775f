"""The quasi-static Jacobian between cup strokes and target positions (docs/model.md §5).

At an equilibrium x⁰ the linearised response of the free nodes to a small
cup motion δs solves

    K_ff δx_f = −K_fc B δs,     δx_c = B δs,     δx_fixed = 0,

and the targets follow their rest triangles, δx_t = S_t δx. Hence

    J = S_t [ B ; −K_ff⁻¹ K_fc B ]    (2K × C, mm/mm),

which is −S_t K_ff⁻¹ K_fc B when no target's element touches a gripped node
and, when one does, also carries the gripped node's own motion B δs.

K is the exact Hessian of the strain energy, not the PSD-projected one used
far from convergence by Newton: J is a derivative of the equilibrium map and
only the exact tangent gives it. One sparse factorisation of K_ff serves all cups.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import TargetProbe, apply_probe
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.linear import Factorization, factorize_free


def nodal_response(
    tissue: Tissue, x: np.ndarray, factor: Factorization | None = None
) -> tuple[np.ndarray, Factorization]:
    """∂x/∂s (dN, C) in mm/mm at the equilibrium x (N, d), d = 2 or 3, and the factorisation of K_ff.

    Column c is the first-order displacement of every dof for a unit stroke of
    cup c: the cup's axis on its gripped nodes, zero on fixed ones and
    −K_ff⁻¹ K_fc B e_c on the free ones. K_ff is factored from its upper
    triangle (`linear.factorize_free`, in a slot of its own); `factor`, if
    given (one this function returned), is refactored in place instead (same
    sparsity pattern on every call, so the symbolic analysis is reused) and
    returned. Raises SolverError if K_ff is singular (a buckling
    point) or the response is not finite.
    """
    x = np.asarray(x, float)
    Ke = tissue.element_stiffness(x)  # the exact element Hessians, for K_ff and each cup's K b alike
    K = tissue.stiffness_free(x, Ke=Ke, upper=True)
    if factor is not None:
        factor.refactor(K)
    else:
        try:  # the solvers' own factorisation: in 3-D nested dissection, its ordering cached per pattern
            factor = factorize_free(tissue, K, {})
        except SolverError:  # not positive definite (a buckling point): LDLᵀ
            factor = Factorization(K, upper=True)
    free = tissue.free_dofs
    D = np.zeros((tissue.dim * tissue.mesh.n_nodes, tissue.n_cups))
    for c in range(tissue.n_cups):
        b = tissue.cup_displacement(c)  # zero on free and fixed dofs
        # K b restricted to free rows is K_fc B e_c: b vanishes outside the cup's dofs.
        rhs = -tissue.stiffness_times(x, b, Ke)[free]
        D[:, c] = b
        D[free, c] = factor.solve(rhs)
    if not np.all(np.isfinite(D)):
        raise SolverError("the cup response became non-finite (K_ff singular at this equilibrium?)")
    return D, factor


def cup_target_jacobian(
    tissue: Tissue, x: np.ndarray, probe: TargetProbe, factor: Factorization | None = None
) -> np.ndarray:
    """J = ∂x_t/∂s (dK, C) in mm/mm at the equilibrium x (N, d), d = 2 or 3.

    Rows are [t0x, t0y, (t0z,) t1x, ...], columns the cups in scene order.
    Pass an existing `factor` (e.g. from `nodal_response`) to reuse its
    symbolic analysis across control steps; it is refactored in place.
    """
    D, _ = nodal_response(tissue, x, factor)
    return apply_probe(probe, D, tissue.dim)
