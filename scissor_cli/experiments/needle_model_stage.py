"""The needle-model stage: each plan's target under the needle, as the controller's 3-D model knows it
(docs/model.md §18).

With the needle inserted into the slab (`insertion`, `trials.truth: slab`)
and a 3-D-aware controller model (calibrated, surrogate, slab), every
feasible plan gets a `insertion.NeedleModel`: the nominal slab's insertion
at the plan's strokes (`insertion.model_table.tabulate`), with the needle
aimed at the target's height there. Its end heights aim the trials' and the
nominal run's needle (per strategy), and `loop` steers with its held
Jacobian. It is kept in the cache beside the run, keyed by what it depends
on (the scene, the slab, the needle, the loop's gains and the plan), so a
second run or a resume reads it; with the `layer` model nothing is made
(the paper's method is tested as it is).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config import Config
from scissor_cli.experiments import run_cache
from scissor_cli.insertion import NeedleParams, NeedlePath
from scissor_cli.insertion.model_table import tabulate
from scissor_cli.insertion.steering import NeedleModel
from scissor_cli.layer3d.slab import slab_probe
from scissor_cli.layer3d.truth import SLAB_TRUTH_TOL
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.equilibrium import solve_equilibrium


def needs_needle_models(cfg: Config) -> bool:
    """Whether the run inserts into the slab under a 3-D-aware controller model."""
    return (cfg.insertion is not None and cfg.layer_check is not None and cfg.trials.truth == "slab"
            and cfg.controller.model != "layer")


def _key(cfg: Config, plan) -> str:
    return run_cache.key({
        "tol": SLAB_TRUTH_TOL,
        "scene": cfg.model_dump(mode="json", include={"tissue", "material", "cups", "obstacles", "layer_check",
                                                      "insertion", "needle"}),
        "gains": cfg.controller.model_dump(mode="json", include={"kp", "ki", "kd", "rate_hz", "jacobian_update"}),
        "plan": [np.round(np.asarray(v, float), 9).tolist() for v in (plan.strokes, plan.entry, plan.direction)]
        + [round(float(plan.depth_mm), 9)],
    })


def needle_models(cfg: Config, tissue: Tissue, slab: Tissue, plans: list, cache: Optional[Path]) -> dict:
    """{target name: NeedleModel} of every feasible plan (from the cache where it holds one)."""
    params = NeedleParams.from_config(cfg.insertion, cfg.needle, cfg.tissue.mesh)
    layer_z = float(cfg.layer_check.layer_z_mm)
    out = {}
    for target, plan in zip(tissue.scene.targets, plans):
        if not plan.feasible:
            continue

        def make(target=target, plan=plan) -> NeedleModel:
            strokes = np.asarray(plan.strokes, float)
            x0 = solve_equilibrium(slab, strokes, tol=SLAB_TRUTH_TOL).x
            height = float(slab_probe(slab, np.asarray(target.rest, float)[None]).positions(x0)[0, 2])
            needle = NeedlePath(np.append(plan.entry, height), np.append(plan.direction, 0.0), float(plan.depth_mm),
                                np.asarray(target.rest, float), target.name)
            return tabulate(slab, x0, strokes, needle, params, cfg.controller)

        model, how = cached_needle_model(
            None if cache is None else cache / f"needle-{target.name}-{_key(cfg, plan)}.npz", make)
        out[target.name] = model
        progress.info(f"needle model {target.name} ({how}): the target ends {model.end_height_mm - layer_z:+.3f} mm "
                      f"off the layer's plane, {model.steered_height_mm - layer_z:+.3f} mm with loop: the needle "
                      f"is aimed there")
    return out


def cached_needle_model(path: Optional[Path], make: Callable[[], NeedleModel]) -> tuple[NeedleModel, str]:
    """The model cached at path (None: no cache), else make()'s, written there; and how it was had (for the log)."""
    model = read_needle_model(path)
    if model is not None:
        return model, "from the cache"
    t0 = time.perf_counter()
    model = make()
    if path is not None:
        write_needle_model(path, model)
    return model, f"{len(model.depth_mm)} steps in {time.perf_counter() - t0:.1f} s"


def write_needle_model(path: Path, model: NeedleModel) -> None:
    """The model as one .npz, written whole."""
    run_cache.write_whole(path, lambda partial: np.savez(
        partial, depth_mm=model.depth_mm, target_mm=model.target_mm, jacobian=model.jacobian,
        heights=np.array([model.entry_height_mm, model.steered_height_mm])))


def read_needle_model(path: Optional[Path]) -> Optional[NeedleModel]:
    """A cached model, or None (none there, or unreadable: it is made again)."""
    if path is None or not path.is_file():
        return None
    try:
        with np.load(path) as f:
            entry, steered = (float(v) for v in f["heights"])
            return NeedleModel(f["depth_mm"], f["target_mm"], f["jacobian"], entry, steered)
    except (OSError, ValueError, KeyError):
        return None
