"""Broyden's online correction of the controller's Jacobian from observed moves (docs/model.md §15).

`controller.jacobian_update: broyden`: the loop steers with J = J_model + D,
where J_model is the controller's model Jacobian at its current state (2 × C
in a layer, 3 × C on a body) and D a correction learnt from the moves made so far (uncalibrated visual
servoing: Hosoda & Asada 1994, Jägersand 1997). After each move Δs (the
commanded strokes, C) the camera sees the target move Δy (2,; on a body (3,),
NaN where one camera does not see the depth, whose row is then kept); the
secant (Broyden's "good") update

    D ← D + (Δy − J Δs) Δsᵀ / (Δsᵀ Δs),   J = J_model + D the Jacobian used,

makes J reproduce the move just made and leaves J unchanged across Δs, so
on a linear plant J converges to the true Jacobian along the directions the
loop excites (tests/test_broyden.py).

Guard against noise: Δy is measured, so a small move's secant is mostly
camera noise (σ ≈ 0.15 mm at the default camera: 0.5 px noise plus pixel
rounding, 0.24 mm per pixel). The secant is therefore taken over as many
moves as it takes for the observed or predicted target motion since the
last update to exceed the threshold max(MIN_MOVE_MM, NOISE_FACTOR σ);
and the correction is bounded, ‖D‖_F ≤ MAX_CHANGE ‖J_model‖_F (half), so a
noisy secant cannot turn J round, cancel one of its components or blow it
up (the model still knows the direction and rough size of the response).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

#: the secant waits until the target has moved (observed or predicted) at least this far (mm)...
MIN_MOVE_MM = 0.05
#: ...and NOISE_FACTOR times the measurement's σ: the secant's gain then errs by ≲ √2/NOISE_FACTOR
NOISE_FACTOR = 4.0
#: ‖D‖_F ≤ MAX_CHANGE ‖J_model‖_F: J may shrink to half its size or grow by half and turn by at most 30°.
#: The slab moves a target about half as far as the layer (docs/model.md §15), so half is what a layer model
#: must be able to learn; 1.0 let a noisy secant cancel J's component across the needle (measured: a slab-truth
#: trial then saw its miss as uncorrectable and stopped at "tolerance" 1.4 mm off)
MAX_CHANGE = 0.5


def broyden_update(J: np.ndarray, ds: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Broyden's secant update of J (d, C) from a move ds (C,) mm → dy (d,) mm: J + (dy − J ds) dsᵀ / dsᵀds.

    The update is row by row, so a component the sensor does not see (NaN in
    dy: a body's depth along one camera's view) keeps its row of J.
    """
    ds, dy = np.asarray(ds, float), np.asarray(dy, float)
    residual = np.where(np.isfinite(dy), dy - J @ ds, 0.0)
    return J + np.outer(residual, ds) / float(ds @ ds)


@dataclass
class BroydenCorrection:
    """The correction D (d, C) the loop adds to its model's J; `noise_mm` the measurement's σ (mm).

    `observe` after each move; `updates` counts the secants taken, `skipped`
    the moves that waited for more motion.
    """

    noise_mm: float = 0.0
    D: Optional[np.ndarray] = None
    updates: int = 0
    skipped: int = 0
    _anchor: Optional[tuple] = None  # (strokes, measured y, the model's J) where the current secant starts

    def jacobian(self, J_model: np.ndarray) -> np.ndarray:
        """The Jacobian to steer with (d, C): the model's plus the correction."""
        return J_model if self.D is None else J_model + self.D

    @property
    def threshold_mm(self) -> float:
        return max(MIN_MOVE_MM, NOISE_FACTOR * self.noise_mm)

    def observe(self, J_model: np.ndarray, strokes: np.ndarray, y: np.ndarray) -> None:
        """A measurement y (d,) mm (d = 2, or 3 on a body) at commanded strokes (C,) mm; the model's J (d, C)."""
        strokes, y = np.array(strokes, float), np.asarray(y, float)
        if self._anchor is None:
            self._anchor = (strokes, y, J_model)
            return
        s0, y0, J0 = self._anchor
        ds, dy = strokes - s0, y - y0
        J = self.jacobian(J0)
        seen = np.isfinite(dy)  # (a body seen by one camera: its depth is not)
        if not np.any(ds) or max(np.linalg.norm((J @ ds)[seen]), np.linalg.norm(dy[seen])) < self.threshold_mm:
            self.skipped += 1
            return
        D = broyden_update(J, ds, dy) - J0
        bound = MAX_CHANGE * np.linalg.norm(J0)
        size = np.linalg.norm(D)
        if size > bound:
            D *= bound / size
        self.D = D
        self.updates += 1
        self._anchor = (strokes, y, J_model)
