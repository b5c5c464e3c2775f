"""A Newton step without assembling the Hessian: conjugate gradients on a kept factor, H v by differences.

A 3-D Newton step is first solved by conjugate gradients preconditioned
with the slot's last factorisation (`solvers.newton`, `linear.solve_free`),
and conjugate gradients only ever needs the Hessian H times a vector.
Assembling H for that costs more than the whole solve: the element
Hessians, the nodal element's two-ring coupling and the scatter into K_ff
(docs/model.md §13, "Steps without the Hessian"). Here H v is a
difference of the gradient along v, one compiled pass over the elements
per gradient:

    H v ≈ (∇Φ(x + h v) − ∇Φ(x)) / h            (forward: ∇Φ(x) is known)
    H v ≈ (∇Φ(x + h v) − ∇Φ(x − h v)) / 2h     (central)

The forward one's error is O(h) from the second derivative plus
O(ε ‖∇Φ‖ / h) from round-off, the central one's O(h²) plus the same
round-off. With the largest nodal move h ‖v‖_∞ = FORWARD_STEP_MM or
CENTRAL_STEP_MM each stays decades below the forcing term it serves: the
forward difference for forcing terms from FORWARD_FORCING up (most of a
settle's steps), the central one below, down to SMALLEST_FORCING
(`tests/test_hessian_free.py` checks both against the assembled K_ff).
The operator only shapes the step: the equilibrium is judged on the true
gradient, so its error can cost iterations but never accuracy. Only when
this fails (the factor is stale, conjugate gradients does not converge,
meets negative curvature or a non-finite gradient) is H assembled and the
step solved as before.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.common import Inertia, objective_gradient
from scissor_cli.solvers.held import Held
from scissor_cli.solvers.linear import KRYLOV_MAX_ITER, preconditioned_cg

#: the largest nodal move (mm) of a forward and of a central difference quotient, against the meshes' smallest
#: edges (0.5–10 mm): the forward one's truncation and round-off meet near 1e-7 of ‖H v‖, the central one's lower
FORWARD_STEP_MM = 1e-6
CENTRAL_STEP_MM = 1e-5
#: the forward difference serves forcing terms from this one up, the central one those below
FORWARD_FORCING = 1e-5
#: no difference serves a forcing term below this one: there the assembled H is used (the central difference's
#: error reached 1e-8 of ‖H v‖ on the slab's smooth directions, where conjugate gradients steps)
SMALLEST_FORCING = 1e-6


def hessian_times(tissue: Tissue, x: np.ndarray, grad: np.ndarray | None, inertia: Inertia | None,
                  loads: np.ndarray | None, held: Held) -> Callable[[np.ndarray], np.ndarray]:
    """v ↦ H v for v (Nf,) in `held`'s coordinates: the system `newton_iterations` solves at x (N, d) mm.

    As the assembled system there: the rotated, held-zeroed Hessian of Φ
    (strain energy, inertia, loads) on the free dofs, with identity rows
    and columns for the held ones (`Held.matrix`). mN/mm. With grad (dN,),
    ∇Φ at x, a forward difference; without it (None) a central one.
    """
    free = tissue.free_dofs
    base = x.ravel()
    at_x = None if grad is None else grad[free]  # (the forward difference's base, taken once)

    def gradient_at(step: np.ndarray) -> np.ndarray:
        return objective_gradient(tissue, (base + step).reshape(x.shape), inertia, loads)[1][free]

    def times(v: np.ndarray) -> np.ndarray:
        moved = v.copy()
        moved[held.pos] = 0.0  # the held components: the identity's, added back below
        step = np.zeros(base.size)
        step[free] = held.unrotate(moved)
        largest = float(np.max(np.abs(step)))
        if largest == 0.0:
            return v - moved
        if at_x is not None:
            h = FORWARD_STEP_MM / largest
            change = (gradient_at(h * step) - at_x) / h
        else:
            h = CENTRAL_STEP_MM / largest
            change = (gradient_at(h * step) - gradient_at(-h * step)) / (2.0 * h)
        return held.vector(change) + (v - moved)

    return times


def hessian_free_step(tissue: Tissue, x: np.ndarray, grad: np.ndarray, g: np.ndarray, inertia: Inertia | None,
                      loads: np.ndarray | None, held: Held, factors: dict, rtol: float) -> np.ndarray | None:
    """The Newton step d (Nf,) (held coordinates) with ‖H d + g‖ ≤ rtol ‖g‖, or None.

    grad (dN,) is ∇Φ at x, g (Nf,) its reduced form (`held.vector` of
    grad's free part). None when the slot holds no usable factor (none, not
    Cholesky, stale), rtol is below SMALLEST_FORCING, or conjugate
    gradients fails; also when d is not a descent direction. A failure to
    converge within the iterations marks the factor stale, so the assembled
    step that follows factors at once instead of iterating again; the
    others (negative curvature, a residual the operator's error kept from
    its target, a non-finite gradient) leave the factor to the assembled
    step's own conjugate gradients.
    """
    factor = factors.get("free")
    if rtol < SMALLEST_FORCING or factor is None or factor.method != "cholesky" or factor.stale:
        return None
    times = hessian_times(tissue, x, grad if rtol >= FORWARD_FORCING else None, inertia, loads, held)
    d, _, why = preconditioned_cg(times, g, factor, rtol, KRYLOV_MAX_ITER)
    if d is None:
        factor.stale = why == "iterations"
        return None
    d = -d
    return d if np.all(np.isfinite(d)) and np.dot(g, d) < 0 else None
