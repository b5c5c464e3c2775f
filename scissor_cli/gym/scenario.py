"""What the gymnasium environments run on: the scene built once per process, and each episode's plant and
controller (docs/model.md §22).

The model (mesh, tissue, plans, the targets' tasks) is built at an
environment's first reset and kept for the process (`built`), so further
resets, and further environments on the same config, reuse it. An
episode is one trial of `scissor simulate` (`api.trial_run`: its drawn
truth, sensor and actuator errors) or the nominal run (truth = model,
exact sensor), and its plant and controller are `control.loop.loop_parts`'.

A body's `surrogate` plant (`SurrogatePlant`) is the controller's learned
map of the body (`experiments.body_surrogate`: body solves along a
space-filling design of the strokes, a thin-plate-spline interpolant of
the lesions' 3-D positions): a step is one evaluation of that map at the
strokes the actuator realised. The trial's actuator errors and sensor act
on it; its drawn material does not (the map is the nominal body's).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional

import numpy as np

import scissor_cli
from scissor_cli import api, control
from scissor_cli.config import resolved_yaml
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.control.actuator import Actuator
from scissor_cli.control.loop import loop_parts, needle_axis
from scissor_cli.control.models import MapController
from scissor_cli.experiments.body_surrogate import body_surrogate_data
from scissor_cli.experiments.trial_types import TargetTask
from scissor_cli.layer3d.surrogate import Surrogate
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.sensing.sensor import TrueState

#: the shipped examples: the 2-D layer's is the CLI's default scene (inside the package); the dome lives in the
#: source tree's configs/ beside the package
LAYER_SCENE = Path(scissor_cli.__file__).parent / "scenes" / "example.yaml"
BODY_SCENE = Path(scissor_cli.__file__).resolve().parents[1] / "configs" / "example_dome.yaml"

PLANTS = ("body", "surrogate")


@dataclass
class Built:
    """One config's model as the environments share it in a process: the validated config, the model tissue
    (the trials' own, `trial_context`), the targets with a feasible plan, and a body's surrogate (or None)."""

    cfg: api.Scene
    tissue: Tissue
    tasks: list[TargetTask]
    surrogate: Optional[Surrogate] = None


_BUILT: dict[str, Built] = {}


def built(cfg: api.Scene, surrogate: bool = False) -> Built:
    """The model of `cfg`, built on first use in this process (one config at a time, as `trial_context`).

    surrogate: also learn the body's surrogate (`experiments.body_surrogate`, not cached on disk).
    """
    key = resolved_yaml(cfg)
    if key not in _BUILT:
        _BUILT.clear()
        tissue = api.build_tissue(cfg)  # the trials' model: one build serves the plans and the trials
        _BUILT[key] = Built(cfg, tissue, api.tasks(cfg, tissue, api.plan(cfg, tissue)))
    model = _BUILT[key]
    needs = surrogate or (isinstance(cfg, BodyConfig) and cfg.controller.model == "surrogate")
    if needs and model.surrogate is None:
        data = body_surrogate_data(cfg, model.tissue, None)
        model.surrogate = Surrogate(data.samples, components=3)
        # the trials of `controller.model: surrogate` take the samples from their task (`model_controllers`)
        model.tasks = [replace(t, controller_model=data) for t in model.tasks]
    return model


def task_named(model: Built, target: Optional[str]) -> TargetTask:
    """The task of target `target`, or the first with a feasible plan (None); ValueError when there is none."""
    if not model.tasks:
        raise ValueError(f"{model.cfg.name}: no target has a feasible plan")
    if target is None:
        return model.tasks[0]
    for task in model.tasks:
        if task.name == target:
            return task
    raise ValueError(f"target {target!r} has no feasible plan in {model.cfg.name}; "
                     f"those that have: {[t.name for t in model.tasks]}")


class SurrogatePlant:
    """A body's plant that is the surrogate: the lesion (3,) mm the map predicts at the realised strokes (C,).

    The same face as `control.Plant` where the environments use it
    (`apply`, `position`, `true_state`, `strokes`, `actuator`); a step
    never fails (no solve).
    """

    def __init__(self, surrogate: Surrogate, index: int, actuator: Actuator):
        self.surrogate, self.index, self.actuator = surrogate, index, actuator
        self._strokes = actuator.stroke.copy()
        self._position = self._at(self._strokes)

    def _at(self, strokes: np.ndarray) -> np.ndarray:
        return self.surrogate.predict(strokes[None])[0, self.index]

    @property
    def position(self) -> np.ndarray:
        """The plant's lesion (3,) mm."""
        return self._position

    @property
    def strokes(self) -> np.ndarray:
        return self._strokes

    def true_state(self) -> TrueState:
        """What a sensor sees: the lesion only (no nodes)."""
        return TrueState(self._position)

    def apply(self, command: np.ndarray, tangent: bool = False) -> np.ndarray:
        """Actuate `command` (C,) mm; the lesion moves to the map's prediction there. Returns the strokes (C,)."""
        self._strokes = self.actuator.apply(command)
        self._position = self._at(self._strokes)
        return self._strokes.copy()


def episode_run(model: Built, task: TargetTask, trial: Optional[int]) -> tuple[Tissue, control.TargetRun]:
    """The tissue model and `control.TargetRun` of trial `trial`, or of the nominal manipulation (None):
    `api.trial_run`, what `simulate` runs."""
    return api.trial_run(model.cfg, task, trial)


def episode_parts(model: Built, task: TargetTask, trial: Optional[int], plant: str = "body"):
    """(plant, controller, needle axis (d,) or None, run) of one episode.

    plant "body" (a layer's too): `loop_parts` on the run; "surrogate": a
    `SurrogatePlant` with the run's actuator errors and a `MapController`
    on the same map (its J the map's derivative).
    """
    tissue, run = episode_run(model, task, trial)
    if plant != "surrogate":
        parts = loop_parts(tissue, task.rest, run)
        return (*parts, run)
    actuator = Actuator.from_scene(model.tissue.scene, run.resolution_mm, run.backlash_mm)
    truth = SurrogatePlant(model.surrogate, task.index, actuator)
    controller = MapController(model.surrogate.target_map(task.index), len(actuator.lo), actuator.lo, actuator.hi,
                               run.resolution_mm)
    direction = needle_axis(run)
    return truth, controller, direction, run
