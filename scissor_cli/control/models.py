"""The controllers of the other tissue models: calibrated layer, learned map, nominal slab (docs/model.md §15).

`plant.Controller` is the paper's: its model is the 2-D layer, solved at
the commanded strokes, J the layer's tangent response there. The loop
(`control.loop.run_loop`) asks every controller the same few things — the
strokes it commanded, J (2, C) there, its stroke limits and resolution,
`update(commanded)` — so it does not know which model it holds:

* `CalibratedController`: the layer with one stroke transmission τ_c per
  cup (the stroke the layer sees is τ ⊙ s): its equilibrium at τ ⊙ s, and
  J = J_layer(τ ⊙ s) diag(τ);
* `MapController`: a smooth map strokes → target (2,) with its J, such as
  the surrogate learned from slab equilibria (`layer3d.surrogate`);
* `SlabController`: the nominal 3-D slab, tracked like the layer; J the
  in-plane rows of the slab's tangent response at the target;
* `SectionController`: a layer that is a body's section (the paper's
  reduction of a 3-D scene): its in-plane J carried into the body's frame.
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from scissor_cli.control.allocation import stroke_step
from scissor_cli.control.plant import Controller, Plant
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import TargetProbe

#: (strokes (C,) mm) → (target (k,) mm, J (k, C) mm/mm): what a learned map answers (k = 2; 3 for a body's)
TargetMap = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


class CalibratedController(Controller):
    """The 2-D layer seen through one stroke transmission per cup, transmission (C,) > 0 (docs/model.md §15)."""

    def __init__(self, tissue: Tissue, probe: TargetProbe, lo, hi, transmission, resolution_mm: float = 0.0,
                 tol: float = 1e-10):
        super().__init__(tissue, probe, lo, hi, resolution_mm, tol)
        self.transmission = np.asarray(transmission, float)
        self._commanded = np.zeros(tissue.n_cups)

    @property
    def jacobian(self) -> np.ndarray:
        """J (2, C): the layer's at τ ⊙ s times diag(τ) (the chain rule through the transmission)."""
        return super().jacobian * self.transmission[None, :]

    @property
    def strokes(self) -> np.ndarray:
        return self._commanded

    def shares(self, plant: Plant) -> bool:
        return False  # the layer it solves sits at τ ⊙ s, never at the plant's strokes

    def update(self, commanded: np.ndarray, plant: Optional[Plant] = None) -> None:
        self._commanded = np.array(commanded, float)
        self.eq.move_to(self.transmission * self._commanded, tangent=True)


class MapController:
    """A controller whose model is a map strokes → (target, J) (`TargetMap`), e.g. the learned surrogate."""

    def __init__(self, target_map: TargetMap, n_cups: int, lo, hi, resolution_mm: float = 0.0):
        self.map, self.n_cups = target_map, n_cups
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.resolution_mm = resolution_mm
        self._strokes = np.zeros(n_cups)
        self.position, self._J = target_map(self._strokes)

    @property
    def jacobian(self) -> np.ndarray:
        """J (k, C) mm/mm of the map at the commanded strokes (k = 2, or 3 for a body's surrogate)."""
        return self._J

    @property
    def strokes(self) -> np.ndarray:
        return self._strokes

    def shares(self, plant: Plant) -> bool:
        return False

    def update(self, commanded: np.ndarray, plant: Optional[Plant] = None) -> None:
        self._strokes = np.array(commanded, float)
        self.position, self._J = self.map(self._strokes)


class SlabController(Controller):
    """The nominal slab as the controller's model; probe: a `layer3d.slab.SlabProbe` of the one target."""

    @property
    def jacobian(self) -> np.ndarray:
        """J (2, C): the in-plane rows of the slab's tangent response at the target."""
        if self.tissue.n_cups == 0:
            return np.zeros((2, 0))
        return self.probe.response(self.eq.response)[0, :2]


class SectionController(Controller):
    """A 2-D layer lying in a plane of a body as the controller's model (the paper's reduction, docs/model.md §19).

    basis (3, 2): the plane's orthonormal axes in the body's frame (`config.body_section.SectionPlane`); the
    layer's target moves in that plane, so its J (2, C) is J (3, C) = basis J in the body's frame.
    """

    def __init__(self, tissue: Tissue, probe: TargetProbe, basis, lo, hi, resolution_mm: float = 0.0,
                 tol: float = 1e-10):
        super().__init__(tissue, probe, lo, hi, resolution_mm, tol)
        self.basis = np.asarray(basis, float)

    @property
    def jacobian(self) -> np.ndarray:
        """J (3, C) mm/mm: the layer's in-plane J carried into the body's frame."""
        return self.basis @ super().jacobian


#: the inverse stops once the driven error is this small (mm), far below a camera's noise
INVERSE_TOL_MM = 1e-3
#: Gauss–Newton iterations of the inverse; each is one solve of the model
INVERSE_ITERATIONS = 20


def strokes_for(target_map: TargetMap, desired: np.ndarray, lo, hi, direction: Optional[np.ndarray] = None,
                mode: str = "miss", start: Optional[np.ndarray] = None) -> tuple[np.ndarray, float]:
    """The strokes (C,) mm at which a model puts its target at `desired` (2,) mm, and the driven error left (mm).

    Gauss–Newton on the model's own positions and J, each step the loop's
    bounded least-squares step (`allocation.stroke_step`: stroke limits,
    "miss" drives only the error across the needle axis `direction`), halved
    while it does not reduce the error. Ends within INVERSE_TOL_MM, at a
    stroke limit that asks to go further, or after INVERSE_ITERATIONS; the
    error left says whether the model can reach the point at all.
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    desired = np.asarray(desired, float)
    s = np.zeros(lo.size) if start is None else np.clip(np.asarray(start, float), lo, hi)
    y, J = target_map(s)
    left = _driven(desired - y, direction, mode)
    for _ in range(INVERSE_ITERATIONS):
        if left <= INVERSE_TOL_MM or lo.size == 0:
            break
        ds = stroke_step(J, desired - y, s, lo, hi, None, direction, mode).ds
        for _ in range(6):  # halve a step that overshoots (the model is nonlinear)
            trial = np.clip(s + ds, lo, hi)
            if np.allclose(trial, s, rtol=0.0, atol=1e-9):
                return s, left
            y_t, J_t = target_map(trial)
            left_t = _driven(desired - y_t, direction, mode)
            if left_t < left:
                break
            ds = 0.5 * ds
        else:
            break
        s, y, J, left = trial, y_t, J_t, left_t
    return s, left


def _driven(error: np.ndarray, direction: Optional[np.ndarray], mode: str) -> float:
    """|P e| across the needle axis (mode "miss" with an axis), else |e| (mm)."""
    if mode != "miss" or direction is None or not np.all(np.isfinite(direction)):
        return float(np.linalg.norm(error))
    n = np.asarray(direction, float) / np.linalg.norm(direction)
    return float(np.linalg.norm(error - (error @ n) * n))
