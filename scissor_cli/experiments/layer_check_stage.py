"""The layer-check stage of `scissor simulate` (docs/model.md §13).

After the forward cases: the slab of `layer_check` is solved for every
forward case and compared with the 2-D layer. The layer is solved again
with Newton to its reference tolerance for the comparison, so the check
compares models, not the configured solver's tolerance.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config import Config
from scissor_cli.experiments import run_cache
from scissor_cli.experiments.build import build_model
from scissor_cli.experiments.pool import run_pool
from scissor_cli.experiments.sink import product_key
from scissor_cli.layer3d.check import build_layer_check, plane_ladder, slab_spec
from scissor_cli.layer3d.resolution import SlabCandidate, SlabChoice, choose_slab, in_process
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.equilibrium import EquilibriumSolver


def run_layer_check(cfg: Config, tissue: Tissue, sink, done: frozenset[str] = frozenset()) -> list:
    """Solve and hand to the sink the layer check of every forward case not in `done`; returns the figures' paths."""
    cases = [case for case in cfg.forward if product_key("layer_check", case.name) not in done]
    if not cases:
        return []
    t0 = time.perf_counter()
    check = build_layer_check(tissue, slab_spec(cfg.layer_check, cfg.tissue.mesh))
    sm = check.mesh
    progress.info(f"layer check: slab of {sm.n_elements} tetrahedra, {sm.n_nodes} nodes, "
                  f"{len(sm.levels_mm) - 1} prism layers, built in {time.perf_counter() - t0:.1f} s")
    sink.layer_check_mesh(sm)
    scene, mesh = tissue.scene, tissue.mesh
    layer = EquilibriumSolver(tissue, "newton")
    paths = []
    advance = progress.bar("layer check", len(cases))
    for case in cases:
        strokes = scene.strokes_vector(case.strokes)
        r2 = layer.solve(strokes)
        result = check.run_case(case.name, strokes, r2)
        rest = {t.name: t.rest for t in scene.targets}
        figure = dict(
            title=(f"{cfg.name} — layer check {case.name}: in-plane difference {result.in_plane_diff_mm:.3f} mm "
                   f"({100 * result.in_plane_diff_fraction:.1f} %), out of plane {result.out_of_plane_mm:.3f} mm, "
                   f"closer to {result.closer_to.replace('_', ' ')}"),
            rest_2d=mesh.nodes, layer_2d=r2.x, layer_3d=result.layer_nodes, triangles=mesh.triangles,
            targets_rest=rest, targets_2d=result.targets_2d, targets_3d=result.targets,
            targets_stress=result.targets_stress, layer_z_mm=float(sm.levels_mm[sm.layer_level]),
        )
        path = sink.layer_check(result, figure)
        sink.mark_finished(product_key("layer_check", case.name))
        progress.info(
            f"layer check {case.name}: 3-D Newton {result.iterations} iterations, {result.time_s:.1f} s; in-plane "
            f"difference {result.in_plane_diff_mm:.3f} mm ({100 * result.in_plane_diff_fraction:.1f} %), "
            f"out of plane {result.out_of_plane_mm:.3f} mm, closer to {result.closer_to}"
        )
        if path is not None:
            paths.append(path)
        advance(1)
    return paths


#: the share of each cup's stroke limits the ladder's cases use when the scene has no forward case
LADDER_STROKE_FRACTION = 2.0 / 3.0


def ladder_cases(cfg: Config, scene) -> list[np.ndarray]:
    """The strokes (C,) mm the slab's candidates are compared at: the forward cases, or without any, each cup alone
    at LADDER_STROKE_FRACTION of its push and of its pull limit."""
    if cfg.forward:
        return [scene.strokes_vector(case.strokes) for case in cfg.forward]
    cases = []
    for c, cup in enumerate(scene.cups):
        for limit in (cup.stroke_max_mm, cup.stroke_min_mm):
            if limit != 0.0:
                s = np.zeros(len(scene.cups))
                s[c] = LADDER_STROKE_FRACTION * limit
                cases.append(s)
    return cases


def slab_resolution_stage(cfg: Config, cache: Optional[Path] = None, jobs: int = 1) -> tuple[Config, SlabChoice]:
    """`layer_check.accuracy_mm` (0.1 mm unless set; null pins the slab): choose the slab's z grading and in-plane
    mesh (docs/model.md §13, §18); the run goes on with it.

    The config the run records has the chosen `first_layer_mm`,
    `max_layer_mm` and `in_plane_scale` and `accuracy_mm: null`, so the layer check, the slab-truth
    trials and `--resume` build exactly the slab that was chosen; the
    candidates are stored in /layer_check_resolution. The choice is kept in
    `cache` (the `.scissor-cache/` beside the run), keyed by what it depends
    on, so a second run of the scene reads it. With jobs ≥ 2 the ladder's
    slabs are solved in that many worker processes (the same pick and numbers).
    """
    lc = cfg.layer_check
    path = None if cache is None else cache / f"slab-resolution-{_resolution_key(cfg)}.json"
    choice = _read_choice(path)
    if choice is not None:
        progress.info(f"slab resolution: {choice.explain()} (from the cache)")
    else:
        _, _, tissue = build_model(cfg)
        t0 = time.perf_counter()
        choice = choose_slab(tissue, slab_spec(lc, cfg.tissue.mesh), ladder_cases(cfg, tissue.scene), lc.accuracy_mm,
                             plane_ladder(lc, cfg.tissue.mesh), ladder_runner(jobs), jobs)
        progress.info(f"slab resolution: {choice.explain()} ({time.perf_counter() - t0:.1f} s)")
        _write_choice(path, choice)
    chosen = choice.chosen
    section = lc.model_copy(update={"first_layer_mm": chosen.first_layer_mm, "max_layer_mm": chosen.max_layer_mm,
                                    "in_plane_scale": chosen.in_plane_scale, "accuracy_mm": None})
    return cfg.model_copy(update={"layer_check": section}), choice


def ladder_runner(jobs: int):
    """`choose_slab`'s run_tasks: here with one job, else `jobs` worker processes that end with the choice."""
    return (lambda fn, batches: run_pool(fn, batches, jobs)) if jobs > 1 else in_process


def _resolution_key(cfg: Config) -> str:
    """What the ladder's choice depends on, hashed: the scene, its forward cases, the slab, the code's version."""
    return run_cache.key({"ladder": "coarse-to-fine", "scene": cfg.model_dump(mode="json", include={
        "tissue", "material", "cups", "targets", "obstacles", "forward", "layer_check"})})


def _read_choice(path: Optional[Path]) -> Optional[SlabChoice]:
    if path is None or not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        return SlabChoice(float(data["accuracy_mm"]), int(data["pick"]),
                          tuple(SlabCandidate(**c) for c in data["candidates"]))
    except (OSError, ValueError, KeyError, TypeError):  # unreadable: the ladder runs again
        return None


def _write_choice(path: Optional[Path], choice: SlabChoice) -> None:
    if path is None:
        return
    text = json.dumps({"accuracy_mm": choice.accuracy_mm, "pick": choice.pick,
                       "candidates": [asdict(c) for c in choice.candidates]},
                      default=lambda value: value.item())  # numpy scalars as Python numbers
    run_cache.write_whole(path, lambda partial: partial.write_text(text))
