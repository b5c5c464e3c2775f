"""A whole insertion under one compensation strategy (docs/model.md §12).

Strategies:

* `none`: insert to the planned depth;
* `depth`: stop when the tip reaches the target's measured position along
  the axis (measured after every step; the last step is shortened to it);
* `loop`: `depth`, and after every step the cup loop of §6 acts on the
  miss across the needle: δs* from `control.law.split_error` on the 1×C
  Jacobian of the transverse target coordinate, the command from the §6
  `PID`, then the plant's equilibrium at the new strokes with the needle's
  hold. The Jacobian is the controller's: its model tissue's linear
  response with the captured nodes held, at the model's own equilibrium
  under the needle (`model_state.ModelState`), not the plant's.

The plant may be the layer or the slab (`tissue.dim` 3, docs/model.md §14):
in the slab the needle's axis lies in the layer (z = the layer's height),
the target and the obstacles are the layer's points carried by the slab's
nodes at the layer's level (their 2-D probe on the slab's plane), the
camera sees the target's in-plane part and the clearance is measured in
the layer's plane. With a 2-D controller model against the slab, `loop`
runs the model's own insertion (`model_state.ModelInsertion`). The plant
may also be a body (docs/model.md §20): the needle along any axis, the
lesion and the obstacles read in 3-D (`points.BodyPoints`), `loop` on
both components of the miss across the needle (those its cameras see),
each command within the drives' speed.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from scissor_cli.config import ControllerConfig
from scissor_cli.control.law import PID, split_error
from scissor_cli.insertion.capture import free_nodes
from scissor_cli.insertion.model_state import ModelInsertion, ModelState, move_held, moved_start
from scissor_cli.insertion.needle import NeedleParams, NeedleState, advance, transverse_basis
from scissor_cli.insertion.points import is_body, needle_points
from scissor_cli.insertion.steering import MissFilter, NeedleModel, TableSteering, seen_directions
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import target_positions
from scissor_cli.sensing.sensor import EXACT, Sensor, TrueState
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.equilibrium import solve_equilibrium

STRATEGIES = ("none", "depth", "loop")
#: an insertion never goes deeper than this multiple of the planned depth
MAX_DEPTH_FACTOR = 2.0


@dataclass
class InsertionResult:
    """One insertion, K steps (docs/contract.md `/insertion/<target>/<strategy>`).

    depth_mm (K,), tip (K, d), target (K, d) (d = 2 in the layer, 3 in the
    slab), needle_force_mN (K,), stuck,
    slipping (K,) int, min_clearance_mm (K,) (0.0 without obstacles: see
    has_obstacles), strokes (K, C) mm, displacement (K, N, d) mm (None when
    not kept); outcome: miss_mm (target to the needle line), depth_error_mm
    (tip minus target along n), obstacle_touched, stop_reason ("depth
    reached", "target reached", or why it stopped early), unsettled (steps
    whose active set did not settle), x (N, d) the final positions.
    """

    target_name: str
    strategy: str
    entry: np.ndarray
    direction: np.ndarray
    depth_mm: np.ndarray
    tip: np.ndarray
    target: np.ndarray
    needle_force_mN: np.ndarray
    stuck: np.ndarray
    slipping: np.ndarray
    min_clearance_mm: np.ndarray
    strokes: np.ndarray
    displacement: Optional[np.ndarray]
    miss_mm: float
    depth_error_mm: float
    obstacle_touched: bool
    has_obstacles: bool
    stop_reason: str
    unsettled: int
    time_s: float
    x: np.ndarray

    @property
    def steps(self) -> int:
        return int(self.depth_mm.size)

    @property
    def completed(self) -> bool:
        return self.stop_reason in ("depth reached", "target reached")


def miss_and_depth_error(target: np.ndarray, entry: np.ndarray, direction: np.ndarray,
                         depth_mm: float) -> tuple[float, float]:
    """Distance (mm) from the target (d,) to the needle line, and tip minus target along the axis (mm); d = 2 or 3."""
    rel = np.asarray(target, float) - entry
    if rel.size == 2:
        miss = abs(rel @ np.array([-direction[1], direction[0]]))
    else:  # both components across the axis
        miss = np.linalg.norm(transverse_basis(direction) @ rel)
    return float(miss), float(depth_mm - rel @ direction)


@dataclass(frozen=True)
class NeedlePath:
    """The plan's needle as the robot holds it.

    entry (d,) mm, direction (d,) unit, depth_mm: the plan (in the slab: the
    layer's plan lifted to z = the layer's height, n_z = 0); target_rest
    (2,) mm: the target in the layer's rest mesh; target_name: for the result.
    """

    entry: np.ndarray
    direction: np.ndarray
    depth_mm: float
    target_rest: np.ndarray
    target_name: str = ""


def needle_path(tissue: Tissue, entry: np.ndarray, direction: np.ndarray, depth_mm: float, target_rest: np.ndarray,
                target_name: str = "", height_mm: Optional[float] = None) -> NeedlePath:
    """The layer's plan (entry (2,), direction (2,)) as the needle the plant is pierced by: as it is in the layer;
    in the slab lifted to `height_mm` (default the layer's level; docs/model.md §14, §18), n_z = 0."""
    entry, direction = np.asarray(entry, float), np.asarray(direction, float)
    if tissue.dim == 3:
        sm = tissue.mesh
        z = float(sm.levels_mm[sm.layer_level]) if height_mm is None else float(height_mm)
        entry, direction = np.append(entry, z), np.append(direction, 0.0)
    return NeedlePath(entry, direction, float(depth_mm), np.asarray(target_rest, float), target_name)


@dataclass(frozen=True)
class InsertionOptions:
    """How an insertion runs: the strategy and what it steers and sees with.

    controller: the `controller` section (gains, rate, jacobian_update) for
    "loop"; sensor: how the target is seen (default exact); model: the
    controller's tissue for "loop" (default: the plant itself), model_x0
    (N, 2) its equilibrium at the strokes (solved from x0 when not given,
    which needs model and plant of one dimension); needle_model: the
    controller's 3-D model of the target under the needle (`steering`):
    with it "loop" steers with its held Jacobian instead of a model tissue's;
    keep_displacement: store every step's nodes; on_step(depth_mm): called
    after every step (progress); record(state, x, strokes): called after
    every step with the needle, the nodes (N, d) and the strokes (C,).
    """

    strategy: str = "none"
    controller: Optional[ControllerConfig] = None
    sensor: Sensor = EXACT
    model: Optional[Tissue] = None
    model_x0: Optional[np.ndarray] = None
    needle_model: Optional[NeedleModel] = None
    keep_displacement: bool = True
    on_step: Optional[Callable[[float], None]] = None
    record: Optional[Callable[[NeedleState, np.ndarray, np.ndarray], None]] = None


@dataclass
class _Trace:
    """The rows of an insertion as it goes: one per step, and the nodes' displacement when kept."""

    rows: list = field(default_factory=list)
    frames: list = field(default_factory=list)
    unsettled: int = 0


class _Needle:
    """One needle going in: the plant's equilibrium x (N, d) at strokes s (C,), the needle's state, the rows.

    `pending` is a loop command not yet applied: with a tabulated model the
    cups move with the needle's next step (one equilibrium for both), not in
    an equilibrium of their own.
    """

    def __init__(self, tissue: Tissue, x0: np.ndarray, strokes: np.ndarray, path: NeedlePath, params: NeedleParams,
                 options: InsertionOptions):
        self.tissue, self.path, self.params, self.options = tissue, path, params, options
        self.n = np.asarray(path.direction, float) / np.linalg.norm(path.direction)
        self.p0 = np.asarray(path.entry, float)
        if self.n.size == 3 and abs(self.n[2]) > 1e-12 and not is_body(tissue):
            raise ValueError("in the slab the needle's axis lies in the layer (direction z = 0)")
        self.body = is_body(tissue)
        self.points = needle_points(tissue, np.asarray(path.target_rest, float))
        self.probe = self.points.probe
        self.state = NeedleState(self.p0, self.n)
        self.candidates = free_nodes(tissue)
        self.x, self.s = np.array(x0, float), np.array(strokes, float)
        self.pending: Optional[np.ndarray] = None
        self.trace = _Trace()

    def target(self) -> np.ndarray:
        """The true target (d,) mm."""
        return target_positions(self.probe, self.x)[0]

    def seen(self) -> np.ndarray:
        """The sensor's reading of the target: (2,) mm in the layer and the slab, (3,) on a body (NaN where its
        cameras do not see; the exact sensor's reading is the whole target)."""
        if self.options.sensor is EXACT and self.body:
            return self.target()
        return self.options.sensor.measure(TrueState(self.target(), self.x, self.tissue.mesh))

    def step(self, step_mm: float):
        """Advance by step_mm (with a pending cup command); the row recorded. Raises SolverError."""
        x = self.x
        if self.pending is not None:
            x = moved_start(self.tissue, self.state, x, self.pending)
            self.s, self.pending = self.pending, None
        out = advance(self.tissue, self.state, x, self.s, step_mm, self.params, self.candidates)
        self.x = out.x
        return out

    def keep(self, out) -> None:
        """The row of the step just taken (and the hooks')."""
        t, state, x = self.trace, self.state, self.x
        t.unsettled += not out.settled
        t.rows.append((state.depth_mm, state.tip, self.target(), out.force_mN, out.stuck, out.slipping,
                       self.points.clearance(x, self.p0, state.tip, self.params.radius_mm),
                       self.s.copy()))
        if self.options.keep_displacement:
            t.frames.append(x - self.tissue.rest)
        if self.options.on_step is not None:
            self.options.on_step(state.depth_mm)
        if self.options.record is not None:
            self.options.record(state, x, self.s)

    def branch(self) -> "_Needle":
        """A copy that can go on alone (its rows and state its own; the kept factorisation shared)."""
        other = copy.copy(self)
        other.state = dataclasses.replace(self.state)
        other.trace = _Trace(list(self.trace.rows), list(self.trace.frames), self.trace.unsettled)
        return other

    def settle_pending(self, loads: np.ndarray) -> None:
        """Apply a pending command in an equilibrium of its own (the insertion ends: no step to carry it)."""
        if self.pending is not None:
            command, self.pending = self.pending, None
            self.x = move_held(self.tissue, self.state, self.x, self.s, command, loads, None)
            self.s = command
            if self.trace.rows:
                row = self.trace.rows[-1]
                self.trace.rows[-1] = row[:2] + (self.target(),) + row[3:7] + (self.s.copy(),)

    def result(self, strategy: str, reason: str, wall_s: float) -> InsertionResult:
        return _result(self.tissue, self.path, strategy, self.trace, self.options.keep_displacement, self.x,
                       self.target(), self.state, self.points.has_obstacles, reason, wall_s)


def _goal(needle: _Needle, strategy: str) -> float:
    """How deep (mm) the strategy wants the tip now: the plan's depth, or the measured target along the axis."""
    if strategy == "none":
        return needle.path.depth_mm
    seen = needle.seen()
    k = seen.size  # in the layer and the slab the in-plane reading; on a body 3-D, NaN where no camera sees
    return float(np.nansum((seen - needle.p0[:k]) * needle.n[:k]))


def run_insertion(tissue: Tissue, x0: np.ndarray, strokes: np.ndarray, path: NeedlePath, params: NeedleParams,
                  options: InsertionOptions = InsertionOptions()) -> InsertionResult:
    """Insert from the equilibrium x0 (N, d) at cup strokes (C,) mm along the plan; never raises on a solver failure.

    `tissue` is the plant. A failed step ends the insertion with the reason
    in stop_reason; what was reached is kept.
    """
    return run_strategies(tissue, x0, strokes, {options.strategy: path}, params, {options.strategy: options})[0]


def run_strategies(tissue: Tissue, x0: np.ndarray, strokes: np.ndarray, paths: dict, params: NeedleParams,
                   options: dict) -> list[InsertionResult]:
    """Every strategy's insertion from the same state: paths and options by strategy; the results in that order.

    `none` and `depth` move no cup: on one path they take the same steps
    until one of them is within a step of its goal, so they are inserted as
    one needle that branches for the last, shortened step of the first to
    stop (the kept factorisation shared). `loop` goes alone.
    """
    for strategy in paths:
        if strategy not in STRATEGIES:
            raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    results: dict[str, InsertionResult] = {}
    still = [k for k in paths if k != "loop"]
    if len(still) == 2 and _same_path(paths[still[0]], paths[still[1]]):
        results.update(_insert_together(tissue, x0, strokes, paths[still[0]], params,
                                        {k: options[k] for k in still}))
    for strategy in paths:
        if strategy not in results:
            results.update(_insert_together(tissue, x0, strokes, paths[strategy], params,
                                            {strategy: options[strategy]}))
    return [results[k] for k in paths]


def _same_path(a: NeedlePath, b: NeedlePath) -> bool:
    return (np.array_equal(a.entry, b.entry) and np.array_equal(a.direction, b.direction)
            and a.depth_mm == b.depth_mm and np.array_equal(a.target_rest, b.target_rest))


def _insert_together(tissue, x0, strokes, path, params, options: dict) -> dict:
    """The strategies of `options` on one needle (one strategy, or `none` and `depth` sharing their steps)."""
    t0 = time.perf_counter()
    first = next(iter(options.values()))
    needle = _Needle(tissue, x0, strokes, path, params, first)
    steering = _steering(needle, first, params) if "loop" in options else None
    # a body's loop on a model tissue filters the miss it steers on (a table's steering filters its own)
    miss = (MissFilter(2, first.controller.tolerance_mm, first.sensor.noise_mm)
            if needle.body and steering is not None and not isinstance(steering, TableSteering) else None)
    pid = None
    if steering is not None:
        gains = first.controller
        pid = PID(gains.kp, gains.ki, gains.kd, 1.0 / gains.rate_hz)
    running = {k: needle for k in options}  # each strategy's needle (a branch once it takes its last step)
    last: dict[str, bool] = dict.fromkeys(options, False)
    done: dict[str, InsertionResult] = {}
    max_depth = MAX_DEPTH_FACTOR * path.depth_mm + params.step_mm
    loads = np.zeros(0)
    while running:
        # each strategy's goal, measured before the step (in the order of `options`: a sensor's draws with it)
        remaining = {k: _goal(n, k) - n.state.depth_mm for k, n in running.items()}
        for k in list(running):
            if remaining[k] <= 1e-9 or last[k]:
                # the last step is shortened to the goal measured before it; the drag during it is not chased
                n = running.pop(k)
                if steering is not None:
                    n.settle_pending(loads)
                done[k] = n.result(k, "depth reached" if k == "none" else "target reached", time.perf_counter() - t0)
        if not running:
            break
        if needle.state.depth_mm >= max_depth:
            for k, n in running.items():
                done[k] = n.result(k, f"stopped at {n.state.depth_mm:.3g} mm: the target kept moving ahead of the "
                                      f"tip", time.perf_counter() - t0)
            break
        shared = [k for k, n in running.items() if n is needle]
        ending = [k for k in shared if remaining[k] <= params.step_mm]
        for k in ending:
            last[k] = True
            if len(shared) > 1:  # the others go on from here: this one's last step on a branch
                running[k] = needle.branch()
        try:
            for k, n in running.items():
                if n is needle and k != shared[0] and k not in ending:
                    continue  # (one step of the shared needle serves every strategy on it)
                amount = min(params.step_mm, remaining[k]) if k in ending else params.step_mm
                out = n.step(amount)
                loads = out.loads
                if steering is not None:
                    _correct(n, steering, out.loads, pid, miss)
                n.keep(out)
        except SolverError as exc:
            for k, n in list(running.items()):
                done[k] = n.result(k, f"solver failed at depth {n.state.depth_mm:.3g} mm: {exc}",
                                   time.perf_counter() - t0)
            break
    return done


def _steering(needle: _Needle, options: InsertionOptions, params: NeedleParams):
    """`loop`'s source of J: the tabulated 3-D model, or a model tissue under the needle."""
    gains = options.controller
    if options.needle_model is not None:
        return TableSteering(options.needle_model, _across(needle), gains.jacobian_update == "broyden",
                             options.sensor.noise_mm, gains.tolerance_mm)
    return _model_state(needle.tissue, options.model, needle.x, options.model_x0, needle.s, needle.p0, needle.n,
                        np.asarray(needle.path.target_rest, float), params)


def _model_state(plant, model, x0, model_x0, strokes, p0, n, target_rest, params):
    """The controller's model at the start: the plant itself, its own equilibrium at the strokes, or (a 2-D
    model of the slab) its own insertion (`ModelInsertion`)."""
    if model is None or model is plant:
        return ModelState(plant, plant, x0, x0, strokes)
    if model.dim != plant.dim:
        if model_x0 is None:
            raise ValueError("a 2-D controller model of the slab needs its equilibrium at the strokes (model_x0)")
        return ModelInsertion(model, model_x0, strokes, p0[:2], n[:2], target_rest, params)
    if model_x0 is None:  # x0 only warms the solve: the model's equilibrium does not depend on it
        model_x0 = solve_equilibrium(model, strokes, start=x0, start_strokes=strokes).x
    return ModelState(model, plant, model_x0, x0, strokes)


def _across(needle: _Needle) -> np.ndarray:
    """The directions (r, d) across the needle that `loop` steers the miss along: a body's two transverse axes in
    3-D, the layer's (and the slab's) in-plane normal."""
    t = needle.state.transverse
    return t if needle.body else t[:1, :2]


def _correct(needle: _Needle, steering, loads: np.ndarray, pid: PID, miss: Optional[MissFilter] = None) -> None:
    """One §6 loop iteration on the miss across the needle, the needle holding its captured nodes.

    J is the controller's: its 3-D model's held Jacobian at this depth
    (`steering.TableSteering`), or its model tissue's linear response with
    the hold at its own equilibrium under the needle (`ModelState`,
    `ModelInsertion`). On the slab's table the command moves the cups with
    the needle's next step (one equilibrium for both, the step bounded by
    the drives' speed); otherwise the plant is solved at the command with
    the same hold (§14, the layer model's loop as it was; on a body a large
    move at the cup's rigid rim inverts an element at a needle step's
    start). On a body the miss is filtered (the table's filter, or `miss`:
    the model body's own move under the needle predicts, the reading
    corrects what the sensor sees), and the cups stay while the estimate,
    or the part of it their move can correct (J J⁺ e), is within the
    deadband (as on the slab's table).
    """
    state, x, s = needle.state, needle.x, needle.s
    seen = needle.seen()
    body = needle.body
    across = _across(needle)
    offset = seen - needle.p0[:seen.size]
    if body:
        # One camera does not see the depth along its view (NaN there): the unseen coordinates count as 0 and
        # the filter is told which directions across the needle the sensor sees (T S Tᵀ, S its projector:
        # `seen` of the camera or ultrasound sensor, else onto the coordinates it reports). (across @ offset
        # alone is NaN in both rows, 0 · NaN being NaN: the cups once never moved.) Where it sees nothing the
        # estimate is the model's prediction, and the loop drives both components (a cup that corrects the
        # seen one moves the unseen one too).
        measured = np.isfinite(offset)
        S = getattr(needle.options.sensor, "seen", None)
        observed = across @ (np.diag(measured.astype(float)) if S is None else S) @ across.T  # (2, 2)
        reading = across @ np.where(measured, offset, 0.0)
    if isinstance(steering, TableSteering):
        J, responses = steering.jacobian(state.depth_mm, s, seen), None
        estimate = (steering.offset(state.depth_mm, s, reading, J, seen_directions(observed)) if body
                    else steering.offset(state.depth_mm, s, across @ offset, J))
        deadband = steering.deadband_mm
        if np.linalg.norm(estimate) <= deadband:  # on the line as well as the filter can tell
            return
        e = -estimate
    elif body:
        before = target_positions(needle.probe, steering.x)[0]
        steering.follow(state, x, s, loads)
        moved = across @ (target_positions(needle.probe, steering.x)[0] - before)
        estimate = miss.update(moved, reading, seen_directions(observed))
        deadband = miss.deadband_mm
        if np.linalg.norm(estimate) <= deadband:
            return  # on the line as well as the filter can tell: the cups stay
        e = -estimate
        J, responses = steering.jacobian(state, needle.probe, state.solver, rows=2)
    else:
        e, deadband = -(across @ offset), None  # the layer's loop steers on every reading
        steering.follow(state, x, s, loads)
        J, responses = steering.jacobian(state, needle.probe, state.solver)
        if responses.shape[1:] != x.shape:
            # a 2-D model's responses are no start for the slab (its levels near the fixed chest wall do not
            # move as the layer does): the strokes placed only
            responses = None
    seen_rows = np.isfinite(e)
    if not np.any(seen_rows):
        return
    ds, correctable, _ = split_error(J[seen_rows], e[seen_rows])
    if deadband is not None and np.linalg.norm(correctable) <= deadband:
        return  # what the cups can correct is on the line already: a move would only trade one component for another
    tissue = needle.tissue
    lo = np.array([c.stroke_min_mm for c in tissue.scene.cups])
    hi = np.array([c.stroke_max_mm for c in tissue.scene.cups])
    if isinstance(steering, TableSteering) or needle.body:  # the drives' speed over a control period, as in §6
        reach = np.array([c.speed_mm_per_s for c in tissue.scene.cups]) * pid.dt
        ds = np.clip(ds, -reach, reach)
    command, _ = pid.command(s, ds, lo, hi)
    if np.allclose(command, s, atol=1e-12, rtol=0):
        return
    if isinstance(steering, TableSteering) and not body:  # the cups move with the needle's next step
        needle.pending = command
    else:
        needle.x, needle.s = _move_plant(tissue, state, x, s, command, loads, responses), command


def _move_plant(tissue, state, x, s, command, loads, responses) -> np.ndarray:
    """The plant's equilibrium (N, d) at the command (C,) with the needle's hold and loads (`model_state.move_held`)."""
    return move_held(tissue, state, x, s, command, loads, responses)


def _result(tissue, path: NeedlePath, strategy, trace: _Trace, keep, x, y, state, has_obstacles, reason,
            wall) -> InsertionResult:
    rows = trace.rows
    k = len(rows)
    p0, n = np.asarray(path.entry, float), np.asarray(path.direction, float) / np.linalg.norm(path.direction)

    def col(i, shape=()):
        return np.array([r[i] for r in rows], float).reshape((k,) + shape)

    clearance = col(6)
    miss, depth_error = miss_and_depth_error(y, p0, n, state.depth_mm)
    touched = bool(has_obstacles and k and np.min(clearance) <= 0.0)
    return InsertionResult(
        path.target_name, strategy, p0, n, col(0), col(1, (p0.size,)), col(2, (p0.size,)), col(3),
        col(4).astype(np.int64), col(5).astype(np.int64), np.where(np.isfinite(clearance), clearance, 0.0),
        np.array([r[7] for r in rows], float).reshape(k, tissue.n_cups),
        np.array(trace.frames) if keep else None, miss, depth_error, touched, has_obstacles,
        reason, trace.unsettled, wall, x,
    )
