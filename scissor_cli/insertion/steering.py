"""The `loop` strategy steered by the controller's 3-D model of the target under the needle (docs/model.md §18).

Against the slab a 2-D controller model cannot say how the needle's hold
changes the cups' effect on the target, nor where the target goes out of
the layer's plane. A 3-D-aware controller (`controller.model` calibrated,
surrogate or slab) is given, per planned target, a `NeedleModel`: the
nominal slab's own insertion at the plan's strokes (the needle aimed at the
target's height there, strategy `depth` with an exact sensor), recorded at
every step as

* the target's 3-D position (the drag the needle will give it, in the
  plane and out of it), and
* its 3-D response to a unit stroke of each cup with the needle's hold as
  it stands at that depth (the held Jacobian, `ModelState.target_response`
  on the nominal slab).

The plan takes the needle's height from it (`end_height_mm`: where the
target is when the tip reaches it: the drag out of the plane is
pre-compensated, since no sensor in the layer's plane can see it), and
`loop` steers with its Jacobian at the current depth (`TableSteering`),
corrected online by Broyden's update from what the sensor sees with the
model's drag taken off, averaged over BROYDEN_WINDOW frames
(`controller.jacobian_update: broyden`). Nothing of
the true tissue enters: the model is the nominal slab's, the measurement
the sensor's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scissor_cli.control.broyden import BroydenCorrection

#: the process noise (mm per step) of the across-axis offset's filter: the drag the model may miss in a step
DRIFT_SD_MM = 0.01
#: the share of the controller's tolerance within which the filtered offset leaves the cups where they are
DEADBAND = 0.5
#: Broyden's secant during an insertion is taken on the mean of this many frames (and of their strokes): under
#: the hold the cups move the target little, and one frame's noise would teach J the noise
BROYDEN_WINDOW = 5


@dataclass(frozen=True)
class NeedleModel:
    """One target under the needle, tabulated over depth (the nominal slab's or body's insertion at the plan).

    depth_mm (K,) increasing; target_mm (K, 3): the target after each step,
    the tissue's frame; jacobian (K, 3, C) mm/mm: its response to a unit
    stroke of each cup with the needle's hold at that step; in the slab,
    entry_height_mm: the needle's height in that insertion;
    steered_height_mm: the target's height at the end of the same insertion
    steered by `loop` with this model (its cup moves lift or lower the
    target too); in a body both are the entry's z (no height is aimed).
    """

    depth_mm: np.ndarray
    target_mm: np.ndarray
    jacobian: np.ndarray
    entry_height_mm: float
    steered_height_mm: float

    def __post_init__(self):
        if self.depth_mm.ndim != 1 or not len(self.depth_mm) or np.any(np.diff(self.depth_mm) <= 0):
            raise ValueError("a needle model needs at least one step, its depths increasing")

    def _interpolated(self, table: np.ndarray, depth_mm: float) -> np.ndarray:
        """The table (K, ...) at a depth, linear between steps and held at its ends."""
        d = self.depth_mm
        k = int(np.clip(np.searchsorted(d, depth_mm), 1, max(len(d) - 1, 1)))
        if len(d) == 1:
            return table[0]
        w = float(np.clip((depth_mm - d[k - 1]) / (d[k] - d[k - 1]), 0.0, 1.0))
        return (1.0 - w) * table[k - 1] + w * table[k]

    def target_at(self, depth_mm: float) -> np.ndarray:
        """The nominal target (3,) mm at a needle depth (mm)."""
        return self._interpolated(self.target_mm, depth_mm)

    def jacobian_at(self, depth_mm: float) -> np.ndarray:
        """The held Jacobian (3, C) mm/mm at a needle depth (mm)."""
        return self._interpolated(self.jacobian, depth_mm)

    @property
    def end_height_mm(self) -> float:
        """The target's height (mm, slab frame) when the tip reached it with the cups still."""
        return float(self.target_mm[-1, 2])

    def height_for(self, strategy: str) -> float:
        """The needle's height (mm, slab frame) for a strategy: where the target will be when the tip reaches it."""
        return self.steered_height_mm if strategy == "loop" else self.end_height_mm


class MissFilter:
    """A Kalman filter of the target's offset across the needle's axis, k components (mm), as `loop` steers on it.

    The prior is the manipulation's end: on the line, σ tolerance_mm (the
    controller's) per component; within DEADBAND of it (`deadband_mm`) the
    loop leaves the cups where they are. Each frame the model predicts
    the offset's move since the last (its drag and the cups' effect: a
    table's, `TableSteering`, or a model body's own insertion), uncertain by
    DRIFT_SD_MM per component; the reading corrects the components the
    sensor sees, each with its σ noise_mm (an exact sensor: the reading
    itself there). A component no sensor sees keeps the prediction.
    """

    def __init__(self, k: int, tolerance_mm: float, noise_mm: float):
        self.offset_mm = np.zeros(k)
        #: (k, k) mm² the estimate's covariance
        self.covariance = float(tolerance_mm) ** 2 * np.eye(k)
        #: |offset| (mm) below which the loop does not move the cups
        self.deadband_mm = DEADBAND * float(tolerance_mm)
        self._noise_var = float(noise_mm) ** 2
        self._started = False

    def update(self, moved_mm: np.ndarray, reading_mm: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """The filtered offset (k,) mm after a frame.

        moved_mm (k,): the model's predicted move since the last frame
        (ignored on the first: the prior holds there); reading_mm (k,): the
        sensor's offset, read only along `seen` (r, k), the orthonormal
        directions it observes (r ≤ k; r = 0: nothing seen this frame).
        """
        k = self.offset_mm.size
        if self._started:
            self.offset_mm = self.offset_mm + np.asarray(moved_mm, float)
            self.covariance = self.covariance + DRIFT_SD_MM ** 2 * np.eye(k)
        self._started = True
        H = np.asarray(seen, float).reshape(-1, k)
        if H.shape[0]:
            P = self.covariance
            innovation = H @ P @ H.T + self._noise_var * np.eye(H.shape[0])
            gain = np.linalg.solve(innovation, H @ P).T  # P Hᵀ S⁻¹ (S and P symmetric)
            self.offset_mm = self.offset_mm + gain @ (H @ np.asarray(reading_mm, float) - H @ self.offset_mm)
            self.covariance = (np.eye(k) - gain @ H) @ P
        return self.offset_mm.copy()


def seen_directions(observed: np.ndarray) -> np.ndarray:
    """The orthonormal rows (r, k) spanning what a sensor observes of a k-component offset, from its projector
    restricted to those components (k, k) (T S Tᵀ: symmetric, eigenvalues in [0, 1], 0 or 1 where the view is
    square to the components): the directions it sees more than half of, `MissFilter.update`'s `seen`."""
    values, vectors = np.linalg.eigh(0.5 * (observed + observed.T))
    return vectors[:, values > 0.5].T


class TableSteering:
    """The `loop` strategy's Jacobian from a `NeedleModel`, with Broyden's correction when asked for.

    across (r, d): the unit directions across the needle's axis the miss is
    steered along, in the table's first d coordinates (the slab: r = 1, the
    in-plane normal, d = 2; a body: r = 2, the two transverse axes, d = 3);
    broyden: whether to correct J from the moves; noise_mm: the sensor's σ
    (the filter's, and Broyden's guard); tolerance_mm: the controller's (the
    filter's prior σ and the deadband). `jacobian` returns the (r, C)
    response of the miss across the needle, `offset` the filtered miss.
    """

    def __init__(self, model: NeedleModel, across: np.ndarray, broyden: bool = False, noise_mm: float = 0.0,
                 tolerance_mm: float = 0.1):
        self.model = model
        self.across = np.atleast_2d(np.asarray(across, float))
        self.correction: Optional[BroydenCorrection] = BroydenCorrection(noise_mm) if broyden else None
        self._drift0: Optional[np.ndarray] = None
        self._window: list = []
        self._filter = MissFilter(self.across.shape[0], tolerance_mm, noise_mm)
        #: |offset| (mm) below which the loop does not move the cups (the filter's)
        self.deadband_mm = self._filter.deadband_mm
        #: the depth, strokes and J the filter's estimate holds at
        self._at: tuple = ()

    def offset(self, depth_mm: float, strokes: np.ndarray, seen_offset_mm: np.ndarray, J_across: np.ndarray,
               seen: Optional[np.ndarray] = None) -> np.ndarray:
        """The filtered offset (r,) mm of the target across the needle line, from this frame's `seen_offset_mm`
        (r,) at depth (mm) and strokes (C,) mm; J_across (r, C) the held Jacobian steered with: the table's drag
        and J_across times the strokes' change predict the move (`MissFilter`); seen (q, r): the directions the
        sensor observes (default all)."""
        strokes = np.asarray(strokes, float)
        r, d = self.across.shape
        moved = np.zeros(r)
        if self._at:
            depth0, strokes0, J0 = self._at
            drift = self.across @ (self.model.target_at(depth_mm) - self.model.target_at(depth0))[:d]
            moved = drift + J0 @ (strokes - strokes0)
        self._at = (depth_mm, strokes.copy(), np.atleast_2d(np.asarray(J_across, float)).copy())
        return self._filter.update(moved, np.asarray(seen_offset_mm, float).reshape(r),
                                   np.eye(r) if seen is None else seen)

    def jacobian(self, depth_mm: float, strokes: np.ndarray, measured: np.ndarray) -> np.ndarray:
        """J (r, C) of the miss across the needle at this depth; `measured` (d,) the sensor's target at strokes
        (C,) mm.

        Broyden sees the measured target less the model's drag since the
        first step (the cups' part of the motion, as far as the model knows
        the drag; a coordinate no sensor sees is NaN, which it skips).
        """
        d = self.across.shape[1]
        J = self.model.jacobian_at(depth_mm)[:d]
        if self.correction is not None:
            drift = self.model.target_at(depth_mm)[:d]
            if self._drift0 is None:
                self._drift0 = drift
            measured = np.asarray(measured, float)[:d]
            self._window.append((np.array(strokes, float), measured - (drift - self._drift0), J))
            if len(self._window) == BROYDEN_WINDOW:
                s, y, Js = (np.mean(v, axis=0) for v in zip(*self._window))
                self.correction.observe(Js, s, y)
                self._window.clear()
            J = self.correction.jacobian(J)
        return self.across @ J
