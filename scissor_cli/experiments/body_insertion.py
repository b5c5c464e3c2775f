"""The insertion stage of a 3-D run (docs/model.md §20, §12): every planned lesion, every strategy, in the body.

Each lesion is inserted from the body's equilibrium at its plan's strokes
(the truth's mesh, nothing drawn: as a layer's nominal insertion) along the
plan's entry and direction — any 3-D axis — once per configured strategy,
seen by the scene's camera(s) without error (one camera does not see its
depth: `depth` measures along what it sees, `loop` drives what it sees)
(`none` and `depth` on one needle that branches for its last step,
`insertion.run_strategies`). The needle's law is §12's with state on the
tetrahedra; `depth` stops at the lesion's measured position along the
axis; `loop` drives both components of the miss across the needle with
every cup, steered by the controller's model of the lesion under the
needle: the nominal `depth` insertion tabulated (`body_needle_models`, the
same in every trial), its J (2 × cups) the held response there. The
results have 3-D shapes (`tip`, `target` (K, 3), `displacement` (K, N, 3));
the figures are the force against depth and the lesion's path in the plane
across the needle.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.experiments import run_cache
from scissor_cli.experiments.body_trials import body_sensor_model, nominal_insertions, plan_path
from scissor_cli.experiments.insertion_stage import StepBar, report_insertions, to_insert
from scissor_cli.experiments.needle_model_stage import cached_needle_model
from scissor_cli.experiments.profiles import error_model
from scissor_cli.experiments.sink import Insertion, RunSink, product_key
from scissor_cli.insertion import NeedleModel, NeedleParams
from scissor_cli.insertion.model_table import tabulate
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.equilibrium import solve_equilibrium


def body_insertion_stage(cfg: BodyConfig, truth: Tissue, plans: list, sink: RunSink,
                         done: frozenset[str] = frozenset(), needle: Optional[dict] = None,
                         starts: Optional[dict] = None) -> list[Path]:
    """Insert into every planned lesion not in `done` under every strategy, in the body `truth` (the configured
    mesh); print each lesion's miss per strategy. Returns the figures' paths.

    needle: {lesion: NeedleModel} `loop` steers with (`body_needle_models`); starts: {lesion: the body's
    equilibrium (N, 3) at its plan's strokes} already solved (filled here with those it solves)."""
    starts = {} if starts is None else starts
    needle = needle or {}
    sensors = body_sensor_model(cfg, error_model(cfg.trials), truth.mesh)
    params = NeedleParams.from_config(cfg.insertion, cfg.needle, cfg.tissue.mesh)
    index = {t.name: k for k, t in enumerate(truth.scene.targets)}
    paths: list[Path] = []
    for target, plan in to_insert(truth.scene.targets, plans, done):
        strokes = np.asarray(plan.strokes, float)
        path = plan_path(plan, target.rest, target.name)
        bar = StepBar(target.name, path.depth_mm, params, list(cfg.insertion.strategies))
        try:
            results = nominal_insertions(cfg, truth, sensors, index[target.name], path, strokes,
                                         np.asarray(plan.desired, float),
                                         _plan_start(truth, target.name, strokes, starts), needle.get(target.name),
                                         on_step=bar)
        finally:
            bar.close()
        paths += store_insertion(sink, truth, target, plan, results, needle.get(target.name))
    return paths


def store_insertion(sink: RunSink, truth: Tissue, target, plan, results: list,
                    needle: Optional[NeedleModel]) -> list[Path]:
    """Store a lesion's (the scene's `target`) nominal insertions along its plan (/insertion), mark them finished,
    print the misses; their figures."""
    paths = sink.insertion(Insertion(target.name, results, truth, np.asarray(target.rest, float),
                                     np.asarray(plan.desired, float), [], False, None, needle))
    sink.mark_finished(product_key("insertion", target.name))
    report_insertions(target.name, results)
    return paths


def body_needle_models(cfg: BodyConfig, model: Tissue, plans: list, cache: Optional[Path],
                       starts: Optional[dict] = None) -> dict:
    """{lesion: NeedleModel} of every feasible plan: the controller's model of its lesion under the needle, which
    `loop` steers with in the nominal insertion and in every trial (docs/model.md §20).

    The controller's own body (`model`: at `controller.mesh_scale`, the
    truth's mesh at 1), its `depth` insertion at the plan's strokes,
    tabulated (`insertion.model_table.tabulate`: the lesion after every
    step, its held response to each cup along the way): a table of the
    lesion, not of nodes, so it steers a truth on another mesh. Kept in the
    run's cache keyed by what it depends on, so a second run or a resume
    reads it. starts: as `body_insertion_stage`'s, for the same body
    (filled here).
    """
    params = NeedleParams.from_config(cfg.insertion, cfg.needle, cfg.tissue.mesh)
    starts = {} if starts is None else starts
    out = {}
    for target, plan in zip(model.scene.targets, plans):
        if not plan.feasible:
            continue
        strokes = np.asarray(plan.strokes, float)
        needle = plan_path(plan, target.rest, target.name)

        def make(name=target.name, strokes=strokes, needle=needle) -> NeedleModel:
            return tabulate(model, _plan_start(model, name, strokes, starts), strokes, needle, params, cfg.controller)

        try:
            table, how = cached_needle_model(
                None if cache is None else cache / f"body-needle-{target.name}-{_key(cfg, plan)}.npz", make)
        except SolverError as exc:  # `loop` on this lesion steers on the body under the needle instead
            progress.info(f"needle model {target.name}: none ({exc}); `loop` follows the needle in the undrawn "
                          f"body instead")
            continue
        out[target.name] = table
        drag = np.linalg.norm(table.target_mm[-1] - table.target_mm[0])
        progress.info(f"needle model {target.name} ({how}): the needle drags the lesion {drag:.3f} mm on its way")
    return out


def _plan_start(body: Tissue, name: str, strokes: np.ndarray, starts: dict) -> np.ndarray:
    """The body's equilibrium (N, 3) at a plan's strokes (C,), solved once per run (kept in starts by lesion)."""
    if name not in starts:
        starts[name] = solve_equilibrium(body, strokes).x
    return starts[name]


def _key(cfg: BodyConfig, plan) -> str:
    return run_cache.key({
        "scene": cfg.model_dump(mode="json", include={"tissue", "material", "cups", "targets", "obstacles",
                                                      "insertion", "needle"}),
        "mesh_scale": cfg.controller.mesh_scale,
        "plan": [np.round(np.asarray(v, float), 9).tolist() for v in (plan.strokes, plan.entry, plan.direction)]
        + [round(float(plan.depth_mm), 9)],
    })
