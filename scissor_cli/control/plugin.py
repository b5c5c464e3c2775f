"""Controllers from outside: the plug-in protocol, what a controller sees, and the drives (docs/model.md §22).

A controller is any object with two methods:

    reset(observation, info) -> None          # once, before the first frame of a manipulation
    act(observation, info) -> velocities      # every frame: (C,) mm/s, one per cup

It sees what the sensor gives and the robot knows, never the truth:

* ``observation`` (`observation`): ``measured_mm`` (d,) the sensor's
  reading of the lesion; ``desired_mm`` (d,) where the plan wants it;
  ``direction`` (d,) the unit needle axis (zeros when there is none);
  ``strokes_mm`` (C,) the commanded strokes now; ``time_s`` the robot's
  time;
* ``info`` (`frame_info`): ``jacobian`` (d, C) the controller model's J at
  the command (Broyden-corrected with `controller.jacobian_update:
  broyden`); ``stroke_lo_mm``, ``stroke_hi_mm``, ``speed_mm_per_s`` (C,);
  ``dt_s`` the frame period; ``error_mode``; ``iteration``; ``target``;
  ``cup_names``.

The velocities pass through the same drives as the built-in law's commands
(`drive`): the speed limit, then the stroke limits, then the resolution.
What the drives cut is counted (`Drive.clipped`), so a controller that
asks for more than the robot can do is seen in the history.

`PIDLaw` is the built-in law of docs/model.md §6 written as such a class:
driven through the plug-in path (or a gymnasium environment) it commands
what `loop.run_loop`'s own PID commands.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Protocol

import numpy as np

from scissor_cli.control.actuator import quantise
from scissor_cli.control.allocation import stroke_step
from scissor_cli.control.law import PID


class ControllerError(RuntimeError):
    """An outside controller raised, or returned something that is not one finite velocity per cup."""


class ControllerLaw(Protocol):
    """What `controller.law: python` (and `mpc`) asks of a controller class."""

    def reset(self, observation: dict[str, Any], info: dict[str, Any]) -> None: ...

    def act(self, observation: dict[str, Any], info: dict[str, Any]) -> np.ndarray: ...


def observation(measured_mm, desired_mm, direction, strokes_mm, time_s: float) -> dict[str, Any]:
    """What the controller sees this frame (the module docstring): float64 arrays, copies."""
    d = np.asarray(desired_mm, float).size
    axis = np.zeros(d) if direction is None else np.asarray(direction, float).copy()
    return {"measured_mm": np.array(measured_mm, float), "desired_mm": np.array(desired_mm, float),
            "direction": axis, "strokes_mm": np.array(strokes_mm, float), "time_s": float(time_s)}


def frame_info(jacobian, lo, hi, speed_mm_per_s, dt_s: float, error_mode: str, iteration: int, target: str,
               cup_names: list[str]) -> dict[str, Any]:
    """What the robot knows besides the observation (the module docstring)."""
    return {"jacobian": np.array(jacobian, float), "stroke_lo_mm": np.array(lo, float),
            "stroke_hi_mm": np.array(hi, float), "speed_mm_per_s": np.array(speed_mm_per_s, float),
            "dt_s": float(dt_s), "error_mode": error_mode, "iteration": int(iteration), "target": target,
            "cup_names": list(cup_names)}


@dataclass(frozen=True)
class Drive:
    """One frame through the drives: the command (C,) mm they reach and how many cups they cut (speed or
    stroke limit; the resolution's rounding is not a cut)."""

    command: np.ndarray
    clipped: int


def drive(strokes_mm: np.ndarray, velocity_mm_per_s: np.ndarray, dt_s: float, lo: np.ndarray, hi: np.ndarray,
          speed_mm_per_s: np.ndarray, resolution_mm: float = 0.0) -> Drive:
    """The command after one frame at `velocity_mm_per_s` (C,) from `strokes_mm` (C,) mm.

    The speed limit holds per cup (|v| ≤ speed), then the stroke limits
    [lo, hi] (C,) mm, then the resolution (`actuator.quantise`).
    """
    v = np.asarray(velocity_mm_per_s, float)
    speed = np.asarray(speed_mm_per_s, float)
    v_ok = np.clip(v, -speed, speed)
    raw = np.asarray(strokes_mm, float) + v_ok * dt_s
    inside = np.clip(raw, lo, hi)
    cut = (v_ok != v) | (inside != raw)
    return Drive(quantise(inside, lo, hi, resolution_mm), int(np.count_nonzero(cut)))


def checked_velocity(velocity, n_cups: int) -> np.ndarray:
    """A controller's answer as (C,) float64 mm/s; ControllerError when it is not C finite numbers."""
    try:
        v = np.asarray(velocity, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ControllerError(f"act() returned {type(velocity).__name__}, not {n_cups} velocities (mm/s)") from exc
    if v.size != n_cups:
        raise ControllerError(f"act() returned {v.size} velocities; the scene has {n_cups} cups")
    if not np.all(np.isfinite(v)):
        raise ControllerError(f"act() returned a non-finite velocity: {v.tolist()}")
    return v


class PIDLaw:
    """The built-in law (docs/model.md §6) as a plug-in: the bounded least-squares step on the model's J, then
    the PID of `law.PID`; returns the velocity (C,) mm/s that reaches the PID's command in one frame.

    kp, ki, kd: the gains of `controller` (defaults the config's). `seen`
    (d,) bool: the axes the sensor sees (a body seen by one camera), or None.
    """

    def __init__(self, kp: float = 0.8, ki: float = 0.1, kd: float = 0.0, seen: Optional[np.ndarray] = None):
        self.kp, self.ki, self.kd, self.seen = float(kp), float(ki), float(kd), seen
        self.pid: Optional[PID] = None

    def reset(self, observation: dict[str, Any], info: dict[str, Any]) -> None:
        self.pid = PID(self.kp, self.ki, self.kd, info["dt_s"])

    def act(self, observation: dict[str, Any], info: dict[str, Any]) -> np.ndarray:
        if self.pid is None:
            self.reset(observation, info)
        s, dt = observation["strokes_mm"], info["dt_s"]
        lo, hi = info["stroke_lo_mm"], info["stroke_hi_mm"]
        axis = observation["direction"]
        step = stroke_step(info["jacobian"], observation["desired_mm"] - observation["measured_mm"], s, lo, hi,
                           info["speed_mm_per_s"] * dt, axis if np.any(axis) else None, info["error_mode"],
                           seen=self.seen)
        new, _ = self.pid.command(s, step.ds, lo, hi)
        return (new - s) / dt
