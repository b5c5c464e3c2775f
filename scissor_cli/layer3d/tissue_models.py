"""The controller's model of the tissue, one of four, behind one interface (docs/model.md §15).

`ModelData` is what a model is made of, as plain arrays (it travels to the
trial workers with the tasks, and into /controller_model): nothing for
`layer` and `slab`, the transmissions for `calibrated`, the training and
held-out slab samples for `surrogate`. `ControllerModel` turns it back into
what the loop and the planner use, the same for all four:

* `controller(target, lo, hi, resolution_mm)` — the per-target controller
  of `control.run_loop` (`plant.Controller` or one of `control.models`);
* `scene_map()` — strokes (C,) → the targets' in-plane positions (T, 2) and
  J (T, 2, C): what the planner inverts and the figure draws;
* `layer_map()` — strokes (C,) → the layer's nodes in-plane (N2, 2): where
  a plan made again with the model finds the obstacles and the skin.

The slab itself (for `slab`, and for the plan's `slab_strokes`) is the
nominal slab of `layer3d.truth.SlabTruth`, built once per process.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from scissor_cli.control.corridor_check import Corridor, corridor_at
from scissor_cli.control.models import CalibratedController, MapController, SlabController
from scissor_cli.control.plant import Controller
from scissor_cli.layer3d.calibration import Calibration, calibration_strokes, fit_transmission
from scissor_cli.layer3d.slab import layer_probe, slab_probe
from scissor_cli.layer3d.surrogate import GroupSolver, Surrogate, SurrogateSamples, train
from scissor_cli.layer3d.truth import SLAB_TRUTH_TOL
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import apply_probe, probe_targets, target_positions
from scissor_cli.solvers.tracking import TrackedEquilibrium

KINDS = ("layer", "calibrated", "surrogate", "slab")
#: strokes (C,) mm → targets' in-plane positions (T, 2) mm and J (T, 2, C) mm/mm
SceneMap = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
#: strokes (C,) mm → the layer's nodes in-plane (N2, 2) mm, one per 2-D node
LayerMap = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class ModelData:
    """A controller model as plain data: kind, and what it was fitted to (None where the kind has none)."""

    kind: str
    build_time_s: float = 0.0
    #: surrogate: the largest distance to held-out slab solves; calibrated: to the slab at its fitting strokes (mm)
    validation_error_mm: Optional[float] = None
    calibration: Optional[Calibration] = None
    samples: Optional[SurrogateSamples] = None
    #: with the needle in the slab: each planned target's model under the needle (`insertion.NeedleModel`,
    #: docs/model.md §18), by target name
    needle: Optional[dict] = None


def build_model_data(kind: str, layer: Tissue, slab: Optional[Tissue], plan_strokes: list[np.ndarray],
                     samples: int, advance: Callable[[int], None] = lambda n: None,
                     solve_groups: Optional[GroupSolver] = None) -> ModelData:
    """Fit the model of `kind` for the layer's scene: slab solves for calibrated and surrogate (none otherwise).

    plan_strokes: the layer plans' strokes (C,) of every planned target
    (where the calibration is fitted); samples: the surrogate's design size;
    solve_groups: how the surrogate's design groups are solved (`surrogate.train`).
    """
    if kind not in KINDS:
        raise ValueError(f"controller model must be one of {KINDS}, got {kind!r}")
    if kind in ("layer", "slab"):
        return ModelData(kind)
    rests = np.array([t.rest for t in layer.scene.targets]).reshape(-1, 2)
    targets = slab_probe(slab, rests)
    lo, hi = _limits(layer)
    if kind == "calibrated":
        t0 = time.perf_counter()
        probe = probe_targets(layer.mesh, rests)
        cal = fit_transmission(layer, probe, slab, targets, calibration_strokes(lo, hi, plan_strokes), SLAB_TRUTH_TOL,
                               advance)
        return ModelData(kind, time.perf_counter() - t0, cal.error_mm, calibration=cal)
    data = train(slab, targets, layer_probe(slab, layer.mesh), lo, hi, samples, SLAB_TRUTH_TOL, advance, solve_groups)
    return ModelData(kind, data.build_time_s, Surrogate(data).validation_error_mm(), samples=data)


def model_solves(kind: str, layer: Tissue, plan_strokes: list[np.ndarray], samples: int) -> int:
    """How many slab solves `build_model_data` makes (for its progress bar)."""
    if kind == "surrogate":
        return samples + max(4, samples // 4)
    if kind == "calibrated":
        return sum(v.size for v in calibration_strokes(*_limits(layer), plan_strokes))
    return 0


def _limits(tissue: Tissue) -> tuple[np.ndarray, np.ndarray]:
    cups = tissue.scene.cups
    return np.array([c.stroke_min_mm for c in cups]), np.array([c.stroke_max_mm for c in cups])


class ControllerModel:
    """A `ModelData` made usable in one process: per-target controllers and the scene map.

    layer: the controller's 2-D tissue; slab: the nominal slab (needed by
    the `slab` kind only).
    """

    def __init__(self, data: ModelData, layer: Tissue, slab: Optional[Tissue] = None):
        if data.kind == "slab" and slab is None:
            raise ValueError("the slab model needs the nominal slab")
        self.data, self.layer, self.slab = data, layer, slab
        self.surrogate = Surrogate(data.samples) if data.samples is not None else None
        self._rests = np.array([t.rest for t in layer.scene.targets]).reshape(-1, 2)

    @property
    def kind(self) -> str:
        return self.data.kind

    @property
    def transmission(self) -> Optional[np.ndarray]:
        return None if self.data.calibration is None else self.data.calibration.transmission

    def controller(self, target: int, lo, hi, resolution_mm: float = 0.0, tol: float = 1e-10):
        """The controller of one target (its index in the scene) for `control.run_loop`."""
        probe = probe_targets(self.layer.mesh, self._rests[target][None])
        if self.kind == "layer":
            return Controller(self.layer, probe, lo, hi, resolution_mm, tol)
        if self.kind == "calibrated":
            return CalibratedController(self.layer, probe, lo, hi, self.transmission, resolution_mm, tol)
        if self.kind == "surrogate":
            return MapController(self.surrogate.target_map(target), self.layer.n_cups, lo, hi, resolution_mm)
        return SlabController(self.slab, slab_probe(self.slab, self._rests[target][None]), lo, hi, resolution_mm,
                              SLAB_TRUTH_TOL)

    def layer_map(self) -> Optional[LayerMap]:
        """strokes → the layer's nodes in-plane (N2, 2) mm as this model predicts them; None for `layer` (the
        planner's own states) and for a surrogate fitted without them."""
        if self.kind == "surrogate":
            return self.surrogate.layer_at if self.surrogate.knows_layer else None
        if self.kind == "slab":
            return SlabMap(self.slab, self.layer, self._rests).layer_at
        if self.kind == "calibrated":
            eq, tau = TrackedEquilibrium(self.layer), self.transmission

            def calibrated_layer(strokes):
                eq.move_to(tau * np.asarray(strokes, float), tangent=False)
                return eq.x

            return calibrated_layer
        return None

    def scene_map(self) -> SceneMap:
        """strokes → (targets (T, 2), J (T, 2, C)) of this model; a tracked solve for layer, calibrated, slab."""
        if self.kind == "surrogate":
            def surrogate_map(strokes):
                y, J = self.surrogate.answer(strokes)
                return y[:, :2], J[:, :2]

            return surrogate_map
        if self.kind == "slab":
            return slab_map(self.slab, self.layer, self._rests)
        layer_answer = layer_map(self.layer, self._rests)
        if self.kind == "layer":
            return layer_answer
        tau = self.transmission

        def calibrated_map(strokes):
            y, J = layer_answer(tau * np.asarray(strokes, float))
            return y, J * tau[None, None, :]

        return calibrated_map


def layer_map(layer: Tissue, rests: np.ndarray) -> SceneMap:
    """The 2-D layer's `SceneMap`: one tracked equilibrium with its exact tangent."""
    probe = probe_targets(layer.mesh, rests)
    eq = TrackedEquilibrium(layer)

    def answer(strokes):
        eq.move_to(np.asarray(strokes, float), tangent=True)
        J = apply_probe(probe, eq.response).reshape(len(rests), 2, layer.n_cups)
        return target_positions(probe, eq.x), J

    return answer


class SlabMap:
    """The nominal slab's `SceneMap` (one tracked equilibrium, SLAB_TRUTH_TOL): in-plane targets and J; also the
    corridor to a point at given strokes, judged on the slab's layer (its obstacles and skin where the slab has
    them), for the plan's check."""

    def __init__(self, slab: Tissue, layer: Tissue, rests: np.ndarray):
        self.layer = layer
        self.probe = slab_probe(slab, rests)
        self.eq = TrackedEquilibrium(slab, SLAB_TRUTH_TOL)
        self._layer = layer_probe(slab, layer.mesh)

    def __call__(self, strokes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.eq.move_to(np.asarray(strokes, float), tangent=True)
        return self.probe.positions(self.eq.x)[:, :2], self.probe.response(self.eq.response)[:, :2]

    def layer_at(self, strokes: np.ndarray) -> np.ndarray:
        """The nominal slab's layer in-plane (N2, 2) mm at `strokes` (C,) mm (a `LayerMap`)."""
        self.eq.move_to(np.asarray(strokes, float), tangent=False)
        return self._layer.positions(self.eq.x)[:, :2]

    def clearance(self, strokes: np.ndarray, point: np.ndarray, corridor: Corridor) -> float:
        """The corridor's clearance (mm, > 0 clear; NaN: it does not reach the skin) to `point` (2,) mm with
        the nominal slab at `strokes` (C,) mm: what a slab-truth trial checks at its end (`control.corridor_at`)."""
        return corridor_at(self.layer, self.layer_at(strokes), np.asarray(point, float), corridor)[1]


def slab_map(slab: Tissue, layer: Tissue, rests: np.ndarray) -> SlabMap:
    """The nominal slab's `SceneMap` (`SlabMap`)."""
    return SlabMap(slab, layer, rests)


@dataclass(frozen=True)
class ModelPaths:
    """What the figure draws, per cup c: stroke grids and the targets' in-plane positions there.

    strokes[c] (G,), model[c] / layer[c] (G, T, 2) mm; slab_strokes[c] (V,), slab[c] (V, T, 2) mm (the
    nominal slab, solved or from the model's samples).
    """

    kind: str
    cup_names: list
    target_names: list
    strokes: list
    model: list
    layer: list
    slab_strokes: list
    slab: list
    #: the targets at rest (T, 2) mm: the figure draws the motion from there
    rest: np.ndarray = None
