"""Newton's method on the tissue energy: the exact reference, and the one Newton loop (docs/model.md §4).

Far from the solution the Hessian is PSD-projected per element, so every
step is a descent direction; near it (relative residual below
`exact_below`) the exact Hessian takes over and convergence ends quadratic.
A backtracking line search keeps every element's J > 0 and decreases Φ.

The start matters for large strokes: placing the cup nodes and leaving the
rest at the old state can invert the elements next to the cup. So a solve
starts from a tangent predictor (the linearised response to the stroke
increment) and, if even that inverts an element, splits the stroke
increment into steps (load continuation).

This is the only Newton iteration in scissor: forward cases, the planner,
trials and the controller's incremental tracker (`solvers.tracking`) all
run `newton_iterations`. External loads and extra held dofs come in as
`Conditions`; held dofs keep the pattern of K_ff (their rows and columns
become identity rows), so a factorisation's symbolic analysis is reused.
Callers normally go through `solvers.equilibrium.solve_equilibrium`.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.common import (
    NO_CONDITIONS,
    Conditions,
    Inertia,
    SolverError,
    SolveResult,
    check_finite,
    objective_gradient,
)
from scissor_cli.solvers.held import Held as _Held
from scissor_cli.solvers.hessian_free import hessian_free_step
from scissor_cli.solvers.linear import KRYLOV_MAX_ITER, NotPositiveDefinite, factorize_free, solve_free, stepping_solve

ARMIJO = 1e-4
#: a full step whose Φ decrease reaches this fraction of the linear prediction
#: (a Newton step on a quadratic reaches 1/2) is tried longer
EXTRAPOLATE_RATIO = 0.9
MAX_EXTRAPOLATION = 64.0
#: an intermediate load step goes this far towards the first inverted element
STEP_FRACTION = 0.7
#: and is solved to this relative residual only: it is the next predictor's start, and that predictor corrects its
#: residual (benchmarks/bench_continuation.py: tighter settles cost iterations and factorisations, not substeps)
SUBSTEP_TOL = 1e-3
#: a load step below this fraction of the remaining increment ends the continuation: the path has met a stroke
#: where an element inverts whatever the path (the feasible fraction then shrinks about 3× a step, and each step
#: is a Newton solve at a nearly singular state), not a detour it can go round
SMALLEST_LOAD_STEP = 1e-3
#: a chord step (the last factorisation reused) is kept when it shrinks the residual this much
CHORD_CONTRACTION = 0.3
#: chord steps only far from the solution: the last steps are full Newton steps
CHORD_ABOVE = 1e-3
#: with `krylov` (3-D), a Newton step solves K d = −g only to ‖K d + g‖ ≤ η ‖g‖,
#: η = min(KRYLOV_FORCING, relative residual): inexact Newton, still quadratic at the end
KRYLOV_FORCING = 1e-2
#: and the tangent predictor to this relative residual
PREDICTOR_RTOL = 1e-4
#: without `krylov` (2-D), a step first runs conjugate gradients on the previous step's factor
#: when that full step shrank the residual this much: the residual a step on K_k leaves is
#: (K̄ − K_k) d, so a small one says K_k still models the tangent (`_reuse_forcing`)
KRYLOV_CONTRACTION = 0.25
#: at most this many iterations (a 2-D factorisation costs about 7 of them at 16k unknowns)
KRYLOV_MAX_ITER_2D = 6
#: to Eisenstat–Walker's forcing term η = EW_GAMMA θ², at most KRYLOV_FORCING_MAX_2D
EW_GAMMA = 0.9
KRYLOV_FORCING_MAX_2D = 0.1
#: with `krylov` (3-D), an exact Hessian that is not positive definite near the solution (relative residual
#: below SHIFT_BELOW) is first shifted, K + μ k̄ I (k̄ its mean diagonal), μ the first of SHIFTS that
#: factors: projecting every tetrahedron's Hessian on its eigenvalues costs ~2 factorisations, and its
#: steps crawled through the indefinite states at a cup's rim (twice the Newton iterations of the shifted
#: Hessian on one settle of the paper's slab; benchmarks/bench_slab_truth.py). Farther out the projected
#: Hessian stays first: there the shifted one's steps stalled.
SHIFTS = (1e-4, 1e-3, 1e-2, 1e-1)
SHIFT_BELOW = 1e-2
#: with `krylov` (3-D), a step near the solution is first solved without assembling the Hessian
#: (`solvers.hessian_free`); off, every such step assembles K_ff (for A/B runs: benchmarks/ab_trials.py)
HESSIAN_FREE = True


def krylov_default(tissue: Tissue, krylov: bool | None) -> bool:
    """Whether steps first try conjugate gradients on the last factor (default: in 3-D, where factoring dominates)."""
    return tissue.dim == 3 if krylov is None else krylov


def tangent_predictor(
    tissue: Tissue,
    x: np.ndarray,
    strokes: np.ndarray,
    inertia: Inertia | None = None,
    conditions: Conditions = NO_CONDITIONS,
    factors: dict | None = None,
    krylov: bool | None = None,
) -> np.ndarray:
    """First-order response of the free nodes when the Dirichlet nodes move to `strokes`.

    x (N, 2) is an equilibrium (or the rest state); returns positions (N, 2)
    with K_ff δx_f = −K_fd δx_d − ∇Φ_f(x) solved at x's tangent (held dofs
    stay). `factors` is the slot of the reusable factorisation (default: the
    tissue's shared one); with `krylov` (default in 3-D) the slot's earlier
    factor preconditions conjugate gradients to PREDICTOR_RTOL first.
    """
    held = _Held(tissue, conditions)
    x_new = tissue.apply_strokes(x, strokes)
    delta = (x_new - x).ravel()
    U, grad_U, Ke = tissue.energy_gradient_stiffness(x)  # one pass over the elements for both
    _, grad = objective_gradient(tissue, x, inertia, conditions.loads, strain=(U, grad_U))
    rhs = -tissue.stiffness_times(x, delta, Ke)[tissue.free_dofs] - grad[tissue.free_dofs]
    if inertia is not None:
        rhs -= inertia.weight[tissue.free_dofs] * delta[tissue.free_dofs]
    rhs = held.vector(rhs)
    # The exact tangent of a stable equilibrium is positive definite; the
    # per-element projection only where it is not (the factorisation says).
    dx = None
    rtol = PREDICTOR_RTOL if krylov_default(tissue, krylov) else None
    for project in (False, True):
        K = _system(tissue, x, project, inertia, held, None if project else Ke)
        try:
            dx = held.unrotate(solve_free(tissue, K, rhs, factors, rtol)[0])
        except SolverError:
            continue
        if np.all(np.isfinite(dx)):
            break
    if dx is None or not np.all(np.isfinite(dx)):
        raise SolverError("the tangent predictor found no positive definite stiffness "
                          "(is a part of the layer unconstrained?)")
    flat = x_new.ravel().copy()
    flat[tissue.free_dofs] += dx
    return flat.reshape(x_new.shape)


def _reuse_forcing(factors: dict, res: float, previous: float) -> float | None:
    """The forcing term of a 2-D step by CG on the slot's factor, or None when that is not expected to pay.

    Eisenstat–Walker's choice 2, η = 0.9 θ² (θ = res / previous, the last
    step's contraction; at most KRYLOV_FORCING_MAX_2D): a Newton step leaves
    about θ² of its residual, so solving further buys nothing (16k, 5 mm:
    θ = 0.2, η = 0.037, 3 CG iterations instead of 4); η falls with θ², so
    the end stays quadratic. None when the factor's measured rate cannot
    reach η within KRYLOV_MAX_ITER_2D (before its first such solve it can).
    """
    eta = min(KRYLOV_FORCING_MAX_2D, EW_GAMMA * (res / previous) ** 2)
    factor = factors.get("free")
    return eta if factor is not None and factor.cg_iterations_for(eta) <= KRYLOV_MAX_ITER_2D else None


def _factor_count(tissue: Tissue, factors: dict | None) -> int:
    """Numeric factorisations so far of the slot's factor (0 before the first)."""
    factor = (tissue.factor_cache if factors is None else factors).get("free")
    return factor.factorizations if factor is not None else 0


def _system(tissue, x, project, inertia, held, Ke=None) -> sp.csr_matrix:
    """The upper triangle of K_ff (+ M/Δt²) at x, held rows made identity rows."""
    K = tissue.stiffness_free(x, project=project, Ke=Ke, upper=True)
    if inertia is not None:
        K = K + _diag(inertia.weight[tissue.free_dofs])
    return held.matrix(K)


def _diag(v: np.ndarray) -> sp.csr_matrix:
    return sp.diags(v, format="csr")


def newton_iterations(
    tissue: Tissue,
    x: np.ndarray,
    inertia: Inertia | None = None,
    tol: float = 1e-10,
    max_iter: int = 100,
    exact_below: float = 1.0,
    chord: bool = False,
    chord_above: float = CHORD_ABOVE,
    conditions: Conditions = NO_CONDITIONS,
    factors: dict | None = None,
    krylov: bool | None = None,
) -> SolveResult:
    """Newton from a feasible start x (N, 2) with the Dirichlet nodes already placed.

    With `chord`, while the relative residual is above `chord_above` a step
    first reuses the last factorisation (the predictor's or the previous
    iteration's) and is kept when it shrinks the residual by
    CHORD_CONTRACTION at full length; otherwise, and always below
    `chord_above`, K is refactored for a full Newton step, so convergence
    still ends quadratic. Above a relative residual of `exact_below` the Hessian is
    PSD-projected per element (far from equilibrium the exact one sends
    pull8 wandering); below it the exact one, falling back to the projected
    one when its step is not a descent direction — in 3-D near the solution
    first to the shifted one (SHIFTS, `_shifted_solve`). `conditions` adds loads and
    held dofs; `factors` is the factorisation slot (default: the tissue's).
    With `krylov` (default: a 3-D tissue) a step is first solved by
    conjugate gradients preconditioned with the slot's last factorisation,
    to the forcing term min(KRYLOV_FORCING, residual), and K is factored only
    when that fails (`linear.solve_free`): most 3-D steps need no
    factorisation. Without `krylov`, a step does the same (at most
    KRYLOV_MAX_ITER_2D iterations, to the forcing term `_reuse_forcing`)
    only when the previous step of this call was a full step that shrank the
    residual by KRYLOV_CONTRACTION and the factor's measured rate can still
    reach that term: the factor is then always one this call made. `factorizations` counts the
    factorisations.
    """
    t0 = time.perf_counter()
    factors = tissue.factor_cache if factors is None else factors
    held = _Held(tissue, conditions)
    x = np.array(x, dtype=float)
    phi, grad = objective_gradient(tissue, x, inertia, conditions.loads)
    history = []
    free = tissue.free_dofs
    n_factor = 0
    krylov = krylov_default(tissue, krylov)
    full_step = False  # the last step of this call was a full Newton step (not a chord step, not shortened)
    for it in range(max_iter + 1):
        check_finite(grad, "the Newton gradient")
        res = held.residual(tissue, grad)
        contracted = full_step and res <= KRYLOV_CONTRACTION * history[-1]
        history.append(res)
        if res <= tol:
            return SolveResult(x, True, it, res, time.perf_counter() - t0, "newton", "converged", history, n_factor)
        if it == max_iter:
            break
        g = held.vector(grad[free])
        if chord and res > chord_above and "free" in factors:
            kept = _chord_step(tissue, x, g, inertia, res, conditions, held, factors)
            if kept is not None:
                x, phi, grad = kept
                full_step = False
                continue
        step = None
        rtol = min(KRYLOV_FORCING, res) if krylov else None
        if contracted and not krylov:
            rtol = _reuse_forcing(factors, res, history[-2])
        if krylov and HESSIAN_FREE and res < exact_below:
            d = hessian_free_step(tissue, x, grad, g, inertia, conditions.loads, held, factors, rtol)
            step = None if d is None else held.unrotate(d)
        if step is None:
            step, factored = _assembled_step(tissue, x, g, res, res < exact_below, inertia, held, factors, rtol,
                                             krylov)
            n_factor += factored
        if step is None:
            raise SolverError(
                f"Newton found no descent direction at iteration {it} (residual {res:.3g})",
                SolveResult(x, False, it, res, time.perf_counter() - t0, "newton", "no descent direction", history,
                            n_factor),
            )
        x, phi, grad, alpha = _line_search(tissue, x, phi, grad, step, inertia, res, conditions.loads, held)
        full_step = alpha == 1.0
    return SolveResult(
        x, False, max_iter, history[-1], time.perf_counter() - t0, "newton",
        f"not converged in {max_iter} iterations (relative residual {history[-1]:.3g} > {tol:g})", history, n_factor,
    )


def _assembled_step(tissue, x, g, res, exact, inertia, held, factors, rtol, krylov) -> tuple[np.ndarray | None, int]:
    """(the Newton step (Nf,) or None, factorisations) on the assembled Hessian: the exact one first when
    `exact`, shifted in 3-D near the solution when it is not positive definite, else the PSD-projected one."""
    n_factor = 0
    cg_iter = KRYLOV_MAX_ITER if krylov else KRYLOV_MAX_ITER_2D
    for project in ([False, True] if exact else [True]):
        K = _system(tissue, x, project, inertia, held)
        try:
            d, factored = solve_free(tissue, K, g, factors, rtol, cg_iter)
        except NotPositiveDefinite as exc:  # an indefinite exact Hessian: shifted (3-D), then the projected one
            n_factor += exc.factored
            shifted = (_shifted_solve(tissue, K, g, factors) if krylov and not project and res < SHIFT_BELOW
                       else None)
            if shifted is None:
                continue
            d, factored = shifted  # (factored: the factorisations the shifts took)
        n_factor += factored
        d = -d
        if np.all(np.isfinite(d)) and np.dot(g, d) < 0:
            return held.unrotate(d), n_factor
    return None, n_factor


def _shifted_solve(tissue, K, g, factors) -> tuple[np.ndarray, int] | None:
    """(d, factorisations) with (K + μ k̄ I) d = g for the first μ in SHIFTS whose matrix factors, or None.

    The search starts one below the μ that factored last in this slot (`factors["shift"]`): along a
    move the states stay about as indefinite, and each μ that fails costs a factorisation.
    """
    kbar = float(np.mean(K.diagonal()))
    first = max(0, SHIFTS.index(factors["shift"]) - 1) if factors.get("shift") in SHIFTS else 0
    for tries, mu in enumerate(SHIFTS[first:], start=1):
        try:
            d = factorize_free(tissue, K + (mu * kbar) * sp.identity(K.shape[0], format="csr"), factors).solve(g)
        except SolverError:
            continue
        factors["shift"] = mu
        return d, tries
    return None


def _chord_step(tissue, x, g, inertia, res, conditions, held, factors):
    """A full step on the cached factorisation, if it is feasible and contracts the residual enough."""
    d = -stepping_solve(factors["free"])(g)
    if not np.all(np.isfinite(d)) or np.dot(g, d) >= 0:
        return None
    step = np.zeros(x.size)
    step[tissue.free_dofs] = held.unrotate(d)
    trial = x + step.reshape(x.shape)
    phi_t, grad_t = objective_gradient(tissue, trial, inertia, conditions.loads, require_positive_J=True)
    if grad_t is None:  # the step inverts an element
        return None
    if held.residual(tissue, grad_t) > CHORD_CONTRACTION * res:
        return None
    return trial, phi_t, grad_t


def _line_search(tissue, x, phi, grad, d_free, inertia, res, loads=None, held=None):
    """Backtracking: keep every J > 0, then Armijo on Φ (or a smaller residual once Φ is flat).

    Returns (x, Φ, ∇Φ, α) at the accepted point x + α d (α > 1 when extrapolated).

    A full step that lowers Φ by nearly its linear prediction met (almost) no
    curvature along d: the Hessian used overrates it (a PD-modified one, where
    the exact Hessian is indefinite: an element folding at a grip end). Then
    the step is doubled while Φ keeps falling, instead of crawling there in
    unit steps (30 such iterations on a 10 mm push of the 15.7k mesh).
    """
    free = tissue.free_dofs
    g = grad[free] if held is None else held.vector(grad[free])
    slope = float(np.dot(g, d_free if held is None else held.rotate(d_free)))
    step = np.zeros(x.size)
    step[free] = d_free
    step = step.reshape(x.shape)
    feasible = 0.95 * tissue.max_feasible_step(x, step)
    alpha = min(1.0, feasible)
    g_norm = np.linalg.norm(g)
    while alpha > 1e-12:
        trial = x + alpha * step
        phi_t, grad_t = objective_gradient(tissue, trial, inertia, loads, require_positive_J=True)
        if grad_t is not None:
            g_t = grad_t[free] if held is None else held.vector(grad_t[free])
            # Near the solution Φ changes below round-off; a falling residual decides there.
            if phi_t <= phi + ARMIJO * alpha * slope or (
                abs(phi_t - phi) <= 1e-12 * max(abs(phi), 1.0) and np.linalg.norm(g_t) < g_norm
            ):
                if alpha == 1.0 and phi_t - phi <= EXTRAPOLATE_RATIO * slope:
                    return _extrapolate(tissue, x, step, phi_t, (trial, phi_t, grad_t, alpha), feasible, inertia, loads)
                return trial, phi_t, grad_t, alpha
        alpha *= 0.5
    raise SolverError(
        f"Newton line search failed (residual {res:.3g}): no step keeps all elements uninverted and lowers the energy",
        SolveResult(x, False, 0, res, 0.0, "newton", "line search failed"),
    )


def _extrapolate(tissue, x, step, phi_best, best, feasible, inertia, loads=None):
    """Double a full step (up to MAX_EXTRAPOLATION, inside the feasible range) while Φ falls."""
    alpha = 2.0
    while alpha <= min(MAX_EXTRAPOLATION, feasible):
        trial = x + alpha * step
        phi_t, grad_t = objective_gradient(tissue, trial, inertia, loads, require_positive_J=True)
        if grad_t is None or not phi_t < phi_best:
            break
        phi_best, best = phi_t, (trial, phi_t, grad_t, alpha)
        alpha *= 2.0
    return best


def solve_newton(
    tissue: Tissue,
    strokes: np.ndarray,
    x0: np.ndarray | None = None,
    strokes0: np.ndarray | None = None,
    inertia: Inertia | None = None,
    tol: float = 1e-10,
    max_iter: int = 100,
    max_substeps: int = 64,
    conditions: Conditions = NO_CONDITIONS,
    factors: dict | None = None,
    krylov: bool | None = None,
) -> SolveResult:
    """Equilibrium (or one implicit-Euler step) for cup strokes (C,) in mm.

    x0 (N, 2) is the warm start, an equilibrium for strokes0 (default: rest,
    zero strokes). A warm start with inverted elements is replaced by the
    rest state, and the message says so. Held dofs of `conditions` stay where
    x0 (or rest) has them.
    """
    t0 = time.perf_counter()
    strokes = np.asarray(strokes, float)
    note = ""
    if x0 is None:
        x0, strokes0 = tissue.rest, np.zeros_like(strokes)
    elif np.min(tissue.jacobians(x0)) <= 0:
        n_bad = int(np.sum(tissue.jacobians(x0) <= 0))
        note = f"start guess had {n_bad} inverted element(s): restarted from rest; "
        x0, strokes0 = tissue.rest, np.zeros_like(strokes)
    elif strokes0 is None:
        strokes0 = strokes
    x, s_done = np.array(x0, float), np.asarray(strokes0, float)
    # Load continuation. The predictor is linear in the stroke increment, so the
    # largest fraction of it that keeps every J > 0 is known in closed form; an
    # intermediate state goes to STEP_FRACTION of that and is solved loosely
    # (it only has to be a good start for the next step).
    iterations, substeps, n_factor = 0, 0, 0
    while True:
        before = _factor_count(tissue, factors)
        pred = tangent_predictor(tissue, x, strokes, inertia, conditions, factors, krylov)
        n_factor += _factor_count(tissue, factors) - before
        alpha = tissue.max_feasible_step(x, pred - x)
        final = alpha > 1.0 / STEP_FRACTION
        fraction = 1.0 if final else STEP_FRACTION * alpha
        if fraction < SMALLEST_LOAD_STEP:
            raise SolverError(
                note + f"every load step inverts an element: at most {alpha:.2g} of the remaining stroke increment "
                f"is feasible, at strokes {np.round(s_done, 3).tolist()} mm on the way to "
                f"{np.round(strokes, 3).tolist()} mm",
                SolveResult(x, False, iterations, np.nan, time.perf_counter() - t0, "newton", "inversion"),
            )
        s_next = s_done + fraction * (strokes - s_done)
        start = x + fraction * (pred - x)
        result = newton_iterations(tissue, start, inertia, tol if final else max(tol, SUBSTEP_TOL), max_iter,
                                   conditions=conditions, factors=factors, krylov=krylov)
        iterations += result.iterations
        n_factor += result.factorizations
        result.factorizations = n_factor
        if not result.converged:
            result.message = note + result.message
            raise SolverError(result.message, result)
        x, s_done = result.x, s_next
        if final:
            result.iterations = iterations
            result.time_s = time.perf_counter() - t0
            result.substeps = substeps
            result.message = note + (f"converged with {substeps} load substeps" if substeps else "converged")
            return result
        substeps += 1
        if substeps > max_substeps:
            raise SolverError(
                note + f"load continuation needed more than {max_substeps} substeps",
                SolveResult(x, False, iterations, np.nan, time.perf_counter() - t0, "newton", "inversion"),
            )
