"""The insertion stage of `scissor simulate` (docs/model.md §12): every planned target, every strategy.

Each target is inserted from the equilibrium at its plan's strokes (the
nominal manipulation's end: model = truth, exact camera) along the plan's
entry and direction, once per configured strategy. The results and figures
go to the sink; the first target with a plan also gets the animation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scissor_cli.config import Config
from scissor_cli.experiments.sink import Insertion, RunSink, product_key
from scissor_cli.insertion import NeedleParams, run_insertion
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.equilibrium import solve_equilibrium

#: equilibria shown for the manipulation before the insertion in the animation
RAMP_FRAMES = 6


def manipulation_ramp(tissue: Tissue, strokes: np.ndarray, frames: int = RAMP_FRAMES) -> list[np.ndarray]:
    """Equilibria (N, 2) at strokes × k/frames, k = 0..frames, each warm-started from the last; the last is the start."""
    strokes = np.asarray(strokes, float)
    x, s_prev, out = tissue.rest.copy(), np.zeros_like(strokes), [tissue.rest.copy()]
    for k in range(1, frames + 1):
        s = strokes * k / frames
        x = solve_equilibrium(tissue, s, start=x, start_strokes=s_prev).x
        s_prev = s
        out.append(x)
    return out


def insertion_stage(cfg: Config, tissue: Tissue, plans: list, sink: RunSink, reporter,
                    done: frozenset[str] = frozenset()) -> list[Path]:
    """Insert into every planned target not in `done` under every strategy; print each target's miss per strategy."""
    params = NeedleParams.from_config(cfg.insertion, cfg)
    paths: list[Path] = []
    first = next((t.name for t, p in zip(tissue.scene.targets, plans) if p.feasible), None)
    for target, plan in zip(tissue.scene.targets, plans):
        if product_key("insertion", target.name) in done:
            continue
        if not plan.feasible:
            reporter.info(f"insertion {target.name}: skipped, no plan ({plan.reason})")
            continue
        animate = target.name == first
        frames = manipulation_ramp(tissue, plan.strokes, RAMP_FRAMES if animate else 1)
        results = [
            run_insertion(tissue, frames[-1], plan.strokes, plan.entry, plan.direction, plan.depth_mm, target.rest,
                          params, strategy, controller=cfg.controller, target_name=target.name)
            for strategy in cfg.insertion.strategies
        ]
        paths += sink.insertion(Insertion(target.name, results, tissue, np.asarray(target.rest, float),
                                          np.asarray(plan.desired, float), frames, animate))
        sink.mark_finished(product_key("insertion", target.name))
        parts = ", ".join(f"{r.strategy} {r.miss_mm:.3f} mm (depth error {r.depth_error_mm:+.3f} mm)" for r in results)
        reporter.info(f"insertion {target.name}: miss {parts}")
        for r in results:
            if not r.completed:
                reporter.info(f"insertion {target.name} ({r.strategy}): {r.stop_reason}")
            if r.obstacle_touched:
                reporter.info(f"insertion {target.name} ({r.strategy}): the shaft touched an obstacle")
            if r.unsettled:
                reporter.info(f"insertion {target.name} ({r.strategy}): the stick-slip set did not settle in "
                              f"{r.unsettled} step(s)")
    return paths
