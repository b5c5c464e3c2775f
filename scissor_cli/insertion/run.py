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
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from scissor_cli.control.law import PID, split_error
from scissor_cli.geometry import segment_polygon_distance
from scissor_cli.insertion.chord import ChordFailed
from scissor_cli.insertion.model_state import ModelState, hold_at
from scissor_cli.insertion.needle import (NeedleParams, NeedleState, STEP_TOL, advance, free_nodes, needle_conditions,
                                         transverse_basis)
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.outlines import deformed_outlines, embed_outlines
from scissor_cli.mesh.probe import probe_targets, target_positions
from scissor_cli.solvers.common import SolverError, objective_gradient
from scissor_cli.solvers.equilibrium import solve_equilibrium

STRATEGIES = ("none", "depth", "loop")
#: an insertion never goes deeper than this multiple of the planned depth
MAX_DEPTH_FACTOR = 2.0


@dataclass
class InsertionResult:
    """One insertion, K steps (docs/contract.md `/insertion/<target>/<strategy>`).

    depth_mm (K,), tip (K, 2), target (K, 2), needle_force_mN (K,), stuck,
    slipping (K,) int, min_clearance_mm (K,) (0.0 without obstacles: see
    has_obstacles), strokes (K, C) mm, displacement (K, N, 2) mm (None when
    not kept); outcome: miss_mm (target to the needle line), depth_error_mm
    (tip minus target along n), obstacle_touched, stop_reason ("depth
    reached", "target reached", or why it stopped early), unsettled (steps
    whose active set did not settle), x (N, 2) the final positions.
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


def run_insertion(
    tissue: Tissue,
    x0: np.ndarray,
    strokes: np.ndarray,
    entry: np.ndarray,
    direction: np.ndarray,
    planned_depth_mm: float,
    target_rest: np.ndarray,
    params: NeedleParams,
    strategy: str = "none",
    *,
    controller=None,
    measure: Callable[[np.ndarray], np.ndarray] | None = None,
    keep_displacement: bool = True,
    target_name: str = "",
    model: Tissue | None = None,
    model_x0: np.ndarray | None = None,
) -> InsertionResult:
    """Insert from the equilibrium x0 (N, 2) at cup strokes (C,) mm along the plan; never raises on a solver failure.

    entry (2,), direction (2,) unit, planned_depth_mm: the plan; target_rest
    (2,): the target in the rest mesh; controller: the `controller` config
    section (gains, rate) for "loop"; measure: the camera, true (2,) →
    measured (2,) (default exact). `tissue` is the plant; model: the
    controller's tissue for "loop" (default: the plant itself), model_x0
    (N, 2) its equilibrium at the strokes (solved from x0 when not given).
    A failed step ends the insertion with the reason in stop_reason; what
    was reached is kept.
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    t0 = time.perf_counter()
    measure = measure or (lambda y: y)
    n = np.asarray(direction, float) / np.linalg.norm(direction)
    p0 = np.asarray(entry, float)
    state = NeedleState(p0, n)
    probe = probe_targets(tissue.mesh, np.asarray(target_rest, float)[None])
    obstacles = [o.outline for o in tissue.scene.obstacles]
    embedding = embed_outlines(tissue.mesh, obstacles)
    candidates = free_nodes(tissue)
    x, s = np.array(x0, float), np.array(strokes, float)
    lo = np.array([c.stroke_min_mm for c in tissue.scene.cups])
    hi = np.array([c.stroke_max_mm for c in tissue.scene.cups])
    pid = controller_model = None
    if strategy == "loop":
        pid = PID(controller.kp, controller.ki, controller.kd, 1.0 / controller.rate_hz)
        controller_model = _model_state(tissue, model, x, model_x0, s)
    rows: list[tuple] = []
    frames: list[np.ndarray] = []
    unsettled, reason = 0, ""
    max_depth = MAX_DEPTH_FACTOR * planned_depth_mm + params.step_mm
    last = False
    while True:
        y = target_positions(probe, x)[0]
        goal = planned_depth_mm if strategy == "none" else float((measure(y) - p0) @ n)
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
                x, s = _loop_correction(tissue, controller_model, state, x, s, out.loads, probe, pid, lo, hi, p0, measure)
        except SolverError as exc:
            reason = f"solver failed at depth {state.depth_mm:.3g} mm: {exc}"
            break
        unsettled += not out.settled
        y = target_positions(probe, x)[0]
        rows.append((state.depth_mm, state.tip, y, out.force_mN, out.stuck, out.slipping,
                     _clearance(embedding, x, p0, state.tip, params.radius_mm), s.copy()))
        if keep_displacement:
            frames.append(x - tissue.rest)
    return _result(tissue, target_name, strategy, p0, n, rows, frames, keep_displacement, x, state, bool(obstacles),
                   reason, unsettled, time.perf_counter() - t0, probe, s)


def _model_state(plant, model, x0, model_x0, strokes) -> ModelState:
    """The controller's model at the start: the plant itself, or its own equilibrium at the strokes."""
    if model is None or model is plant:
        return ModelState(plant, plant, x0, x0, strokes)
    if model_x0 is None:  # x0 only warms the solve: the model's equilibrium does not depend on it
        model_x0 = solve_equilibrium(model, strokes, start=x0, start_strokes=strokes).x
    return ModelState(model, plant, model_x0, x0, strokes)


def _loop_correction(tissue, controller_model, state, x, s, loads, probe, pid, lo, hi, p0, measure):
    """One §6 loop iteration on the miss across the needle, the needle holding its captured nodes.

    J is the controller's (`ModelState`: its model, at its equilibrium under
    the needle); the plant is then solved at the command with the same hold.
    """
    controller_model.follow(state, x, s, loads)
    J, responses = controller_model.jacobian(state, probe, state.solver)
    y = target_positions(probe, x)[0]
    e = np.array([-(measure(y) - p0) @ state.across])
    ds, _, _ = split_error(J, e)
    command, _ = pid.command(s, ds, lo, hi)
    if np.allclose(command, s, atol=1e-12, rtol=0):
        return x, s
    return _move_plant(tissue, state, x, s, command, loads, responses), command


def _move_plant(tissue, state, x, s, command, loads, responses) -> np.ndarray:
    """The plant's equilibrium (N, 2) at the command (C,) with the needle's hold and loads, from x at s.

    Chord steps on the insertion's kept factorisation from the model's
    linear response to the stroke change; Newton (as a step's fallback)
    when they fail or that start inverts an element.
    """
    hold = hold_at(state, x)
    start = hold.place(tissue.apply_strokes(x + np.tensordot(command - s, responses, axes=1), command))
    _, g = objective_gradient(tissue, start, None, loads, require_positive_J=True)
    if g is not None:
        try:
            return state.solver.converge(start, g, hold, STEP_TOL, loads)[0]
        except ChordFailed:
            pass
    r = solve_equilibrium(tissue, command, start=x, start_strokes=s, conditions=needle_conditions(state, loads),
                          tol=STEP_TOL)
    return r.x


def _clearance(embedding, x, p0, tip, radius_mm) -> float:
    """Shaft (p0 → tip, radius) to the nearest deformed obstacle (mm); +inf without obstacles."""
    outlines = deformed_outlines(embedding, x)
    if not outlines:
        return float("inf")
    return min(segment_polygon_distance(p0, tip, poly) for poly in outlines) - radius_mm


def _result(tissue, name, strategy, p0, n, rows, frames, keep, x, state, has_obstacles, reason, unsettled, wall,
            probe, s) -> InsertionResult:
    k = len(rows)
    col = (lambda i, shape=(): np.array([r[i] for r in rows], float).reshape((k,) + shape))
    clearance = col(6)
    y = target_positions(probe, x)[0]
    miss, depth_error = miss_and_depth_error(y, p0, n, state.depth_mm)
    touched = bool(has_obstacles and k and np.min(clearance) <= 0.0)
    return InsertionResult(
        name, strategy, p0, n, col(0), col(1, (2,)), col(2, (2,)), col(3), col(4).astype(np.int64),
        col(5).astype(np.int64), np.where(np.isfinite(clearance), clearance, 0.0),
        np.array([r[7] for r in rows], float).reshape(k, tissue.n_cups),
        np.array(frames) if keep else None, miss, depth_error, touched, has_obstacles,
        reason, unsettled, wall, x,
    )
