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
every cup, J (2 × cups) the body's held response (`ModelState`, the
controller's model the body itself, as in a layer's nominal run). The
results have 3-D shapes (`tip`, `target` (K, 3), `displacement` (K, N, 3));
the figures are the force against depth and the lesion's path in the plane
across the needle.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.experiments.body_trials import body_sensor_model
from scissor_cli.experiments.insertion_stage import StepBar, report_insertions, to_insert
from scissor_cli.experiments.profiles import error_model
from scissor_cli.experiments.sink import Insertion, RunSink, product_key
from scissor_cli.insertion import InsertionOptions, NeedleParams, NeedlePath, run_strategies
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.equilibrium import solve_equilibrium


def body_insertion_stage(cfg: BodyConfig, truth: Tissue, plans: list, sink: RunSink,
                         done: frozenset[str] = frozenset()) -> list[Path]:
    """Insert into every planned lesion not in `done` under every strategy, in the body `truth` (the configured
    mesh); print each lesion's miss per strategy. Returns the figures' paths."""
    params = NeedleParams.from_config(cfg.insertion, cfg.needle, cfg.tissue.mesh)
    strategies = list(cfg.insertion.strategies)
    sensors = body_sensor_model(cfg, error_model(cfg.trials), truth.mesh)
    index = {t.name: k for k, t in enumerate(truth.scene.targets)}
    paths: list[Path] = []
    for target, plan in to_insert(truth.scene.targets, plans, done):
        strokes = np.asarray(plan.strokes, float)
        x0 = solve_equilibrium(truth, strokes).x
        path = NeedlePath(np.asarray(plan.entry, float), np.asarray(plan.direction, float), float(plan.depth_mm),
                          np.asarray(target.rest, float), target.name)
        sensor = sensors.nominal(np.asarray(plan.desired, float), index[target.name], cfg.seed)
        bar = StepBar(target.name, path.depth_mm, params, strategies)
        try:
            results = run_strategies(truth, x0, strokes, dict.fromkeys(strategies, path), params,
                                     {k: InsertionOptions(k, cfg.controller, sensor=sensor, on_step=bar)
                                      for k in strategies})
        finally:
            bar.close()
        paths += sink.insertion(Insertion(target.name, results, truth, np.asarray(target.rest, float),
                                          np.asarray(plan.desired, float), [], False, None))
        sink.mark_finished(product_key("insertion", target.name))
        report_insertions(target.name, results)
    return paths
