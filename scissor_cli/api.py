"""scissor's Python API: the CLI's own pipeline, one call per step (docs/api.md, docs/model.md §22).

    import scissor_cli.api as scissor

    cfg = scissor.load_config("configs/example.yaml")          # validate a scene (ConfigError)
    tissue = scissor.build_tissue(cfg)                          # mesh + material + cups: the layer or the body
    eq = scissor.solve(tissue, [5.0])                           # the equilibrium at cup strokes (mm)
    plans = scissor.plan(cfg, tissue)                           # each target's needle and strokes
    task = scissor.tasks(cfg, tissue, plans)[0]                 # a planned target, as plain data
    result = scissor.manipulate(cfg, task, controller=MyController())   # the closed loop
    summary = scissor.simulate(cfg, "runs/mine")                # everything `scissor simulate` does
    trials = scissor.read_trials("runs/mine/results.h5")        # the trials' arrays per target

Nothing here is a second machinery: each name hands over to the function
the CLI runs (`experiments`, `control`, `solvers`), and `scissor
simulate` itself runs through `run`. The names in `__all__` are kept
stable; docs/api.md lists them with their arguments.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache
from pathlib import Path
from typing import Optional, Union

import h5py
import numpy as np

from scissor_cli import control
from scissor_cli.config import Config, ConfigError, load_config, parse_config, resolved_yaml
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.control import ControllerError, ControllerLaw, LoopResult, PIDLaw
from scissor_cli.experiments.body_closed_loop import body_plans, body_tasks
from scissor_cli.experiments.body_resolution import resolved_by_accuracy
from scissor_cli.experiments.run_summary import RunSummary
from scissor_cli.experiments.selection import resolved_by_selection
from scissor_cli.experiments.simulate import layer_plans, run_simulation, trial_tasks
from scissor_cli.experiments.trial_stage import Execution
from scissor_cli.experiments.trial_types import TargetTask
from scissor_cli.experiments.trials import trial_context
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.output.results_sink import RunDirectory
from scissor_cli.solvers.equilibrium import solve_equilibrium

Scene = Union[Config, BodyConfig]

__all__ = [
    "ConfigError", "ControllerError", "ControllerLaw", "LoopResult", "PIDLaw", "Scene", "TargetTask",
    "build_tissue", "load_config", "manipulate", "parse_config", "plan", "read_trials", "resolved_yaml", "run",
    "simulate", "solve", "tasks", "trial_run",
]


def build_tissue(cfg: Scene) -> Tissue:
    """The scene's tissue as `simulate` builds it (the 2-D layer, on what `solver.accuracy_mm` picks when given;
    or the body at `controller.mesh_scale`, on the element and mesh `tissue.accuracy_mm` picks when given): the one
    the trials of this config use in this process, built on first use."""
    return _context(cfg).tissue


def _context(cfg: Scene):
    """The trial context `simulate`'s trials of this config would run in (`experiments.trials.trial_context`)."""
    return trial_context(_computed_yaml(resolved_yaml(cfg)))


@lru_cache(maxsize=8)
def _computed_yaml(config_yaml: str) -> str:
    """The config a run computes on, as YAML: a body's `tissue.accuracy_mm` resolved into its element and model
    mesh (`experiments.body_resolution.resolved_by_accuracy`), a layer's `solver.accuracy_mm` into its element,
    mesh, model and solver (`experiments.selection.resolved_by_selection`), as `simulate` resolves them (both
    solve, so the answer is kept)."""
    cfg = parse_config(config_yaml, "<api config>")
    if isinstance(cfg, BodyConfig):
        return config_yaml if cfg.tissue.accuracy_mm is None else resolved_yaml(resolved_by_accuracy(cfg)[0])
    return config_yaml if cfg.solver.accuracy_mm is None else resolved_yaml(resolved_by_selection(cfg)[0])


def solve(tissue: Tissue, strokes_mm, start: Optional[np.ndarray] = None):
    """The static equilibrium at cup strokes (C,) mm (`solvers.equilibrium.solve_equilibrium`, Newton): its
    `x` (N, d) mm are the deformed nodes; SolverError when it does not converge."""
    return solve_equilibrium(tissue, np.asarray(strokes_mm, float), start=start)


def plan(cfg: Scene, tissue: Tissue) -> list:
    """Each target's needle plan, in the scene's order: the layer's (`NeedlePlan`, docs/model.md §8) or the
    body's (`BodyNeedlePlan`, §19). The plans `simulate` makes on the layer model; with another
    `controller.model` it replans inside the stroke reserve, which needs the slab and is `simulate`'s."""
    return body_plans(cfg, tissue) if isinstance(cfg, BodyConfig) else layer_plans(cfg, tissue)


def tasks(cfg: Scene, tissue: Tissue, plans: list) -> list[TargetTask]:
    """The targets with a feasible plan, as the plain-data tasks the trials run (rest, desired, needle axis)."""
    return body_tasks(tissue, plans) if isinstance(cfg, BodyConfig) else trial_tasks(tissue, plans)


def trial_run(cfg: Scene, task: TargetTask, trial: Optional[int] = None) -> tuple[Tissue, control.TargetRun]:
    """The tissue model and `control.TargetRun` of trial `trial` (the profile's draws for it, its sensor, the
    truth: `simulate`'s trial with that index and the config's seed), or with None the nominal manipulation's
    (the model's truth, an exact sensor)."""
    context = _context(cfg)
    if trial is None:
        return context.tissue, context.nominal_run(task)
    return context.tissue, context.target_run(task, trial)[0]


def manipulate(cfg: Scene, task: TargetTask, controller: Optional[ControllerLaw] = None,
               trial: Optional[int] = None) -> LoopResult:
    """One target's closed loop (docs/model.md §6): the nominal one (truth = model, exact sensor) or, with
    `trial`, that trial's. `task` is one of `tasks(...)`; `controller` any object with
    reset(observation, info) and act(observation, info) (docs/model.md §22), else `controller.law`'s."""
    tissue, run = trial_run(cfg, task, trial)
    return control.run_target(tissue, task.rest, task.desired, cfg.controller, replace(run, law=controller))


def run(cfg: Scene, directory: Path, execution: Execution = Execution()) -> RunSummary:
    """`scissor simulate` into `directory` (its results.h5, figures, journal; it must be free to use)."""
    out = RunDirectory(Path(directory))
    out.start(resolved_yaml(cfg))
    return run_simulation(cfg, out, execution)


def simulate(cfg: Scene, directory: Union[str, Path], jobs: int = 1) -> RunSummary:
    """Everything `scissor simulate` does for `cfg`, into `directory` (created), with `jobs` trial processes."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    return run(cfg, directory, Execution(jobs))


def read_trials(path: Union[str, Path]) -> dict[str, dict[str, np.ndarray]]:
    """The trials of a results.h5 per target: every array under /trials/<target> (final_error (T, d) mm,
    iterations, stop_reason, failed, …, docs/contract.md), strings decoded."""
    out: dict[str, dict[str, np.ndarray]] = {}
    with h5py.File(path, "r") as f:
        for name, group in f.get("trials", {}).items():
            out[name] = {key: (ds.asstr()[()] if ds.dtype.kind == "O" else ds[()])
                         for key, ds in group.items() if isinstance(ds, h5py.Dataset)}
    return out
