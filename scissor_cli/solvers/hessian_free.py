"""A Newton step without assembling the Hessian: conjugate gradients on a kept factor, H v by differences.

A 3-D Newton step is first solved by conjugate gradients preconditioned
with the slot's last factorisation (`solvers.newton`, `linear.solve_free`),
and conjugate gradients only ever needs the Hessian H times a vector.
Assembling H for that costs more than the whole solve: the element
Hessians, the nodal element's two-ring coupling and the scatter into K_ff
(docs/model.md §13, "Steps without the Hessian"). Here H v is the
central difference of the gradient along v,

    H v ≈ (∇Φ(x + h v) − ∇Φ(x − h v)) / 2h,

two gradient evaluations (one compiled pass over the elements each). Its
error is O(h²) from the third derivative plus O(ε ‖∇Φ‖ / h) from
round-off; with the largest nodal move h ‖v‖_∞ = DIFFERENCE_STEP_MM both
stay decades below the forcing terms the inexact Newton step asks of
conjugate gradients (`tests/test_hessian_free.py` checks the operator
against the assembled K_ff). Only when this fails (the factor is stale,
conjugate gradients does not converge, meets negative curvature or a
non-finite gradient) is H assembled and the step solved as before.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.common import Inertia, objective_gradient
from scissor_cli.solvers.held import Held
from scissor_cli.solvers.linear import KRYLOV_MAX_ITER, preconditioned_cg

#: the largest nodal move (mm) of a difference quotient: ~1e-5 of the meshes' smallest edges (0.5–10 mm), so
#: the O(h²) truncation and the O(ε/h) round-off are both below 1e-9 of ‖H v‖
DIFFERENCE_STEP_MM = 1e-5
#: the step is tried only for forcing terms at least this large: below it the difference's error would be
#: a sizeable part of what conjugate gradients is asked to resolve, and the assembled H is used
SMALLEST_FORCING = 1e-8


def hessian_times(tissue: Tissue, x: np.ndarray, inertia: Inertia | None, loads: np.ndarray | None,
                  held: Held) -> Callable[[np.ndarray], np.ndarray]:
    """v ↦ H v for v (Nf,) in `held`'s coordinates: the system `newton_iterations` solves at x (N, d) mm.

    As the assembled system there: the rotated, held-zeroed Hessian of Φ
    (strain energy, inertia, loads) on the free dofs, with identity rows
    and columns for the held ones (`Held.matrix`). mN/mm.
    """
    free = tissue.free_dofs
    base = x.ravel()

    def times(v: np.ndarray) -> np.ndarray:
        moved = v.copy()
        moved[held.pos] = 0.0  # the held components: the identity's, added back below
        step = np.zeros(base.size)
        step[free] = held.unrotate(moved)
        largest = float(np.max(np.abs(step)))
        if largest == 0.0:
            return v - moved
        h = DIFFERENCE_STEP_MM / largest
        _, g_plus = objective_gradient(tissue, (base + h * step).reshape(x.shape), inertia, loads)
        _, g_minus = objective_gradient(tissue, (base - h * step).reshape(x.shape), inertia, loads)
        return held.vector((g_plus - g_minus)[free] / (2.0 * h)) + (v - moved)

    return times


def hessian_free_step(tissue: Tissue, x: np.ndarray, g: np.ndarray, inertia: Inertia | None,
                      loads: np.ndarray | None, held: Held, factors: dict, rtol: float) -> np.ndarray | None:
    """The Newton step d (Nf,) (held coordinates) with ‖H d + g‖ ≤ rtol ‖g‖, or None.

    g (Nf,) is the reduced gradient at x (`held.vector` of ∇Φ_f). None when
    the slot holds no usable factor (none, not Cholesky, stale), rtol is
    below SMALLEST_FORCING, or conjugate gradients fails (then the factor is
    marked stale unless H met negative curvature, so the assembled step that
    follows factors at once instead of iterating again); also when d is not
    a descent direction.
    """
    factor = factors.get("free")
    if rtol < SMALLEST_FORCING or factor is None or factor.method != "cholesky" or factor.stale:
        return None
    d, _, why = preconditioned_cg(hessian_times(tissue, x, inertia, loads, held), g, factor, rtol,
                                  KRYLOV_MAX_ITER)
    if d is None:
        factor.stale = why != "curvature"  # (negative curvature: the assembled H decides how to step)
        return None
    d = -d
    return d if np.all(np.isfinite(d)) and np.dot(g, d) < 0 else None
