"""The controller's model during an insertion, and the `loop` strategy's Jacobian on it (docs/model.md §12).

§6 keeps the controller's own model apart from the "true" tissue: the
controller solves its model at the strokes it commands and takes J there.
During an insertion the needle is one more boundary condition, and the
robot knows it: where the needle is, which nodes it holds (capture is
geometric) and the forces it applies. What it does not know is the
tissue's material. So `ModelState` is the model's equilibrium at the current
strokes under the needle's hold and loads as they stand (the captured
nodes at the same held coordinates, the same stuck/slipping set), tracked
from step to step:

* when model and plant are the same tissue (the nominal run) that
  equilibrium *is* the plant's, which was just solved: it is taken over, as
  the §6 controller takes over the plant's equilibrium (`Controller.update`);
* otherwise the model is solved on its own kept factorisation
  (`chord.ChordSolver`, the model's own slot), warm started from its last
  state moved by the plant's increment, with Newton as the fallback.

J (1×C) is the linear response of the target's across-needle coordinate to
a unit stroke of each cup at that state, with the needle's held rows:
K_ff d = −K_fd B e_c subject to the hold's rows C d = 0, d read through the
probe. It is solved with preconditioned conjugate gradients on the hold's
null space, the preconditioner a kept factorisation (the plant's chord
solver in the nominal run, the model's otherwise) with the hold as Schur
rows (`ChordSolver.step`), and K v products from the exact element
Hessians at the state. A kept factorisation is close to the current
tangent, so a few iterations reach PCG_TOL; no factorisation is made unless
they do not (then the kept one is refreshed at the state, where one
iteration suffices). No residual enters J: it is the pure linear response. In 3-D (the slab, a body)
J is the kept factor's answer with the hold's rows from the start (`JACOBIAN_DIRECT_3D`): each PCG
iteration there costs a triangular solve and an element-by-element K v on tens of thousands of
tetrahedra, and the kept factor's answer is close to the converged one (the benchmark
checks how close). A body compressed
ahead of the tip can have a tangent that is not positive definite; the
kept factor is then of its elements' positive semi-definite projection and
PCG on the exact tangent does not converge even on a fresh one. From then
on J is the kept factor's own answer (`direct`; the factor is refreshed
by the needle's steps as they need): the response of a nearby tangent, or
of its projection — a feedback gain the loop corrects, not an equilibrium
(refreshing it at every J costs every captured row's Schur column again).

When the plant is the 3-D slab and the model the 2-D layer (`trials.truth:
slab`, docs/model.md §14), the plant's hold cannot be carried over node by
node: its captured nodes span several levels, its loads sit on slab nodes.
So `ModelInsertion` runs the needle in the model its own way: the same
needle (entry and axis in the layer, the same parameters) advanced in the
model to the plant's depth step by step, with its own capture and
stick–slip, at the strokes the controller commands; J is then the
nominal-run J of that 2-D insertion (`ModelState` with model = plant).
The controller thus uses nothing of the true slab but the camera's
measurement and the needle's depth.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.insertion.capture import free_nodes
from scissor_cli.insertion.chord import ChordFailed, ChordSolver, Hold
from scissor_cli.insertion.needle import (
    STEP_TOL,
    STEP_TOL_3D,
    STEP_TOL_BODY,
    NeedleParams,
    NeedleState,
    advance,
    needle_conditions,
)
from scissor_cli.insertion.points import is_body
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import TargetProbe, probe_targets, target_positions
from scissor_cli.solvers.common import SolverError, objective_gradient
from scissor_cli.solvers.equilibrium import solve_equilibrium
from scissor_cli.solvers.linear import conjugate_gradients

#: J's conjugate gradients stop when the preconditioned residual is this small relative to the response
PCG_TOL = 1e-8
#: iterations before the kept factorisation is refreshed at the state (and then as many again)
PCG_MAX = 40
#: In 3-D the loop's J is the kept factor's answer with the hold, one triangular solve per cup, not PCG to
#: PCG_TOL: a feedback gain the loop corrects; benchmarks/bench_body_insertion.py checks it against PCG's
#: converged J along example_dome's insertion (docs/performance.md)
JACOBIAN_DIRECT_3D = True
#: a cup move's K_fD Δu_D is the gradient's change over this much of the move (mm, its largest boundary displacement)
MOVE_PROBE_MM = 1e-3


class ModelState:
    """The controller's model tissue and its equilibrium x (N, 2) under the needle's hold during an insertion.

    model: the controller's tissue; plant: the tissue that moves. x_model
    (N, 2): the model's equilibrium at `strokes` (C,) with what holds it
    then; x_plant (N, 2): the plant's at the same time (the model's warm
    start follows the plant's increments). When model is plant, x_model
    must be x_plant.
    """

    def __init__(self, model: Tissue, plant: Tissue, x_model: np.ndarray, x_plant: np.ndarray, strokes: np.ndarray):
        self.tissue = model
        self.shared = model is plant
        self.x = np.array(x_model, float)
        self.strokes = np.array(strokes, float)
        self._x_plant = np.array(x_plant, float)
        #: the model's kept factorisation (its own slot); None when it is the plant's
        self.solver = None if self.shared else ChordSolver(model)
        #: PCG iterations and factorisations of the last `jacobian` (the benchmark's evidence)
        self.last_iterations = 0
        self.last_factorizations = 0
        #: each J one solve on the kept factor (`_held_response`): in 3-D from the start (JACOBIAN_DIRECT_3D), in
        #: 2-D once PCG has failed on a fresh factor (a tangent that is not positive definite)
        self.direct = model.dim == 3 and JACOBIAN_DIRECT_3D

    def follow(self, state: NeedleState, x_plant: np.ndarray, strokes: np.ndarray, loads: np.ndarray) -> None:
        """Move to the model's equilibrium at strokes (C,) under the needle's hold and loads (2N,) as they stand.

        x_plant (N, 2): the plant's equilibrium now, whose captured nodes
        give the hold's coordinates. Raises SolverError when no solve works.
        """
        x_plant = np.asarray(x_plant, float)
        strokes = np.asarray(strokes, float)
        if self.shared:
            self.x, self._x_plant, self.strokes = x_plant.copy(), x_plant.copy(), strokes.copy()
            return
        model = self.tissue
        hold = hold_at(state, x_plant)
        start = hold.place(model.apply_strokes(self.x + (x_plant - self._x_plant), strokes))
        _, g = objective_gradient(model, start, None, loads, require_positive_J=True)
        x = None
        if g is not None:
            try:
                x = self.solver.converge(start, g, hold, settled_tol(model), loads)[0]
            except ChordFailed:
                x = None
        if x is None:  # Newton from the last state, the hold placed, continuing from its strokes
            r = solve_equilibrium(model, strokes, start=hold.place(self.x), start_strokes=self.strokes,
                                  conditions=needle_conditions(state, loads), tol=settled_tol(model))
            x = r.x
        self.x, self._x_plant, self.strokes = x, x_plant.copy(), strokes.copy()

    def jacobian(self, state: NeedleState, probe: TargetProbe, kept: ChordSolver | None = None,
                 rows: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """J (rows, C): the target's across-needle response to a unit stroke of each cup, the needle's hold kept.

        Also the model's node responses (C, N, d) per unit stroke (the
        plant's solve starts from them). kept: the plant's chord solver,
        whose factorisation preconditions the solve in the nominal run
        (ignored when the model has its own). rows 1: along the first
        transverse axis — in the slab the in-plane normal (t, 0), the cups
        moving the target in the layer; rows 2: both (a body's miss).
        """
        R, responses = self.target_response(state, probe, kept)
        J = state.transverse[:rows] @ R
        if not np.all(np.isfinite(J)):
            raise SolverError("the loop's Jacobian is not finite")
        return J, responses

    def target_response(self, state: NeedleState, probe: TargetProbe, kept: ChordSolver | None = None,
                        tol: float = PCG_TOL) -> tuple[np.ndarray, np.ndarray]:
        """The target's response (d, C) mm/mm to a unit stroke of each cup with the needle's hold, and the node
        responses (C, N, d): K_ff d = −K_fd B e_c on the hold's null space (see the module doc), solved to the
        relative tolerance tol."""
        model, x = self.tissue, self.x
        solver = self.solver if self.solver is not None else kept
        if solver is None:
            solver = self.solver = ChordSolver(model)
        n_factor = solver.factorizations
        if solver.factorizations == 0:  # nothing kept yet
            solver.refactor(x)
        hold = hold_at(state, x)
        # the held components of a response, exactly zero (not round-off: a target whose nodes the needle all
        # holds has J exactly 0 across the axis, and the loop must not divide by 1e-16)
        held_zero = Hold(hold.captured, np.zeros_like(hold.base), hold.stuck, hold.ride, hold.n, hold.t)
        free = model.free_dofs
        Ke = None if self.direct else model.element_stiffness(x)  # (a direct J needs no K v but K_fD's)
        R = np.zeros((x.shape[1], model.n_cups))
        responses = np.zeros((model.n_cups,) + x.shape)
        its = 0
        for c in range(model.n_cups):
            u_c = model.cup_displacement(c)
            b = -(model.stiffness_times_near(x, u_c) if Ke is None else model.stiffness_times(x, u_c, Ke))
            d, k, direct = _held_response(model, solver, hold, x, Ke, b, free, tol, self.direct)
            self.direct = self.direct or direct
            its += k
            responses[c] = held_zero.place(d.reshape(x.shape))
            responses[c].ravel()[model.dirichlet_dofs] = model.cup_displacement(c)[model.dirichlet_dofs]
            R[:, c] = target_positions(probe, responses[c])[0]
        self.last_iterations, self.last_factorizations = its, solver.factorizations - n_factor
        if not np.all(np.isfinite(R)):
            raise SolverError("the target's held response is not finite")
        return R, responses


class ModelInsertion:
    """The controller's 2-D model running the plant's insertion its own way (plant in the slab; see the module doc).

    model: the controller's 2-D tissue; x_model (N, 2): its equilibrium at
    strokes (C,) mm; entry (2,), direction (2,) unit: the needle in the
    layer; target_rest (2,) mm; params: the needle's parameters. Answers as
    `ModelState` does (`follow`, `jacobian`), with the plant's needle state
    read for its depth only.
    """

    def __init__(self, model: Tissue, x_model: np.ndarray, strokes: np.ndarray, entry: np.ndarray,
                 direction: np.ndarray, target_rest: np.ndarray, params: NeedleParams):
        self.tissue, self.params = model, params
        self.x = np.array(x_model, float)
        self.strokes = np.array(strokes, float)
        self.state = NeedleState(np.asarray(entry, float), np.asarray(direction, float))
        self.probe = probe_targets(model.mesh, np.asarray(target_rest, float)[None])
        self._candidates = free_nodes(model)
        self._loads = np.zeros(self.x.size)
        self._responses = None
        #: the nominal-run J of the model's own insertion
        self._shared = ModelState(model, model, self.x, self.x, self.strokes)

    def follow(self, state: NeedleState, x_plant: np.ndarray, strokes: np.ndarray, loads: np.ndarray) -> None:
        """Move the model to the commanded strokes (C,) under its own needle, then advance that needle to the
        plant's depth."""
        strokes = np.asarray(strokes, float)
        if self.state.solver is not None and not np.array_equal(strokes, self.strokes):
            self.x = move_held(self.tissue, self.state, self.x, self.strokes, strokes, self._loads, self._responses)
        self.strokes = strokes.copy()
        step = state.depth_mm - self.state.depth_mm
        if step > 1e-12:
            out = advance(self.tissue, self.state, self.x, self.strokes, step, self.params, self._candidates)
            self.x, self._loads = out.x, out.loads
        self._shared.follow(self.state, self.x, self.strokes, self._loads)

    def jacobian(self, state: NeedleState, probe=None,
                 kept: ChordSolver | None = None) -> tuple[np.ndarray, np.ndarray]:
        """J (1, C) of the model's own insertion (its target, its needle), and its node responses (C, N, 2)."""
        J, self._responses = self._shared.jacobian(self.state, self.probe, self.state.solver)
        return J, self._responses


def move_held(tissue: Tissue, state: NeedleState, x: np.ndarray, s: np.ndarray, command: np.ndarray,
              loads: np.ndarray, responses: np.ndarray | None) -> np.ndarray:
    """The tissue's equilibrium (N, d) at the command (C,) mm with the needle's hold and loads (dN,), from x at s.

    Chord steps on the insertion's kept factorisation from the linear
    response to the stroke change (responses (C, N, d) per unit stroke, or
    None: the kept factor's own, `moved_start`). When they do not contract,
    the tangent is factored at x, the last equilibrium, and the chord steps
    start again from its exact response to the move (Newton's predictor):
    at a cup's rigid rim the first start's residual is large and a
    factorisation there steps into an inverted element
    (docs/performance-elements.md, "Where a trial with the needle goes").
    Newton when that fails too or its start inverts an element.
    """
    tol = settled_tol(tissue)
    hold = hold_at(state, x)
    solver = state.solver
    predicted = moved_start(tissue, state, x, command) if responses is None else \
        x + np.tensordot(command - s, responses, axes=1)
    for attempt in range(2):
        if attempt:  # Newton's predictor on the chord solver: the exact tangent at x and its held response
            try:
                solver.refactor(x)
            except SolverError:  # (no positive definite tangent at x: Newton's continuation)
                break
            predicted = moved_start(tissue, state, x, command)
        start = hold.place(tissue.apply_strokes(predicted, command))
        _, g = objective_gradient(tissue, start, None, loads, require_positive_J=True)
        if g is not None:
            try:
                return solver.converge(start, g, hold, tol, loads, refactor=attempt == 1)[0]
            except ChordFailed:
                pass
    r = solve_equilibrium(tissue, command, start=x, start_strokes=s, conditions=needle_conditions(state, loads),
                          tol=tol)
    return r.x


def settled_tol(tissue: Tissue) -> float:
    """The relative residual an insertion step settles to in this tissue (`needle`'s by dimension, a body's own):
    a cup move under the needle and the controller's model are solved to it too."""
    if tissue.dim == 2:
        return STEP_TOL
    return STEP_TOL_BODY if is_body(tissue) else STEP_TOL_3D


def moved_start(tissue: Tissue, state: NeedleState, x: np.ndarray, command: np.ndarray) -> np.ndarray:
    """A start (N, d) for the equilibrium after the cups move to the command (C,) mm from x (N, d) under the needle.

    The strokes placed, and the free nodes moved by the kept factorisation's
    linear response to them with every captured node held where it is: one
    chord step, −K⁻¹ K_fD Δu_D under the hold's rows, K_fD Δu_D the
    gradient's change over MOVE_PROBE_MM of the move. The strokes alone move
    only the cup's nodes: at the cup's rim the step from there does not
    contract on the kept factor and ends in a refactorisation or Newton
    (docs/performance.md, "The needle that hits in 3-D"). The strokes
    placed alone when there is no kept factorisation yet or the predicted
    start inverts an element.
    """
    placed = tissue.apply_strokes(x, command)
    jump = placed - x
    largest = float(np.max(np.abs(jump), initial=0.0))
    solver = state.solver
    if largest == 0.0 or solver is None or not solver.factored:
        return placed
    eps = MOVE_PROBE_MM / largest
    _, g0 = tissue.energy_gradient(x)
    _, g1 = tissue.energy_gradient(x + eps * jump, require_positive_J=True)
    if g1 is None:
        return placed
    captured = state.captured
    hold = Hold(captured, x[captured].copy(), np.ones(captured.size, bool), np.zeros(captured.size), state.direction,
                state.transverse)
    d, _ = solver.step((g1 - g0) / eps, hold, x)
    start = placed + d
    return start if np.min(tissue.jacobians(start)) > 0 else placed


def hold_at(state: NeedleState, x: np.ndarray) -> Hold:
    """The needle's hold with the captured nodes where x has them (stuck: both dofs; slipping: across the axis)."""
    captured = state.captured
    return Hold(captured, x[captured].copy(), state.stuck.copy(), np.zeros(captured.size), state.direction,
                state.transverse)


def _held_response(model, solver, hold, x, Ke, b, free, tol=PCG_TOL, direct=False):
    """d (2N,) with K d = b on the hold's null space (C d = 0), K the exact tangent at x; the PCG iterations; and
    whether d is the factor's own answer (see below).

    b (2N,) is read on the free dofs. `linear.conjugate_gradients`, started
    from the preconditioner's answer, the preconditioner the solver's
    factorisation with the hold's Schur rows; if PCG_MAX iterations do not
    reach tol it is refreshed at x and the solve starts again. direct: d is
    the kept factor's answer, no PCG.
    """
    its = 0
    mask = np.zeros(x.size, bool)
    mask[free] = True
    rhs = np.where(mask, b, 0.0)

    def K(v):
        return np.where(mask, model.stiffness_times(x, v, Ke), 0.0)

    def precondition(r):
        g = np.zeros(x.size)
        g[free] = -r[free]
        return solver.step(g, hold, x)[0].ravel()

    if direct:
        d = precondition(rhs)
        if not np.all(np.isfinite(d)):
            raise SolverError("the loop's Jacobian is not finite")
        return d, 0, True
    for attempt in range(2):
        d, k, why = conjugate_gradients(K, precondition, rhs, tol, PCG_MAX, x0=precondition(rhs),
                                        relative_to="solution")
        its += k
        if d is not None:
            return d, its, False
        if why == "curvature":
            raise SolverError("the model's tangent with the needle's hold is not positive definite")
        if attempt == 0:
            solver.refactor(x)
    if why == "iterations":
        # The fresh factor is of the elements' positive semi-definite projection when the exact tangent is not
        # positive definite (a body compressed ahead of the tip): the response on that tangent, one solve on the
        # fresh factor with the hold's rows, is then the loop's J — a feedback gain, not an equilibrium
        d = precondition(rhs)
        if np.all(np.isfinite(d)):
            return d, its, True
    raise SolverError(f"the loop's Jacobian did not converge in {PCG_MAX} iterations on a fresh factorisation ({why})")
