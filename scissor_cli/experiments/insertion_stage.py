"""The insertion stage of `scissor simulate` (docs/model.md §12, §14): every planned target, every strategy.

Each target is inserted from the equilibrium at its plan's strokes (the
nominal manipulation's end: exact camera, no perturbation) along the plan's
entry and direction, once per configured strategy (`none` and `depth` on
one needle that branches for its last step, `run_strategies`). The truth
is the layer (model = truth), or with `trials.truth: slab` the nominal slab of
`layer_check` (docs/model.md §14): entry and axis lifted to the layer's
height, `loop`'s controller on its 2-D model, and the results with 3-D
shapes (`tip`, `target` (K, 3), `displacement` (K, N3, 3)). The results and
figures go to the sink; the first target with a plan also gets the
animation (in the layer's plane).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from scissor_cli import progress
from scissor_cli.config import Config
from scissor_cli.experiments.sink import Insertion, RunSink, product_key
from scissor_cli.insertion import InsertionOptions, NeedleParams, NeedlePath, needle_path, run_strategies
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.equilibrium import solve_equilibrium

#: equilibria shown for the manipulation before the insertion in the animation
RAMP_FRAMES = 6


def manipulation_ramp(tissue: Tissue, strokes: np.ndarray, frames: int = RAMP_FRAMES) -> list[np.ndarray]:
    """Equilibria (N, 2) at strokes × k/frames, k = 0..frames, each warm-started from the last; the last is the
    start."""
    strokes = np.asarray(strokes, float)
    x, s_prev, out = tissue.rest.copy(), np.zeros_like(strokes), [tissue.rest.copy()]
    for k in range(1, frames + 1):
        s = strokes * k / frames
        x = solve_equilibrium(tissue, s, start=x, start_strokes=s_prev).x
        s_prev = s
        out.append(x)
    return out


def slab_ramp(slab: Tissue, strokes: np.ndarray, frames: int, tol: float) -> list[np.ndarray]:
    """The slab's equilibria (N3, 3) at strokes × k/frames, k = 1..frames, each warm-started from the last."""
    strokes = np.asarray(strokes, float)
    x, s_prev, out = None, None, []
    for k in range(1, frames + 1):
        s = strokes * k / frames
        x = solve_equilibrium(slab, s, start=x, start_strokes=s_prev, tol=tol).x
        s_prev = s
        out.append(x)
    return out


class StepBar:
    """The progress of one target's insertions: a bar over their planned steps, advanced after each step.

    `none` and `depth` share their steps (`run_strategies`), so their needle
    counts once. The bar holds at its last step until `close` (an insertion
    may take more steps than planned, or fewer): a live bar must end before
    the next one starts.
    """

    def __init__(self, target: str, depth_mm: float, params: NeedleParams, strategies: list[str]):
        needles = bool(set(strategies) - {"loop"}) + ("loop" in strategies)
        self.left = max(1, needles * int(np.ceil(depth_mm / params.step_mm)))
        self.advance = progress.bar(f"insertion {target} ({', '.join(strategies)})", self.left)

    def __call__(self, depth_mm: float) -> None:
        if self.left > 1:
            self.advance(1)
            self.left -= 1

    def close(self) -> None:
        self.advance(self.left)
        self.left = 0


def to_insert(targets, plans: list, done: frozenset[str]):
    """(target, plan) of every target to insert: not in `done`, with a plan (a skipped one is said)."""
    for target, plan in zip(targets, plans):
        if product_key("insertion", target.name) in done:
            continue
        if not plan.feasible:
            progress.info(f"insertion {target.name}: skipped, no plan ({plan.reason})")
            continue
        yield target, plan


def report_insertions(target: str, results: list) -> None:
    """Print one target's miss per strategy, and what did not go as planned."""
    parts = ", ".join(f"{r.strategy} {r.miss_mm:.3f} mm (depth error {r.depth_error_mm:+.3f} mm)" for r in results)
    progress.info(f"insertion {target}: miss {parts}")
    for r in results:
        if not r.completed:
            progress.info(f"insertion {target} ({r.strategy}): {r.stop_reason}")
        if r.obstacle_touched:
            progress.info(f"insertion {target} ({r.strategy}): the shaft touched an obstacle")
        if r.unsettled:
            progress.info(f"insertion {target} ({r.strategy}): the stick-slip set did not settle in "
                          f"{r.unsettled} step(s)")


def _insert(tissue: Tissue, x0: np.ndarray, strokes: np.ndarray, paths: dict, params: NeedleParams,
            options: dict) -> list:
    """`run_strategies` ({strategy: path}, {strategy: options}) with one progress bar over the steps."""
    first = next(iter(paths.values()))
    bar = StepBar(first.target_name, first.depth_mm, params, list(paths))
    try:
        return run_strategies(tissue, x0, strokes, paths, params,
                              {k: replace(o, on_step=bar) for k, o in options.items()})
    finally:
        bar.close()


def _in_slab(cfg: Config, tissue: Tissue, truth, target, plan, params, animate: bool, needle=None):
    """One target's insertions in the nominal slab (`layer3d.truth.SlabTruth`): results and the in-plane frames.

    needle: the target's `NeedleModel` (a 3-D-aware controller, docs/model.md §18): it aims the needle's height
    per strategy and steers `loop`; without one the needle lies in the layer and `loop` steers with the 2-D
    model's own insertion.
    """
    from scissor_cli.layer3d.slab import layer_probe
    from scissor_cli.layer3d.truth import SLAB_TRUTH_TOL

    slab = truth.slab
    ramp = slab_ramp(slab, plan.strokes, RAMP_FRAMES if animate else 1, SLAB_TRUTH_TOL)
    layer = layer_probe(slab, tissue.mesh)
    frames = [tissue.rest.copy()] + [layer.positions(x)[:, :2] for x in ramp]
    model_x0 = None
    if "loop" in cfg.insertion.strategies and needle is None:
        model_x0 = solve_equilibrium(tissue, plan.strokes).x
    strategies = cfg.insertion.strategies
    paths = {k: needle_path(slab, plan.entry, plan.direction, plan.depth_mm, target.rest, target.name,
                            None if needle is None else needle.height_for(k)) for k in strategies}
    results = _insert(slab, ramp[-1], plan.strokes, paths, params,
                      {k: InsertionOptions(k, cfg.controller, model=tissue, model_x0=model_x0, needle_model=needle)
                       for k in strategies})
    return results, frames, layer


def insertion_stage(cfg: Config, tissue: Tissue, plans: list, sink: RunSink,
                    done: frozenset[str] = frozenset(), needle: dict | None = None) -> list[Path]:
    """Insert into every planned target not in `done` under every strategy; print each target's miss per strategy.

    needle: {target name: NeedleModel} of a 3-D-aware controller in the slab (docs/model.md §18), else None.
    """
    params = NeedleParams.from_config(cfg.insertion, cfg.needle, cfg.tissue.mesh)
    truth = None
    if cfg.trials.truth == "slab" and cfg.layer_check is not None:
        from scissor_cli.layer3d.check import slab_spec
        from scissor_cli.layer3d.truth import SlabTruth

        truth = SlabTruth(tissue, slab_spec(cfg.layer_check, cfg.tissue.mesh))
    paths: list[Path] = []
    first = next((t.name for t, p in zip(tissue.scene.targets, plans) if p.feasible), None)
    for target, plan in to_insert(tissue.scene.targets, plans, done):
        animate = target.name == first
        layer = None
        if truth is None:
            frames = manipulation_ramp(tissue, plan.strokes, RAMP_FRAMES if animate else 1)
            path = NeedlePath(plan.entry, plan.direction, plan.depth_mm, target.rest, target.name)
            strategies = cfg.insertion.strategies
            results = _insert(tissue, frames[-1], plan.strokes, dict.fromkeys(strategies, path), params,
                              {k: InsertionOptions(k, cfg.controller) for k in strategies})
        else:
            results, frames, layer = _in_slab(cfg, tissue, truth, target, plan, params, animate,
                                              (needle or {}).get(target.name))
        paths += sink.insertion(Insertion(target.name, results, tissue, np.asarray(target.rest, float),
                                          np.asarray(plan.desired, float), frames, animate, layer))
        sink.mark_finished(product_key("insertion", target.name))
        report_insertions(target.name, results)
    return paths
