"""Closed-loop target manipulation, one target end to end (docs/model.md §6, paper §3.5).

Two tissues take part in a manipulation and are kept apart on purpose:

* the **plant** is the simulated "true" tissue with its actuator: the
  controller commands strokes, the actuator realises them (limits,
  resolution, backlash), the truth settles into its equilibrium and the
  camera sees the target there;
* the **controller** owns its model tissue, solves it at the *commanded*
  strokes and keeps the cup–target Jacobian J (docs/model.md §5) at that model
  equilibrium.

A trial perturbs the truth (E, ν, η, fiber angle, actuator, measurement)
without touching the controller. When the truth *is* the model (the same
`Tissue` object) and the actuator realised the command exactly, the
controller adopts the plant's equilibrium instead of solving it again.

One loop iteration k (docs/model.md §6), Δt = 1/rate_hz:

    y_k  = the sensor's reading of the true state     (camera: + localisation bias)
    e_k  = P (y_d − y_k)   (the miss across the needle axis n, P = I − n nᵀ)
    δs*_k = argmin ‖P J δs − e_k‖² + λ‖δs‖²      bounded: strokes, speed·Δt
    s_{k+1} = s_k + Kp δs*_k + Ki Σ δs*·Δt + Kd (δs*_k − δs*_{k−1})/Δt
    clip to the stroke limits (anti-windup: no integration while that
    saturates), quantise to the resolution, actuate, solve the truth, solve
    the model at the command and update J there.

The law is the paper's velocity form (its eq. for μ(t) drives the actuator
speed), so the integral term is summed twice: it removes a steady bias but
leaves a slow mode (for the default gains a pole near 0.99 per iteration).
The loop therefore stops as soon as the correctable error is within
tolerance, and declares "stalled" when the error stops improving.

The part of the driven error no stroke within the limits can remove is
reported as the uncorrectable error (`control.allocation`).

Both tissues follow their equilibria with `solvers.tracking.TrackedEquilibrium`
(tangent predictor, then the one Newton iteration with chord steps; the
exact tangent at the converged state gives J). Big moves may start from a
known nearby equilibrium (e.g. the planner's state at the plan's strokes).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from scissor_cli.config import ControllerConfig, controller_instance
from scissor_cli.control.actuator import Actuator, quantise
from scissor_cli.control.allocation import stroke_step
from scissor_cli.control.broyden import BroydenCorrection
from scissor_cli.control.corridor_check import Corridor, corridor_at
from scissor_cli.control.law import PID, stalled, traveling
from scissor_cli.control.plant import Controller, ModelPaths, Plant, TruthFactory, TruthPerturbation, true_tissue
from scissor_cli.control.plugin import ControllerLaw, checked_velocity, drive, frame_info, observation
from scissor_cli.control.result import History, LoopResult
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import probe_targets
from scissor_cli.sensing.sensor import EXACT, Sensor
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.linear import release_free

#: A step this small (mm) towards a stroke limit the command sits at ends the loop ("stroke_limit").
LIMIT_SLACK_MM = 1.0e-3


def run_loop(
    plant: Plant,
    controller: Controller,
    desired: np.ndarray,
    cfg: ControllerConfig,
    sensor: Sensor = EXACT,
    target: str = "",
    cup_names: Optional[list[str]] = None,
    direction: Optional[np.ndarray] = None,
    law: Optional[ControllerLaw] = None,
) -> LoopResult:
    """The closed loop of docs/model.md §6 from the plant's and controller's current states.

    The target is seen only through `sensor` (its reading of the plant's true state).

    desired (2,) mm; direction (2,) the needle axis n: with cfg.error
    "miss" the loop drives the miss P (y_d − y) across it (the along-axis
    part is reported, for the depth); "position" or no axis: the full error.
    Each step is the bounded least-squares step of `allocation.stroke_step`
    (stroke limits, and the drives' speed over one control period), with
    the model's J or, with cfg.jacobian_update "broyden", that J corrected
    from the observed moves (`control.broyden`). Stops when the correctable part of the measured error
    is ≤ cfg.tolerance_mm ("tolerance"), after cfg.max_iterations moves
    ("max_iterations"), when the best correctable error has not improved by
    10 % over the last 5 measurements ("stalled"; not while the speed limit
    cuts a step and the command still goes one way, `law.traveling`), when the command sits at
    a stroke limit and asks to go further ("stroke_limit"), or when a solve
    fails ("solver_failed", the reason in `message`; the failed move is not
    in the history).

    With an outside law (`law`, or `cfg.law` "mpc" / "python", docs/model.md
    §22) the PID is replaced: each frame the law gets the observation and
    info of `control.plugin` and returns velocities (C,) mm/s, which go
    through `plugin.drive`; the stops are the same, plus
    "controller_failed" when the law raises or returns no finite
    velocities (the message says which). The history gains `clipped`.
    """
    t0 = time.perf_counter()
    desired = np.asarray(desired, float)
    cup_names = cup_names or [f"cup{c}" for c in range(controller.n_cups)]
    dt = 1.0 / cfg.rate_hz
    pid = PID(cfg.kp, cfg.ki, cfg.kd, dt)
    tangent = controller.shares(plant)
    hist, corr_norms = History(), []
    command, sim_t, reason, message = controller.strokes.copy(), 0.0, "", ""
    max_step = plant.actuator.speed_mm_per_s * dt
    correction = BroydenCorrection(sensor.noise_mm) if cfg.jacobian_update == "broyden" else None
    seen = getattr(sensor, "seen", None)  # a body seen by one camera: what it observes (`stroke_step`)
    law = outside_law(cfg) if law is None else law  # (None: the built-in PID)
    clipped = None if law is None else [0]  # cups the drives cut in the move to each row's command
    for k in range(cfg.max_iterations + 1):
        y = sensor.measure(plant.true_state())
        J = controller.jacobian
        if cfg.stop_frames > 1 and controller.n_cups and sensor.noise_mm > 0:  # (noiseless frames agree)
            # _confirmed calls the step function at once, in this iteration: J and command are this step's
            y, waited_s = _confirmed(y, sensor, plant, cfg, dt,
                                     lambda y: stroke_step(J if correction is None else correction.jacobian(J),  # noqa: B023
                                                           desired - y, command, controller.lo, controller.hi,  # noqa: B023
                                                           max_step, direction, cfg.error, seen=seen))
            sim_t += waited_s
        if correction is not None:  # J learnt from the moves so far (control.broyden)
            correction.observe(J, command, y)
            J = correction.jacobian(J)
        step = stroke_step(J, desired - y, command, controller.lo, controller.hi, max_step, direction, cfg.error,
                           seen=seen)
        ds = step.ds
        corr_norms.append(_correctable_norm(step))
        hist.add(sim_t, command, plant.strokes, y, plant.position, corr_norms[-1],
                 np.linalg.norm(step.uncorrectable), step.along_mm)
        if controller.n_cups == 0:
            reason = "tolerance" if corr_norms[-1] <= cfg.tolerance_mm else "stalled"
            message = "no cups: nothing to correct; the miss stays as it is"
            break
        pinned = step.at_limit and np.linalg.norm(step.uncorrectable) > cfg.tolerance_mm
        if pinned and np.max(np.abs(ds), initial=0.0) <= max(controller.resolution_mm, LIMIT_SLACK_MM):
            reason, message = "stroke_limit", "the command sits at a stroke limit and asks to go further"
        elif corr_norms[-1] <= cfg.tolerance_mm and not pinned:
            reason = "tolerance"
        elif k == cfg.max_iterations:
            reason = "max_iterations"
        elif stalled(corr_norms) and not (step.limited and traveling(hist.rows["cmd"])):
            reason = "stalled"  # (moving one way at the drives' top speed is not stalling; chattering is)
        if reason:
            break
        if law is None:
            new, saturated = pid.command(command, ds, controller.lo, controller.hi, controller.resolution_mm)
            if saturated.any() and np.array_equal(new, command):
                # Anti-windup froze the integral and the state will not change: the same command forever.
                reason, message = "stroke_limit", "the command sits at a stroke limit and asks to go further"
                break
        else:
            obs = observation(y, desired, direction, command, sim_t)
            info = frame_info(J, controller.lo, controller.hi, plant.actuator.speed_mm_per_s, dt, cfg.error, k,
                              target, cup_names)
            try:
                if k == 0:
                    law.reset(obs, info)
                velocity = checked_velocity(law.act(obs, info), controller.n_cups)
            except Exception as exc:  # noqa: BLE001 - an outside controller may raise anything: its loop stops
                reason, message = "controller_failed", f"{_law_name(law)}: {type(exc).__name__}: {exc}"
                break
            moved = drive(command, velocity, dt, controller.lo, controller.hi, plant.actuator.speed_mm_per_s,
                          controller.resolution_mm)
            new = moved.command
            clipped.append(moved.clipped)
        tw = time.perf_counter()
        try:
            plant.apply(new, tangent=tangent)
            controller.update(new, plant)
        except SolverError as exc:
            reason, message = "solver_failed", str(exc)
            break
        hist.wall.append(time.perf_counter() - tw)
        sim_t += max(dt, plant.actuator.last_move_s)
        command = new
    result = hist.result(plant, controller, desired, target, "closed", reason, message, time.perf_counter() - t0,
                         cup_names, direction, cfg.error)
    if clipped is not None:
        result.hist_clipped = np.array(clipped[:len(result.hist_time_s)], np.int64)
    return result


def outside_law(cfg: ControllerConfig) -> Optional[ControllerLaw]:
    """A new controller object for `cfg.law` "mpc" or "python" (docs/model.md §22); None for the built-in "pid".

    One per manipulation, so a trial starts from the class's own initial state.
    """
    if cfg.law == "mpc":
        from scissor_cli.control.mpc import MPCLaw  # noqa: PLC0415 - OSQP is loaded only by a run that uses it

        return MPCLaw(cfg.mpc.horizon, cfg.mpc.action_weight)
    if cfg.law == "python":
        return controller_instance(cfg)
    return None


def _law_name(law: ControllerLaw) -> str:
    """"module:Class" of a controller object (the form of `controller.class_path`)."""
    return f"{type(law).__module__}:{type(law).__qualname__}"


def _correctable_norm(step) -> float:
    """The size (mm) of the part of the driven error the step's strokes can remove (what tolerance is held to)."""
    return float(np.hypot(np.linalg.norm(step.correctable), step.along_correctable_mm))


def _confirmed(y, sensor: Sensor, plant: Plant, cfg: ControllerConfig, dt: float, step_at) -> tuple[np.ndarray, float]:
    """The measurement (2,) a stop may be decided on, and the robot time (s) spent taking it.

    A frame within tolerance is not trusted alone: stop_frames − 1 more
    frames at the same strokes (one camera period each) and their mean with
    it replace it, whatever that mean then says. A frame outside tolerance
    is used as it is.
    """
    if _correctable_norm(step_at(y)) > cfg.tolerance_mm:
        return y, 0.0
    frames = [y] + [sensor.measure(plant.true_state()) for _ in range(cfg.stop_frames - 1)]
    return np.mean(frames, axis=0), (cfg.stop_frames - 1) * dt


def open_loop(
    plant: Plant,
    controller: Controller,
    desired: np.ndarray,
    sensor: Sensor = EXACT,
    rate_hz: float = 10.0,
    target: str = "",
    cup_names: Optional[list[str]] = None,
    direction: Optional[np.ndarray] = None,
    mode: str = "miss",
) -> LoopResult:
    """One Jacobian step from the current (rest) state: s = s_0 + J⁺ (y_d − y_0), applied once.

    The baseline the closed loop is compared with: the model's linear
    prediction at rest, no feedback. Same result shape, iterations = 1.
    """
    t0 = time.perf_counter()
    desired = np.asarray(desired, float)
    cup_names = cup_names or [f"cup{c}" for c in range(controller.n_cups)]
    hist = History()
    y = sensor.measure(plant.true_state())
    s0 = controller.strokes.copy()
    seen = getattr(sensor, "seen", None)
    step = stroke_step(controller.jacobian, desired - y, s0, controller.lo, controller.hi, None, direction, mode,
                       seen=seen)
    ds = step.ds
    hist.add(0.0, s0, plant.strokes, y, plant.position, np.linalg.norm(step.correctable),
             np.linalg.norm(step.uncorrectable), step.along_mm)
    command = quantise(s0 + ds, controller.lo, controller.hi, controller.resolution_mm)
    reason, message = "max_iterations", "open loop: one Jacobian step"
    tw = time.perf_counter()
    try:
        plant.apply(command, tangent=False)
    except SolverError as exc:
        reason, message = "solver_failed", str(exc)
    else:
        hist.wall.append(time.perf_counter() - tw)
        y = sensor.measure(plant.true_state())
        step = stroke_step(controller.jacobian, desired - y, command, controller.lo, controller.hi, None, direction,
                           mode, seen=seen)
        hist.add(max(1.0 / rate_hz, plant.actuator.last_move_s), command, plant.strokes, y, plant.position,
                 np.linalg.norm(step.correctable), np.linalg.norm(step.uncorrectable), step.along_mm)
    return hist.result(plant, controller, desired, target, "open", reason, message, time.perf_counter() - t0, cup_names,
                       direction, mode)


@dataclass(frozen=True)
class TargetRun:
    """How one target's manipulation runs, besides the model, the rest and desired points and the gains.

    truth: how the true tissue differs from the model; resolution_mm,
    backlash_mm: the actuator's (the controller knows the resolution, not
    the backlash); sensor: how the target is seen; corridor: the plan's
    needle corridor, checked on the final true state; mode "closed" (the
    loop) or "open" (one Jacobian step, the baseline); target: its name;
    tol: the solves' relative residual; truth_tol: the true tissue's, when
    it is not the model itself (None: tol; a camera reads the truth to its
    noise, the controller's J wants the model tighter); guess: (strokes
    (C,), x (N, 2)) a known equilibrium of the model the first big move
    may start from (x may be a function returning it: called only if a
    move does start there);
    truth_guess: the same for the truth (x on the truth's mesh: an earlier
    loop's end on the same true tissue);
    direction (2,): the needle axis of the miss (default the corridor's);
    truth_factory: makes another true tissue (the 3-D slab) and its view
    from the perturbation; controller_factory (lo, hi, resolution_mm, tol)
    → controller: a controller on another model (docs/model.md §15);
    model_paths: the model's states earlier loops of this target solved in
    this process (`plant.ModelPaths`; for the model's own controller);
    law: an outside controller object (`plugin.ControllerLaw`) used instead
    of the config's `law` (the Python API's).
    """

    truth: TruthPerturbation = TruthPerturbation()
    sensor: Sensor = EXACT
    resolution_mm: float = 0.0
    backlash_mm: float = 0.0
    corridor: Optional[Corridor] = None
    mode: str = "closed"
    target: str = ""
    tol: float = 1e-10
    truth_tol: Optional[float] = None
    guess: Optional[tuple[np.ndarray, np.ndarray]] = None
    truth_guess: Optional[tuple[np.ndarray, np.ndarray]] = None
    direction: Optional[np.ndarray] = None
    truth_factory: Optional[TruthFactory] = None
    controller_factory: Optional[Callable] = None
    model_paths: Optional[ModelPaths] = None
    law: Optional[ControllerLaw] = None


def run_target(model: Tissue, target_rest: np.ndarray, desired: np.ndarray, cfg: ControllerConfig,
               run: TargetRun = TargetRun()) -> LoopResult:
    """Manipulate one target from rest to `desired` (2,) mm; closed loop or the open-loop baseline.

    Builds the truth (`true_tissue(model, run.truth)`, or `run.truth_factory`'s
    tissue and view), its actuator (the scene's limits and speeds with the
    run's resolution and backlash), the controller on the model (same limits
    and resolution; or `run.controller_factory`'s, whose `model` then still
    carries the scene and the corridor check), and runs `run_loop` (mode
    "closed") or `open_loop` ("open"). With a corridor, the needle corridor
    through the reached true target is checked on the final true state:
    `corridor_clear`, `clearance_mm`, `corridor_entry`.
    """
    plant, controller, direction = loop_parts(model, target_rest, run)
    scene = model.scene
    names = list(scene.cup_names)
    if run.mode == "closed":
        result = run_loop(plant, controller, desired, cfg, run.sensor, run.target, names, direction, run.law)
    elif run.mode == "open":
        result = open_loop(plant, controller, desired, run.sensor, cfg.rate_hz, run.target, names, direction,
                           cfg.error)
    else:
        raise ValueError(f"mode must be 'closed' or 'open', got {run.mode!r}")
    if run.corridor is not None:
        corridor = run.corridor
        entry, clearance = corridor_at(model if run.truth_factory else plant.tissue, plant.layer_x,
                                       result.final_position, corridor)
        result.corridor_entry, result.clearance_mm = entry, clearance
        result.corridor_direction = corridor.direction
        result.corridor_clear = bool(clearance > 0)
    for part in (plant, controller):  # done: the next loop's new trackers take their factors' analyses over
        tracker = getattr(part, "eq", None)
        if tracker is not None:
            release_free(tracker.tissue, tracker.factors)
    return result


def loop_parts(model: Tissue, target_rest: np.ndarray, run: TargetRun = TargetRun()) -> tuple[Plant, Controller,
                                                                                               Optional[np.ndarray]]:
    """The plant, the controller and the needle axis (d,) (or None) `run_target` runs its loop on.

    The truth is `true_tissue(model, run.truth)` or `run.truth_factory`'s
    tissue and view, its actuator the scene's limits and speeds with the
    run's resolution and backlash; the controller is on the model (or
    `run.controller_factory`'s). Both start at rest; `run.guess` is handed
    to the trackers on `model`.
    """
    direction = needle_axis(run)
    scene = model.scene
    if model.dim == 3:  # a body: the lesion carried as its region's mean
        probe = model.probe(np.asarray(target_rest, float)[None])
    else:
        probe = probe_targets(model.mesh, np.asarray(target_rest, float)[None])
    actuator = Actuator.from_scene(scene, run.resolution_mm, run.backlash_mm)
    truth_tol = run.tol if run.truth_tol is None else run.truth_tol
    if run.truth_factory is None:
        truth = true_tissue(model, run.truth)
        plant = Plant(truth, actuator, probe, run.tol if truth is model else truth_tol)
    else:
        plant = Plant(**_made(run.truth_factory, run.truth), actuator=actuator, probe=probe, tol=truth_tol)
    if run.controller_factory is None:
        controller = Controller(model, probe, actuator.lo, actuator.hi, run.resolution_mm, run.tol, run.model_paths)
    else:
        controller = run.controller_factory(actuator.lo, actuator.hi, run.resolution_mm, run.tol)
    if controller.shares(plant):
        plant.eq.adopt(controller.eq)  # both at rest: one tangent serves both
    if run.guess is not None:  # the guess is the layer's: for the trackers on `model` only
        trackers = [plant.eq] if run.truth_factory is None else []
        trackers += [controller.eq] if getattr(controller, "tissue", None) is model else []
        for eq in trackers:
            eq.guesses.append((np.asarray(run.guess[0], float),
                               run.guess[1] if callable(run.guess[1]) else np.asarray(run.guess[1], float)))
    if run.truth_guess is not None:
        plant.eq.guesses.append((np.asarray(run.truth_guess[0], float), np.asarray(run.truth_guess[1], float)))
    return plant, controller, direction


def needle_axis(run: TargetRun) -> Optional[np.ndarray]:
    """The axis (d,) the loop takes the miss across: the run's direction, else its corridor's, else None."""
    if run.direction is None and run.corridor is not None:
        return run.corridor.direction
    return run.direction


def _made(factory: TruthFactory, truth: TruthPerturbation) -> dict:
    tissue, view = factory(truth)
    return {"tissue": tissue, "view": view}
