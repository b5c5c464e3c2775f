"""What one manipulation leaves: the final state and the per-measurement history (docs/contract.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from scissor_cli.control.allocation import along_mm, miss_mm, stroke_step
from scissor_cli.control.plant import Controller, Plant


@dataclass
class LoopResult:
    """One manipulation of one target (closed or open loop). mm, s.

    final_position (2,): true target at the end; final_error (2,) = true −
    desired (x, y); miss_mm: |P (desired − true)| across the needle axis
    (|final_error| without an axis); along_error_mm: n·(desired − true), the
    signed along-axis part handed to the insertion depth (0 without an
    axis); correctable_error_mm / uncorrectable_error_mm: norms of the parts
    of the driven error (the miss, or the full error for
    `controller.error: position`) that strokes within their limits can /
    cannot remove at the end (J the controller's, docs/model.md §6). iterations: moves applied. time_s: wall clock
    of the loop; sim_time_s: the robot's time (moves at the drives' speed,
    at least 1/rate_hz each).

    History, one row per measurement (K = iterations + 1 rows, row 0 at
    rest before any move): time_s (K,) robot time, strokes_cmd (K, C) the
    commanded strokes in effect, strokes (K, C) the actual ones, measured
    (K, 2), true (K, 2), error (K, 2) = true − desired, correctable (K,) and
    uncorrectable (K,) norms of the measured driven error the controller
    saw, along (K,) its signed along-axis part.
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
    miss_mm: float = float("nan")
    along_error_mm: float = 0.0
    error_mode: str = "miss"
    hist_along: np.ndarray = field(default_factory=lambda: np.zeros(0))
    final_x: Optional[np.ndarray] = None  # (N, 2) true node positions at the end
    corridor_clear: Optional[bool] = None  # None: no corridor to check
    clearance_mm: float = float("nan")
    corridor_entry: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    corridor_direction: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    #: with an outside law (docs/model.md §22): (K,) cups the drives cut in the move to each row's command
    hist_clipped: Optional[np.ndarray] = None

    @property
    def history(self) -> dict[str, np.ndarray]:
        """The history arrays by name: time_s (K,), strokes_cmd (K, C), strokes (K, C), measured,
        true, error (K, 2), correctable_mm, uncorrectable_mm (K,)."""
        return {
            "time_s": self.hist_time_s, "strokes_cmd": self.hist_strokes_cmd, "strokes": self.hist_strokes,
            "measured": self.hist_measured, "true": self.hist_true, "error": self.hist_error,
            "correctable_mm": self.hist_correctable, "uncorrectable_mm": self.hist_uncorrectable,
            "along_mm": self.hist_along,
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
        uncorrectable_mm, along_mm (all mm except time_s in s), with an
        outside law clipped (cups the drives cut); in a body
        measured_z, true_z, error_z too (measured NaN where the sensor does
        not see that axis).
        """
        axes = "xyz"[:np.asarray(self.final_error).size]  # x, y (and z in a body)
        names = (
            ["time_s"]
            + [f"stroke_cmd_{c}" for c in self.cup_names]
            + [f"stroke_{c}" for c in self.cup_names]
            + [f"{kind}_{a}" for kind in ("measured", "true", "error") for a in axes]
            + ["correctable_mm", "uncorrectable_mm", "along_mm"]
            + ([] if self.hist_clipped is None else ["clipped"])
        )
        table = np.column_stack(
            [
                self.hist_time_s, self.hist_strokes_cmd, self.hist_strokes, self.hist_measured,
                self.hist_true, self.hist_error, self.hist_correctable, self.hist_uncorrectable,
                self.hist_along,
            ] + ([] if self.hist_clipped is None else [self.hist_clipped])
        ).astype(np.float64)
        return names, table


class History:
    """Rows collected during a loop."""

    def __init__(self):
        self.rows: dict[str, list] = {k: [] for k in ("t", "cmd", "act", "meas", "true", "corr", "unc", "along")}
        self.wall: list[float] = []

    def add(self, t, cmd, act, meas, true, corr, unc, along=0.0):
        keys = ("t", "cmd", "act", "meas", "true", "corr", "unc", "along")
        for k, v in zip(keys, (t, cmd, act, meas, true, corr, unc, along)):
            self.rows[k].append(np.array(v, float))

    def result(self, plant: Plant, controller: Controller, desired, target, mode, reason, message, wall,
               cup_names, direction=None, error_mode: str = "miss") -> LoopResult:
        r = {k: np.array(v) for k, v in self.rows.items()}
        true = plant.position
        if len(r["cmd"]):
            r["cmd"] = r["cmd"].reshape(len(r["t"]), -1)
            r["act"] = r["act"].reshape(len(r["t"]), -1)
        step = stroke_step(controller.jacobian, desired - true, controller.strokes, controller.lo, controller.hi,
                           None, direction, error_mode)
        corr, unc = step.correctable, step.uncorrectable
        axis = direction if error_mode == "miss" else None
        return LoopResult(
            target=target, mode=mode, desired=np.asarray(desired, float), final_position=true,
            final_error=true - desired,
            correctable_error_mm=float(np.linalg.norm(corr)), uncorrectable_error_mm=float(np.linalg.norm(unc)),
            iterations=len(r["t"]) - 1, time_s=wall, sim_time_s=float(r["t"][-1]),
            stop_reason=reason, converged=reason == "tolerance", cup_names=list(cup_names),
            hist_time_s=r["t"], hist_strokes_cmd=r["cmd"], hist_strokes=r["act"], hist_measured=r["meas"],
            hist_true=r["true"], hist_error=r["true"] - desired, hist_correctable=r["corr"],
            hist_uncorrectable=r["unc"], step_wall_s=np.array(self.wall), message=message, final_x=plant.eq.x,
            miss_mm=miss_mm(desired - true, axis), along_error_mm=along_mm(desired - true, axis), error_mode=error_mode,
            hist_along=r["along"],
        )
