"""The control law: the correctable error, the PID on the stroke step, and when to stop (docs/model.md §6).

The law is the paper's velocity form (its eq. for μ(t) drives the actuator
speed), so the integral term is summed twice: it removes a steady bias but
leaves a slow mode (for the default gains a pole near 0.99 per iteration).
The loop therefore stops as soon as the correctable error is within
tolerance, and declares "stalled" when the error stops improving.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scissor_cli.control.actuator import quantise

#: Why `run_loop` stopped.
STOP_REASONS = ("tolerance", "max_iterations", "stalled", "stroke_limit", "solver_failed", "controller_failed")

#: Iterations without a 10 % better correctable error before the loop is "stalled".
STALL_PATIENCE = 5
STALL_GAIN = 0.9


def split_error(J: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """δs* = J⁺ e (C,) mm, the correctable part J δs* (2,) and the rest e − J δs* (2,), mm."""
    ds = np.linalg.lstsq(J, e, rcond=None)[0]
    corr = J @ ds
    return ds, corr, e - corr


@dataclass
class PID:
    """Discrete PID on δs* (C,) with conditional-integration anti-windup (docs/model.md §6).

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

    def command(self, s: np.ndarray, ds: np.ndarray, lo, hi,
                resolution_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
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


def traveling(commands: list[np.ndarray]) -> bool:
    """Whether the command went one way over the last STALL_PATIENCE moves (its net move at least half its
    path, commands (C,) mm each): a loop cut by the drives' speed is then still carried towards the target.

    A loop that chatters — a camera pixel (0.24 mm at the paper's camera) asks for more stroke than one
    period's travel when J is right, so every step is cut by the speed limit, back and forth — is not
    traveling, and may stall (docs/model.md §6).
    """
    if len(commands) <= STALL_PATIENCE:
        return True
    c = np.asarray(commands[-STALL_PATIENCE - 1:], float)
    path = float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1)))
    return float(np.linalg.norm(c[-1] - c[0])) >= 0.5 * path


def stalled(corr_history: list[float]) -> bool:
    """No 10 % better correctable error in the last STALL_PATIENCE measurements than before them."""
    if len(corr_history) <= STALL_PATIENCE:
        return False
    return min(corr_history[-STALL_PATIENCE:]) > STALL_GAIN * min(corr_history[:-STALL_PATIENCE])
