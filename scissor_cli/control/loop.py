"""Closed-loop target manipulation (MODEL.md §6, paper §3.5).

Two tissues take part in a manipulation and are kept apart on purpose:

* the **plant** is the simulated "true" tissue with its actuator: the
  controller commands strokes, the actuator realises them (limits,
  resolution, backlash), the truth settles into its equilibrium and the
  camera sees the target there;
* the **controller** owns its model tissue, solves it at the *commanded*
  strokes and keeps the cup–target Jacobian J (MODEL.md §5) at that model
  equilibrium.

A trial perturbs the truth (E, ν, η, fiber angle, actuator, measurement)
without touching the controller. When the truth *is* the model (the same
`Tissue` object) and the actuator realised the command exactly, the
controller adopts the plant's equilibrium instead of solving it again.

One loop iteration k (MODEL.md §6), Δt = 1/rate_hz:

    y_k  = measure(true target)                      camera + localisation bias
    e_k  = y_d − y_k,   δs*_k = J⁺ e_k               least squares, (C,)
    s_{k+1} = s_k + Kp δs*_k + Ki Σ δs*·Δt + Kd (δs*_k − δs*_{k−1})/Δt
    clip to the stroke limits (anti-windup: no integration while that
    saturates), quantise to the resolution, actuate, solve the truth, solve
    the model at the command and update J there.

The law is the paper's velocity form (its eq. for μ(t) drives the actuator
speed), so the integral term is summed twice: it removes a steady bias but
leaves a slow mode (for the default gains a pole near 0.99 per iteration).
The loop therefore stops as soon as the correctable error is within
tolerance, and declares "stalled" when the error stops improving.

With fewer cups than target coordinates only the part of e in range(J) can
be corrected; the rest, e − J J⁺ e, is reported as the uncorrectable error.

Both tissues follow their equilibria with `solvers.tracking.Equilibrium`
(tangent predictor, then the one Newton iteration with chord steps; the
exact tangent at the converged state gives J). Big moves may start from a
known nearby equilibrium (e.g. the planner's state at the plan's strokes).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from scissor_cli.scene.camera import Camera
from scissor_cli.config import ControllerConfig
from scissor_cli.mesh.probe import TargetProbe, apply_probe, probe_targets, target_positions
from scissor_cli.solvers.tracking import Equilibrium
from scissor_cli.mesh.outlines import Embedding, boundary_loop, deformed_outlines, embed_outlines
from scissor_cli.planning.corridor import corridor_clearance, entry_points
from scissor_cli.solvers.common import SolverError
from scissor_cli.mechanics.tissue import Tissue

#: Why `run_loop` stopped.
STOP_REASONS = ("tolerance", "max_iterations", "stalled", "stroke_limit", "solver_failed")

#: Iterations without a 10 % better correctable error before the loop is "stalled".
STALL_PATIENCE = 5
STALL_GAIN = 0.9



# --------------------------------------------------------------------------
# Strokes: limits, resolution, the actuator (truth side)


def quantise(command: np.ndarray, lo: np.ndarray, hi: np.ndarray, resolution_mm: float) -> np.ndarray:
    """Strokes (C,) mm clipped to [lo, hi] and rounded to multiples of resolution_mm (0: continuous).

    Rounding never leaves the limits: it stops at the last multiple inside them.
    """
    c = np.clip(np.asarray(command, float), lo, hi)
    if resolution_mm <= 0:
        return c
    r = resolution_mm
    q_lo, q_hi = np.ceil(lo / r - 1e-9) * r, np.floor(hi / r + 1e-9) * r
    return np.clip(np.round(c / r) * r, q_lo, q_hi) + 0.0  # + 0.0: no -0.0 in the history


@dataclass
class Actuator:
    """The cups' linear drives (C cups); what the truth realises of a command.

    lo, hi (C,) mm: stroke limits; speed_mm_per_s (C,); resolution_mm: the
    drive's step (0 = continuous); backlash_mm: play in the drive. On a
    direction reversal the first backlash_mm of commanded motion does not
    move the cup; the first move after construction is lossless (the drive
    starts engaged in that move's direction).

    State: `motor` (C,) the drive position, `stroke` (C,) the cup's, and the
    play band offset (NaN until a cup first moves). `last_move_s` is the
    duration of the last move at the drives' speed.
    """

    lo: np.ndarray
    hi: np.ndarray
    speed_mm_per_s: np.ndarray
    resolution_mm: float = 0.0
    backlash_mm: float = 0.0
    motor: np.ndarray = field(default=None)  # type: ignore[assignment]
    stroke: np.ndarray = field(default=None)  # type: ignore[assignment]
    last_move_s: float = 0.0

    def __post_init__(self):
        self.lo = np.atleast_1d(np.asarray(self.lo, float))
        self.hi = np.atleast_1d(np.asarray(self.hi, float))
        self.speed_mm_per_s = np.broadcast_to(np.asarray(self.speed_mm_per_s, float), self.lo.shape).copy()
        self.motor = np.zeros_like(self.lo) if self.motor is None else np.asarray(self.motor, float).copy()
        self.stroke = self.motor.copy() if self.stroke is None else np.asarray(self.stroke, float).copy()
        # The cup stays in [motor − offset, motor − offset + backlash]; NaN: not engaged yet.
        self._offset = np.full_like(self.lo, np.nan)

    @classmethod
    def from_scene(cls, scene, resolution_mm: float = 0.0, backlash_mm: float = 0.0) -> "Actuator":
        """The drives of a scene's cups (limits and speeds from the config)."""
        return cls(
            lo=np.array([c.stroke_min_mm for c in scene.cups]),
            hi=np.array([c.stroke_max_mm for c in scene.cups]),
            speed_mm_per_s=np.array([c.speed_mm_per_s for c in scene.cups]),
            resolution_mm=resolution_mm,
            backlash_mm=backlash_mm,
        )

    def realisable(self, command) -> np.ndarray:
        """The command (C,) mm clipped to the limits and quantised: where the motor goes."""
        return quantise(command, self.lo, self.hi, self.resolution_mm)

    def move_time(self, command) -> float:
        """Seconds the drives need to reach `command` (C,) from where they are."""
        return float(np.max(np.abs(self.realisable(command) - self.motor) / self.speed_mm_per_s, initial=0.0))

    def apply(self, command) -> np.ndarray:
        """Drive to `command` (C,) mm; returns the cup strokes (C,) mm actually reached."""
        u = self.realisable(command)
        self.last_move_s = self.move_time(u)
        first = np.isnan(self._offset) & (u != self.motor)
        # Engaged on the side that pushes: moving up the cup sits at the band's bottom, moving down at its top.
        self._offset[first] = np.where(u[first] > self.motor[first], 0.0, self.backlash_mm)
        engaged = ~np.isnan(self._offset)
        off = np.nan_to_num(self._offset)
        played = np.clip(self.stroke, u - off, u - off + self.backlash_mm)
        self.stroke = np.where(engaged, played, u)
        self.motor = u
        return self.stroke.copy()


# --------------------------------------------------------------------------
# Measurement


@dataclass(frozen=True)
class Measurement:
    """How the target is seen: a camera (pixel noise + rounding) and a localisation bias.

    camera None is the ideal measurement: the true position exactly, no
    rounding, no random draws. bias_mm (2,) is a fixed per-trial offset of
    the image-based target localisation (drawn by the caller). noise_px
    overrides the camera's pixel noise σ.
    """

    camera: Optional[Camera] = None
    bias_mm: tuple[float, float] = (0.0, 0.0)
    noise_px: Optional[float] = None

    @property
    def ideal(self) -> bool:
        return self.camera is None and not np.any(self.bias_mm)

    def measure(self, true_position: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The measured target (2,) mm of the true target (2,) mm."""
        p = np.asarray(true_position, float)
        if self.camera is not None:
            p = self.camera.measure(p[None], rng, self.noise_px)[0]
        return p + np.asarray(self.bias_mm, float)


# --------------------------------------------------------------------------
# Plant and controller


class Plant:
    """The simulated truth: tissue + actuator + current equilibrium + the target's probe."""

    def __init__(self, tissue: Tissue, actuator: Actuator, probe: TargetProbe, tol: float = 1e-10):
        self.tissue, self.actuator, self.probe = tissue, actuator, probe
        self.eq = Equilibrium(tissue, tol)

    @property
    def position(self) -> np.ndarray:
        """The true target (2,) mm."""
        return target_positions(self.probe, self.eq.x)[0]

    @property
    def strokes(self) -> np.ndarray:
        return self.eq.strokes

    def apply(self, command: np.ndarray, tangent: bool = False) -> np.ndarray:
        """Actuate `command` (C,) mm and settle the truth; returns the actual strokes (C,) mm."""
        actual = self.actuator.apply(command)
        self.eq.move_to(actual, tangent=tangent)
        return actual


class Controller:
    """The controller's model: tissue + equilibrium at the commanded strokes + J there.

    lo, hi (C,) mm and resolution_mm are what it may command (the drives'
    nominal limits; it does not know the backlash).
    """

    def __init__(self, tissue: Tissue, probe: TargetProbe, lo, hi, resolution_mm: float = 0.0, tol: float = 1e-10):
        self.tissue, self.probe = tissue, probe
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.resolution_mm = resolution_mm
        self.eq = Equilibrium(tissue, tol)
        self.eq.move_to(self.eq.strokes, tangent=True)

    @property
    def jacobian(self) -> np.ndarray:
        """J (2, C) mm/mm of the target at the model equilibrium."""
        return apply_probe(self.probe, self.eq.response)

    @property
    def strokes(self) -> np.ndarray:
        return self.eq.strokes

    def shares(self, plant: Plant) -> bool:
        return plant.tissue is self.tissue

    def update(self, commanded: np.ndarray, plant: Optional[Plant] = None) -> None:
        """Move the model to the commanded strokes (C,) mm and update J there.

        When the plant is this very tissue and sits at exactly these strokes,
        its equilibrium (solved with its tangent) is taken over.
        """
        same_state = plant is not None and self.shares(plant) and np.array_equal(plant.strokes, commanded)
        if same_state and plant.eq.jacobian_is_current:
            self.eq.adopt(plant.eq)
        else:
            self.eq.move_to(commanded, tangent=True)


# --------------------------------------------------------------------------
# The control law


def split_error(J: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """δs* = J⁺ e (C,) mm, the correctable part J δs* (2,) and the rest e − J δs* (2,), mm."""
    ds = np.linalg.lstsq(J, e, rcond=None)[0]
    corr = J @ ds
    return ds, corr, e - corr


@dataclass
class PID:
    """Discrete PID on δs* (C,) with conditional-integration anti-windup (MODEL.md §6).

    s_{k+1} = s_k + Kp δs*_k + Ki I_k + Kd (δs*_k − δs*_{k−1})/Δt,
    I_k = I_{k−1} + δs*_k Δt unless that integration pushes a saturated
    command further out of its limits. The derivative starts at 0 (no kick).
    """

    kp: float
    ki: float
    kd: float
    dt: float
    integral: np.ndarray = None  # type: ignore[assignment]
    previous: Optional[np.ndarray] = None

    def command(self, s: np.ndarray, ds: np.ndarray, lo, hi, resolution_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The next command (C,) mm from the current one s (C,) and δs* (C,); and which cups saturate (C,) bool."""
        if self.integral is None:
            self.integral = np.zeros_like(ds)
        deriv = np.zeros_like(ds) if self.previous is None else (ds - self.previous) / self.dt
        base = s + self.kp * ds + self.kd * deriv
        trial = self.integral + ds * self.dt
        raw = base + self.ki * trial
        out_hi, out_lo = raw > hi, raw < lo
        # Integrate only where it does not drive a saturated command further out.
        wind = (out_hi & (ds > 0)) | (out_lo & (ds < 0))
        self.integral = np.where(wind, self.integral, trial)
        self.previous = ds.copy()
        raw = base + self.ki * self.integral
        return quantise(raw, lo, hi, resolution_mm), (raw > hi) | (raw < lo)


# --------------------------------------------------------------------------
# Results


@dataclass
class LoopResult:
    """One manipulation of one target (closed or open loop). mm, s.

    final_position (2,): true target at the end; final_error (2,) = true −
    desired (x, y); correctable_error_mm / uncorrectable_error_mm: norms of
    the parts of (desired − true) inside / orthogonal to range(J) at the
    end (J the controller's). iterations: moves applied. time_s: wall clock
    of the loop; sim_time_s: the robot's time (moves at the drives' speed,
    at least 1/rate_hz each).

    History, one row per measurement (K = iterations + 1 rows, row 0 at
    rest before any move): time_s (K,) robot time, strokes_cmd (K, C) the
    commanded strokes in effect, strokes (K, C) the actual ones, measured
    (K, 2), true (K, 2), error (K, 2) = true − desired, correctable (K,) and
    uncorrectable (K,) norms of the measured error the controller saw.
    step_wall_s (K − 1,) is the compute time of each iteration (truth solve
    + model solve + J update), not part of the deterministic history.
    """

    target: str
    mode: str  # "closed" | "open"
    desired: np.ndarray
    final_position: np.ndarray
    final_error: np.ndarray
    correctable_error_mm: float
    uncorrectable_error_mm: float
    iterations: int
    time_s: float
    sim_time_s: float
    stop_reason: str
    converged: bool
    cup_names: list[str]
    hist_time_s: np.ndarray
    hist_strokes_cmd: np.ndarray
    hist_strokes: np.ndarray
    hist_measured: np.ndarray
    hist_true: np.ndarray
    hist_error: np.ndarray
    hist_correctable: np.ndarray
    hist_uncorrectable: np.ndarray
    step_wall_s: np.ndarray
    message: str = ""
    final_x: Optional[np.ndarray] = None  # (N, 2) true node positions at the end
    corridor_clear: Optional[bool] = None  # None: no corridor to check
    clearance_mm: float = float("nan")
    corridor_entry: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    corridor_direction: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))

    @property
    def history(self) -> dict[str, np.ndarray]:
        """The history arrays by name: time_s (K,), strokes_cmd (K, C), strokes (K, C), measured,
        true, error (K, 2), correctable_mm, uncorrectable_mm (K,)."""
        return {
            "time_s": self.hist_time_s, "strokes_cmd": self.hist_strokes_cmd, "strokes": self.hist_strokes,
            "measured": self.hist_measured, "true": self.hist_true, "error": self.hist_error,
            "correctable_mm": self.hist_correctable, "uncorrectable_mm": self.hist_uncorrectable,
        }

    @property
    def final_strokes(self) -> np.ndarray:
        """Actual strokes (C,) mm at the end."""
        return self.hist_strokes[-1]

    @property
    def final_error_mm(self) -> float:
        return float(np.linalg.norm(self.final_error))

    def history_table(self) -> tuple[list[str], np.ndarray]:
        """Column names and the (K, n) float64 table of the history, for HDF5.

        Columns: time_s, stroke_cmd_<cup>..., stroke_<cup>..., measured_x,
        measured_y, true_x, true_y, error_x, error_y, correctable_mm,
        uncorrectable_mm (all mm except time_s in s).
        """
        names = (
            ["time_s"]
            + [f"stroke_cmd_{c}" for c in self.cup_names]
            + [f"stroke_{c}" for c in self.cup_names]
            + ["measured_x", "measured_y", "true_x", "true_y", "error_x", "error_y", "correctable_mm", "uncorrectable_mm"]
        )
        table = np.column_stack(
            [
                self.hist_time_s, self.hist_strokes_cmd, self.hist_strokes, self.hist_measured,
                self.hist_true, self.hist_error, self.hist_correctable, self.hist_uncorrectable,
            ]
        ).astype(np.float64)
        return names, table


class _History:
    """Rows collected during a loop."""

    def __init__(self):
        self.rows: dict[str, list] = {k: [] for k in ("t", "cmd", "act", "meas", "true", "corr", "unc")}
        self.wall: list[float] = []

    def add(self, t, cmd, act, meas, true, corr, unc):
        for k, v in zip(("t", "cmd", "act", "meas", "true", "corr", "unc"), (t, cmd, act, meas, true, corr, unc)):
            self.rows[k].append(np.array(v, float))

    def result(self, plant: Plant, controller: Controller, desired, target, mode, reason, message, wall,
               cup_names) -> LoopResult:
        r = {k: np.array(v) for k, v in self.rows.items()}
        true = plant.position
        _, corr, unc = split_error(controller.jacobian, desired - true)
        return LoopResult(
            target=target, mode=mode, desired=np.asarray(desired, float), final_position=true,
            final_error=true - desired,
            correctable_error_mm=float(np.linalg.norm(corr)), uncorrectable_error_mm=float(np.linalg.norm(unc)),
            iterations=len(r["t"]) - 1, time_s=wall, sim_time_s=float(r["t"][-1]),
            stop_reason=reason, converged=reason == "tolerance", cup_names=list(cup_names),
            hist_time_s=r["t"], hist_strokes_cmd=r["cmd"], hist_strokes=r["act"], hist_measured=r["meas"],
            hist_true=r["true"], hist_error=r["true"] - desired, hist_correctable=r["corr"],
            hist_uncorrectable=r["unc"], step_wall_s=np.array(self.wall), message=message, final_x=plant.eq.x,
        )


# --------------------------------------------------------------------------
# Loops


def _stalled(corr_history: list[float]) -> bool:
    """No 10 % better correctable error in the last STALL_PATIENCE measurements than before them."""
    if len(corr_history) <= STALL_PATIENCE:
        return False
    return min(corr_history[-STALL_PATIENCE:]) > STALL_GAIN * min(corr_history[:-STALL_PATIENCE])


def run_loop(
    plant: Plant,
    controller: Controller,
    desired: np.ndarray,
    cfg: ControllerConfig,
    measurement: Measurement = Measurement(),
    rng: Optional[np.random.Generator] = None,
    target: str = "",
    cup_names: Optional[list[str]] = None,
) -> LoopResult:
    """The closed loop of MODEL.md §6 from the plant's and controller's current states.

    desired (2,) mm. Stops when the correctable part of the measured error
    is ≤ cfg.tolerance_mm ("tolerance"), after cfg.max_iterations moves
    ("max_iterations"), when the best correctable error has not improved by
    10 % over the last 5 measurements ("stalled"), when the command sits at
    a stroke limit and asks to go further ("stroke_limit"), or when a solve
    fails ("solver_failed", the reason in `message`; the failed move is not
    in the history).
    """
    t0 = time.perf_counter()
    rng = rng if rng is not None else np.random.default_rng(0)
    desired = np.asarray(desired, float)
    cup_names = cup_names or [f"cup{c}" for c in range(controller.tissue.n_cups)]
    dt = 1.0 / cfg.rate_hz
    pid = PID(cfg.kp, cfg.ki, cfg.kd, dt)
    tangent = controller.shares(plant)
    hist, corr_norms = _History(), []
    command, sim_t, reason, message = controller.strokes.copy(), 0.0, "", ""
    for k in range(cfg.max_iterations + 1):
        y = measurement.measure(plant.position, rng)
        ds, corr, unc = split_error(controller.jacobian, desired - y)
        corr_norms.append(float(np.linalg.norm(corr)))
        hist.add(sim_t, command, plant.strokes, y, plant.position, corr_norms[-1], np.linalg.norm(unc))
        if corr_norms[-1] <= cfg.tolerance_mm:
            reason = "tolerance"
        elif k == cfg.max_iterations:
            reason = "max_iterations"
        elif _stalled(corr_norms):
            reason = "stalled"
        if reason:
            break
        new, saturated = pid.command(command, ds, controller.lo, controller.hi, controller.resolution_mm)
        if saturated.any() and np.array_equal(new, command):
            # Anti-windup froze the integral and the state will not change: the same command forever.
            reason, message = "stroke_limit", "the command sits at a stroke limit and asks to go further"
            break
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
    return hist.result(plant, controller, desired, target, "closed", reason, message, time.perf_counter() - t0, cup_names)


def open_loop(
    plant: Plant,
    controller: Controller,
    desired: np.ndarray,
    measurement: Measurement = Measurement(),
    rng: Optional[np.random.Generator] = None,
    rate_hz: float = 10.0,
    target: str = "",
    cup_names: Optional[list[str]] = None,
) -> LoopResult:
    """One Jacobian step from the current (rest) state: s = s_0 + J⁺ (y_d − y_0), applied once.

    The baseline the closed loop is compared with: the model's linear
    prediction at rest, no feedback. Same result shape, iterations = 1.
    """
    t0 = time.perf_counter()
    rng = rng if rng is not None else np.random.default_rng(0)
    desired = np.asarray(desired, float)
    cup_names = cup_names or [f"cup{c}" for c in range(controller.tissue.n_cups)]
    hist = _History()
    y = measurement.measure(plant.position, rng)
    ds, corr, unc = split_error(controller.jacobian, desired - y)
    s0 = controller.strokes.copy()
    hist.add(0.0, s0, plant.strokes, y, plant.position, np.linalg.norm(corr), np.linalg.norm(unc))
    command = quantise(s0 + ds, controller.lo, controller.hi, controller.resolution_mm)
    reason, message = "max_iterations", "open loop: one Jacobian step"
    tw = time.perf_counter()
    try:
        plant.apply(command, tangent=False)
    except SolverError as exc:
        reason, message = "solver_failed", str(exc)
    else:
        hist.wall.append(time.perf_counter() - tw)
        y = measurement.measure(plant.position, rng)
        _, corr, unc = split_error(controller.jacobian, desired - y)
        hist.add(max(1.0 / rate_hz, plant.actuator.last_move_s), command, plant.strokes, y, plant.position,
                 np.linalg.norm(corr), np.linalg.norm(unc))
    return hist.result(plant, controller, desired, target, "open", reason, message, time.perf_counter() - t0, cup_names)


# --------------------------------------------------------------------------
# One target, end to end


@dataclass(frozen=True)
class TruthPerturbation:
    """How the simulated truth differs from the controller's model (MODEL.md §10).

    E_scale multiplies every element's E: a scalar or a field (M,) (e.g.
    `profiles.TrialDraw.E_field`); fiber_offset_rad turns the fiber (the
    model's global angle + offset); nu and eta_kPa replace the model's when
    given, eta_scale multiplies the model's η otherwise. The neutral
    perturbation leaves the truth = the model.

    Note: with displacement-controlled cups a uniform E scale alone does
    not change the equilibrium (U scales as a whole); it acts through the
    ratio to η, which is not scaled, and through heterogeneity.
    """

    E_scale: float | np.ndarray = 1.0
    fiber_offset_rad: float = 0.0
    nu: Optional[float] = None
    eta_kPa: Optional[float] = None
    eta_scale: float = 1.0


def true_tissue(model: Tissue, truth: TruthPerturbation) -> Tissue:
    """The trial's true tissue; the model itself when nothing differs (so one solve serves both)."""
    m = model.scene.material
    nu = None if truth.nu is None or truth.nu == m.nu else truth.nu
    eta = truth.eta_kPa if truth.eta_kPa is not None else (m.eta_kPa * truth.eta_scale if truth.eta_scale != 1 else None)
    eta = None if eta == m.eta_kPa else eta
    E_uniform = np.all(np.asarray(truth.E_scale) == 1.0)
    if E_uniform and truth.fiber_offset_rad == 0 and nu is None and eta is None:
        return model
    angle = m.fiber_angle_rad + truth.fiber_offset_rad if truth.fiber_offset_rad else None
    return model.with_material(truth.E_scale, nu, eta, angle)


@dataclass(frozen=True)
class Corridor:
    """A planned straight insertion to check after manipulation: side, unit direction (2,), half-width mm."""

    side: str
    direction: np.ndarray
    radius_mm: float

    @classmethod
    def from_plan(cls, plan, radius_mm: float) -> Optional["Corridor"]:
        """From a `NeedlePlan` (None when the plan has no direction)."""
        if plan is None or not plan.side or not np.all(np.isfinite(plan.direction)):
            return None
        return cls(plan.side, np.asarray(plan.direction, float), float(radius_mm))


def corridor_at(tissue: Tissue, x: np.ndarray, point: np.ndarray, corridor: Corridor,
                obstacles: Optional[Embedding] = None) -> tuple[np.ndarray, float]:
    """Entry (2,) mm and clearance (mm, > 0 clear) of the corridor to `point` (2,) at node positions x (N, 2).

    The skin and the obstacles are carried by x (deformed); the entry is
    where the ray from the point against the direction leaves the skin
    through the corridor's side (NaN and clearance NaN if it does not).
    """
    obstacles = obstacles or embed_outlines(tissue.mesh, [o.outline for o in tissue.scene.obstacles])
    outline = x[boundary_loop(tissue.mesh)]
    entry = entry_points(point, [(corridor.side, corridor.direction)], outline)[0]
    if not np.all(np.isfinite(entry)):
        return entry, float("nan")
    return entry, corridor_clearance(entry, point, deformed_outlines(obstacles, x), corridor.radius_mm)


def run_target(
    model: Tissue,
    target_rest: np.ndarray,
    desired: np.ndarray,
    cfg: ControllerConfig,
    *,
    truth: TruthPerturbation = TruthPerturbation(),
    measurement: Measurement = Measurement(),
    resolution_mm: float = 0.0,
    backlash_mm: float = 0.0,
    rng: Optional[np.random.Generator] = None,
    corridor: Optional[Corridor] = None,
    mode: str = "closed",
    target: str = "",
    tol: float = 1e-10,
    guess: Optional[tuple[np.ndarray, np.ndarray]] = None,
) -> LoopResult:
    """Manipulate one target from rest to `desired` (2,) mm; closed loop or the open-loop baseline.

    Builds the truth (`true_tissue(model, truth)`), its actuator (the
    scene's limits and speeds with the given resolution and backlash), the
    controller on the model (same limits and resolution; it does not know
    the backlash), and runs `run_loop` (mode "closed") or `open_loop`
    ("open"). With a `corridor`, the needle corridor through the reached
    true target is checked on the final true state: `corridor_clear`,
    `clearance_mm`, `corridor_entry`.
    """
    scene = model.scene
    probe = probe_targets(model.mesh, np.asarray(target_rest, float)[None])
    actuator = Actuator.from_scene(scene, resolution_mm, backlash_mm)
    plant = Plant(true_tissue(model, truth), actuator, probe, tol)
    controller = Controller(model, probe, actuator.lo, actuator.hi, resolution_mm, tol)
    if controller.shares(plant):
        plant.eq.adopt(controller.eq)  # both at rest: one tangent serves both
    if guess is not None:
        for eq in (plant.eq, controller.eq):
            eq.guesses.append((np.asarray(guess[0], float), np.asarray(guess[1], float)))
    names = list(scene.cup_names)
    if mode == "closed":
        result = run_loop(plant, controller, desired, cfg, measurement, rng, target, names)
    elif mode == "open":
        result = open_loop(plant, controller, desired, measurement, rng, cfg.rate_hz, target, names)
    else:
        raise ValueError(f"mode must be 'closed' or 'open', got {mode!r}")
    if corridor is not None:
        entry, clearance = corridor_at(plant.tissue, plant.eq.x, result.final_position, corridor)
        result.corridor_entry, result.clearance_mm = entry, clearance
        result.corridor_direction = corridor.direction
        result.corridor_clear = bool(clearance > 0)
    return result


def figure_inputs(tissue: Tissue, result: LoopResult, target_rest: np.ndarray,
                  corridor: Optional[Corridor] = None) -> dict:
    """Keyword arguments of `figures.manipulation_figure` for one manipulation.

    tissue: the truth the result was simulated on (its mesh and obstacles);
    the "before" corridor runs through the rest target along the planned
    direction on the rest scene, the "after" one through the reached true
    target on the final true state.
    """
    mesh, scene = tissue.mesh, tissue.scene
    loop = boundary_loop(mesh)
    x = result.final_x if result.final_x is not None else mesh.nodes
    obstacles = embed_outlines(mesh, [o.outline for o in scene.obstacles])
    target_rest = np.asarray(target_rest, float)
    before = after = None
    if corridor is not None:
        entry0, _ = corridor_at(tissue, mesh.nodes, target_rest, corridor, obstacles)
        before = np.array([entry0, target_rest])
        after = np.array([result.corridor_entry, result.final_position])
    clearance = "" if corridor is None else f", clearance {result.clearance_mm:.2f} mm"
    title = (
        f"{scene.name} — {result.target}: {result.mode} loop, {result.iterations} iterations ({result.stop_reason}), "
        f"final error ({result.final_error[0]:+.2f}, {result.final_error[1]:+.2f}) mm{clearance}"
    )
    return dict(
        title=title, triangles=mesh.triangles, rest=mesh.nodes, deformed=x,
        outline_rest=mesh.nodes[loop], outline_deformed=x[loop],
        obstacles_rest=[(o.name, o.outline) for o in scene.obstacles],
        obstacles_deformed=deformed_outlines(obstacles, x),
        target_rest=target_rest, target_reached=result.final_position, desired=result.desired,
        corridor_radius_mm=float("nan") if corridor is None else corridor.radius_mm,
        corridor_before=before, corridor_after=after, cup_nodes=list(tissue.cup_nodes),
    )
