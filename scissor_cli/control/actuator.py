"""The cups' linear drives: stroke limits, resolution and backlash (docs/model.md §6).

What the truth realises of a command: the controller commands strokes, the
actuator clips and quantises them and plays its backlash on reversals.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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
