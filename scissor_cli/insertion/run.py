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
runs the model's own insertion (`model_state.ModelInsertion`).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from scissor_cli.config import ControllerConfig
from scissor_cli.control.law import PID, split_error
from scissor_cli.geometry import segment_polygon_distance
from scissor_cli.insertion.model_state import ModelInsertion, ModelState, move_held
from scissor_cli.insertion.needle import NeedleParams, NeedleState, advance, free_nodes, transverse_basis
from scissor_cli.insertion.steering import NeedleModel, TableSteering
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.outlines import deformed_outlines, embed_outlines
from scissor_cli.mesh.probe import TargetProbe, probe_targets, target_positions
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


def miss_and_depth_error(target: np.ndarray, entry: np.ndarray, direction: np.ndarray, depth_mm: float) -> tuple[float, float]:
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


def run_insertion(tissue: Tissue, x0: np.ndarray, strokes: np.ndarray, path: NeedlePath, params: NeedleParams,
                  options: InsertionOptions = InsertionOptions()) -> InsertionResult:
    """Insert from the equilibrium x0 (N, d) at cup strokes (C,) mm along the plan; never raises on a solver failure.

    `tissue` is the plant. A failed step ends the insertion with the reason
    in stop_reason; what was reached is kept.
    """
    strategy = options.strategy
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    t0 = time.perf_counter()
    n = np.asarray(path.direction, float) / np.linalg.norm(path.direction)
    p0 = np.asarray(path.entry, float)
    target_rest = np.asarray(path.target_rest, float)
    probe, embedding = layer_points(tissue, target_rest, [o.outline for o in tissue.scene.obstacles])
    if n.size == 3 and abs(n[2]) > 1e-12:
        raise ValueError("in the slab the needle's axis lies in the layer (direction z = 0)")
    sensor = options.sensor

    def measure(y: np.ndarray, x: np.ndarray) -> np.ndarray:
        return sensor.measure(TrueState(y, x, tissue.mesh))

    state = NeedleState(p0, n)
    candidates = free_nodes(tissue)
    x, s = np.array(x0, float), np.array(strokes, float)
    lo = np.array([c.stroke_min_mm for c in tissue.scene.cups])
    hi = np.array([c.stroke_max_mm for c in tissue.scene.cups])
    pid = steering = None
    if strategy == "loop":
        gains = options.controller
        pid = PID(gains.kp, gains.ki, gains.kd, 1.0 / gains.rate_hz)
        if options.needle_model is not None:
            steering = TableSteering(options.needle_model, state.transverse[0][:2],
                                     gains.jacobian_update == "broyden", sensor.noise_mm)
        else:
            steering = _model_state(tissue, options.model, x, options.model_x0, s, p0, n, target_rest, params)
    trace = _Trace()
    reason = ""
    max_depth = MAX_DEPTH_FACTOR * path.depth_mm + params.step_mm
    last = False
    while True:
        y = target_positions(probe, x)[0]
        goal = path.depth_mm if strategy == "none" else float((measure(y, x) - p0[:2]) @ n[:2])
        remaining = goal - state.depth_mm
        if remaining <= 1e-9 or last:
            # the last step is shortened to the goal measured before it; the drag during it is not chased
            reason = "depth reached" if strategy == "none" else "target reached"
            break
        last = remaining <= params.step_mm
        if state.depth_mm >= max_depth:
            reason = f"stopped at {state.depth_mm:.3g} mm: the target kept moving ahead of the tip"
            break
        try:
            out = advance(tissue, state, x, s, min(params.step_mm, remaining), params, candidates)
            x = out.x
            if pid is not None:
                x, s = _loop_correction(tissue, steering, state, x, s, out.loads, probe, pid, lo, hi, p0, measure)
        except SolverError as exc:
            reason = f"solver failed at depth {state.depth_mm:.3g} mm: {exc}"
            break
        trace.unsettled += not out.settled
        y = target_positions(probe, x)[0]
        trace.rows.append((state.depth_mm, state.tip, y, out.force_mN, out.stuck, out.slipping,
                           _clearance(embedding, x, p0[:2], state.tip[:2], params.radius_mm), s.copy()))
        if options.keep_displacement:
            trace.frames.append(x - tissue.rest)
        if options.on_step is not None:
            options.on_step(state.depth_mm)
        if options.record is not None:
            options.record(state, x, s)
    y = target_positions(probe, x)[0]
    return _result(tissue, path, strategy, trace, options.keep_displacement, x, s, y, state,
                   bool(embedding.splits), reason, time.perf_counter() - t0)


def layer_points(tissue: Tissue, target_rest: np.ndarray, obstacles: list):
    """The target's probe and the obstacles' embedding on the plant's nodes.

    In the layer, on its own mesh; in the slab, the 2-D ones on the slab's
    plane (the 2-D mesh it extruded: the layer's or its own coarser one)
    carried to the slab's nodes at the layer's level (its triangles are
    faces of the slab's tetrahedra there, so the weights are exact).
    """
    if tissue.dim == 2:
        return probe_targets(tissue.mesh, target_rest[None]), embed_outlines(tissue.mesh, obstacles)
    plane = tissue.mesh.plane
    offset = tissue.mesh.node(tissue.mesh.layer_level, 0)
    p = probe_targets(plane, target_rest[None])
    e = embed_outlines(plane, obstacles)
    return (TargetProbe(p.tri_idx, p.nodes + offset, p.bary),
            dataclasses.replace(e, triangles=e.triangles + offset))


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


def _loop_correction(tissue, steering, state, x, s, loads, probe, pid, lo, hi, p0, measure):
    """One §6 loop iteration on the miss across the needle, the needle holding its captured nodes.

    J is the controller's: its 3-D model's held Jacobian at this depth
    (`steering.TableSteering`), or its model tissue's linear response with
    the hold at its own equilibrium under the needle (`ModelState`,
    `ModelInsertion`); the plant is then solved at the command with the
    same hold.
    """
    y = target_positions(probe, x)[0]
    seen = measure(y, x)
    e = np.array([-(seen - p0[:2]) @ state.transverse[0][:2]])
    if isinstance(steering, TableSteering):
        J, responses = steering.jacobian(state.depth_mm, s, seen), None
    else:
        steering.follow(state, x, s, loads)
        J, responses = steering.jacobian(state, probe, state.solver)
        if responses.shape[1:] != x.shape:
            # a 2-D model's responses are no start for the slab (its levels near the fixed chest wall do not
            # move as the layer does): the strokes placed only
            responses = None
    ds, _, _ = split_error(J, e)
    command, _ = pid.command(s, ds, lo, hi)
    if np.allclose(command, s, atol=1e-12, rtol=0):
        return x, s
    return _move_plant(tissue, state, x, s, command, loads, responses), command


def _move_plant(tissue, state, x, s, command, loads, responses) -> np.ndarray:
    """The plant's equilibrium (N, d) at the command (C,) with the needle's hold and loads (`model_state.move_held`)."""
    return move_held(tissue, state, x, s, command, loads, responses)


def _clearance(embedding, x, p0, tip, radius_mm) -> float:
    """Shaft (p0 → tip (2,), radius) to the nearest deformed obstacle in the layer's plane (mm); +inf without obstacles."""
    outlines = deformed_outlines(embedding, x)
    if not outlines:
        return float("inf")
    return min(segment_polygon_distance(p0, tip, poly[:, :2]) for poly in outlines) - radius_mm


def _result(tissue, path: NeedlePath, strategy, trace: _Trace, keep, x, s, y, state, has_obstacles, reason,
            wall) -> InsertionResult:
    rows = trace.rows
    k = len(rows)
    p0, n = np.asarray(path.entry, float), np.asarray(path.direction, float) / np.linalg.norm(path.direction)
    col = (lambda i, shape=(): np.array([r[i] for r in rows], float).reshape((k,) + shape))
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
