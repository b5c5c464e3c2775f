"""The controller-model stage: fit the controller's model and plan with it (docs/model.md §15).

After the layer's needle plans: with `controller.model` other than `layer`
the model is fitted to the nominal slab (calibrated: a handful of slab
solves; surrogate: its design), or read from the cache beside the run
(`<run's parent>/.scissor-cache/`, keyed by everything the fit depends on,
so a second run or a resume reuses it). Then each planned target's strokes
are re-derived with that model (`control.models.strokes_for`: the strokes
its model needs for the plan's desired point), and with a slab at hand
(any non-layer model, or `trials.truth: slab`) also the nominal slab's. A
3-D-aware model that cannot bring the target within the controller's
tolerance inside the stroke limits makes the plan infeasible before any
trial runs; with the `layer` model the slab's verdict is reported beside
the plan (the paper's method is tested as it is). The same holds for the
plan's needle corridor, judged again on the nominal slab at the strokes it
needs (`SlabMap.clearance`: its obstacles are where the slab moves them,
not where the layer does).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config import Config, resolved_yaml
from scissor_cli.experiments import run_cache
from scissor_cli.experiments.model_planning import Replan, plan_with_model
from scissor_cli.experiments.needle_model_stage import needle_models, needs_needle_models
from scissor_cli.experiments.pool import run_pool
from scissor_cli.layer3d.calibration import Calibration
from scissor_cli.layer3d.surrogate import SurrogateSamples, solve_samples
from scissor_cli.layer3d.tissue_models import (
    ControllerModel,
    ModelData,
    ModelPaths,
    SceneMap,
    build_model_data,
    model_solves,
    slab_map,
)
from scissor_cli.layer3d.truth import SLAB_TRUTH_TOL
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.text import vector


def needs_slab(cfg: Config) -> bool:
    """Whether the stage runs at all: a non-layer controller model, or slab truth (the plans' slab strokes)."""
    return cfg.layer_check is not None and (cfg.controller.model != "layer" or cfg.trials.truth == "slab")


def cache_key(cfg: Config, plan_strokes: list[np.ndarray]) -> str:
    """What the fitted model depends on, hashed: the scene, material, cups, targets, slab, design, the code's
    version."""
    kind = cfg.controller.model
    parts = {
        "kind": kind, "tol": SLAB_TRUTH_TOL,
        "scene": cfg.model_dump(mode="json", include={"tissue", "material", "cups", "targets", "obstacles",
                                                      "layer_check"}),
        "surrogate": cfg.controller.surrogate.model_dump(mode="json") if kind == "surrogate" else None,
        "plans": [np.round(np.asarray(s, float), 9).tolist() for s in plan_strokes] if kind == "calibrated" else None,
        "learns_layer": kind == "surrogate",  # a surrogate cached before it learned the layer is fitted again
    }
    return run_cache.key(parts)


def save_model_data(path: Path, data: ModelData) -> None:
    """The fitted arrays as one .npz, written whole (a temporary file renamed), so a killed run leaves no half file."""
    arrays = {"kind": np.array(data.kind), "build_time_s": np.array(data.build_time_s),
              "validation_error_mm": np.array(np.nan if data.validation_error_mm is None else data.validation_error_mm)}
    if data.calibration is not None:
        c = data.calibration
        arrays.update(transmission=c.transmission, fit_strokes=c.strokes, fit_targets=c.targets,
                      fit_error_mm=np.array(c.error_mm))
    if data.samples is not None:
        s = data.samples
        arrays.update(strokes=s.strokes, targets=s.targets, held_strokes=s.held_strokes, held_targets=s.held_targets,
                      lo=s.lo, hi=s.hi)
        if s.layer is not None:
            arrays.update(layer=s.layer, held_layer=s.held_layer)
    run_cache.write_whole(path, lambda partial: np.savez(partial, **arrays))


def load_model_data(path: Path) -> Optional[ModelData]:
    """The cached model, or None when there is none (or it cannot be read: it is then fitted again)."""
    try:
        with np.load(path) as f:
            a = {k: f[k] for k in f.files}
    except (OSError, ValueError, KeyError):
        return None
    error = float(a["validation_error_mm"])
    calibration = samples = None
    if "transmission" in a:
        calibration = Calibration(a["transmission"], a["fit_strokes"], a["fit_targets"], float(a["fit_error_mm"]))
    if "strokes" in a:
        samples = SurrogateSamples(a["strokes"], a["targets"], a["held_strokes"], a["held_targets"], a["lo"], a["hi"],
                                   float(a["build_time_s"]), a.get("layer"), a.get("held_layer"))
    return ModelData(str(a["kind"]), float(a["build_time_s"]), None if np.isnan(error) else error, calibration, samples)


def fitted_model(cfg: Config, tissue: Tissue, slab: Optional[Tissue], plans: list, cache_dir: Optional[Path],
                 jobs: int = 1) -> tuple[ModelData, bool]:
    """The controller's model data, from the cache when it holds this key; (data, came from the cache).

    With jobs ≥ 2 the surrogate's design groups are solved in worker
    processes (`solve_groups_in_workers`): the same numbers, in about half the time.
    """
    plan_strokes = [np.asarray(p.strokes, float) for p in plans if p.feasible]
    kind = cfg.controller.model
    path = None if cache_dir is None else cache_dir / f"controller-{kind}-{cache_key(cfg, plan_strokes)}.npz"
    if path is not None and path.exists():
        data = load_model_data(path)
        if data is not None and data.kind == kind:
            return data, True
    total = model_solves(kind, tissue, plan_strokes, cfg.controller.surrogate.samples)
    advance = progress.bar(f"controller model ({kind}): slab solves", total) if total else (lambda n: None)
    parallel = solve_groups_in_workers(resolved_yaml(cfg), jobs, advance) if jobs > 1 else None
    data = build_model_data(kind, tissue, slab, plan_strokes, cfg.controller.surrogate.samples, advance, parallel)
    if path is not None and kind in ("calibrated", "surrogate"):
        save_model_data(path, data)
    return data, False


def solve_groups_in_workers(config_yaml: str, jobs: int, advance):
    """A `layer3d.surrogate.GroupSolver` on `jobs` worker processes (each builds the scene's nominal slab)."""

    def solve(chunks: list[np.ndarray]) -> list[np.ndarray]:
        out: list = [None] * len(chunks)
        batches = [(config_yaml, k, chunk) for k, chunk in enumerate(chunks)]
        for k, answers in run_pool(_solve_group, batches, min(jobs, len(chunks))):
            out[k] = answers
            advance(len(answers[0]))
        return out

    return solve


_SLABS: dict[str, tuple] = {}


def _solve_group(config_yaml: str, index: int, strokes: np.ndarray) -> list[tuple[int, tuple[np.ndarray, np.ndarray]]]:
    """In a worker: the nominal slab's targets and layer at one design group's strokes (`surrogate.solve_samples`)."""
    if config_yaml not in _SLABS:
        from scissor_cli.config import parse_config  # noqa: PLC0415
        from scissor_cli.experiments.build import build_model  # noqa: PLC0415
        from scissor_cli.layer3d.check import slab_spec  # noqa: PLC0415
        from scissor_cli.layer3d.slab import build_slab, layer_probe, slab_probe  # noqa: PLC0415

        cfg = parse_config(config_yaml, "<run config>")
        scene, mesh, tissue = build_model(cfg)
        slab = build_slab(scene, mesh, slab_spec(cfg.layer_check, cfg.tissue.mesh), model=tissue.params.model,
                          element=tissue.element.name)
        _SLABS[config_yaml] = (slab, slab_probe(slab, np.array([t.rest for t in scene.targets]).reshape(-1, 2)),
                               layer_probe(slab, mesh))
    slab, probe, layer = _SLABS[config_yaml]
    return [(index, solve_samples(slab, probe, strokes, SLAB_TRUTH_TOL, layer=layer))]


def controller_model_stage(cfg: Config, tissue: Tissue, plans: list, location: Optional[Path], jobs: int = 1,
                           replan: Optional[Replan] = None) -> tuple[Optional[ModelData], list, Optional[ModelPaths]]:
    """Fit (or read) the controller's model and plan with it: (model data, plans, the figure's paths).

    replan: see `plan_with_model`.

    (None, plans, None) when the scene has no slab to use; the paths are
    drawn for a non-layer model only.
    """
    if not needs_slab(cfg):
        return None, plans, None
    slab = _nominal_slab(cfg, tissue)
    data, cached = fitted_model(cfg, tissue, slab, plans, run_cache.cache_dir(location), jobs)
    model = ControllerModel(data, tissue, slab)
    how = "from the cache" if cached else f"in {data.build_time_s:.1f} s"
    error = "" if data.validation_error_mm is None else f", error against the slab {data.validation_error_mm:.3g} mm"
    extra = "" if model.transmission is None else f", transmission {vector(model.transmission)}"
    if model.surrogate is not None and model.surrogate.knows_layer:
        extra += f"; its layer (obstacles, skin) within {model.surrogate.layer_error_mm():.3g} mm"
    if data.kind != "layer":
        progress.info(f"controller model {data.kind}: {how}{error}{extra}")
    rests = np.array([t.rest for t in tissue.scene.targets]).reshape(-1, 2)
    slab_answer = slab_map(slab, tissue, rests)
    plans = plan_with_model(cfg, plans, model, slab_answer, replan)
    paths = model_paths(cfg, tissue, model, slab_answer) if model.kind != "layer" else None
    if needs_needle_models(cfg):
        data = replace(data, needle=needle_models(cfg, tissue, slab, plans, run_cache.cache_dir(location)))
    return data, plans, paths


def refitted_model(cfg: Config, tissue: Tissue, location: Optional[Path], plans: list) -> Optional[ModelData]:
    """The model data alone, from the cache or fitted again: a resumed run whose file lost /controller_model
    (its needle models for the stored plans too)."""
    if not needs_slab(cfg):
        return None
    slab = _nominal_slab(cfg, tissue)
    data = fitted_model(cfg, tissue, slab, [], run_cache.cache_dir(location))[0]
    if needs_needle_models(cfg):
        data = replace(data, needle=needle_models(cfg, tissue, slab, plans, run_cache.cache_dir(location)))
    return data


def _nominal_slab(cfg: Config, tissue: Tissue) -> Tissue:
    from scissor_cli.layer3d.check import slab_spec  # noqa: PLC0415
    from scissor_cli.layer3d.slab import build_slab  # noqa: PLC0415

    return build_slab(tissue.scene, tissue.mesh, slab_spec(cfg.layer_check, cfg.tissue.mesh), model=tissue.params.model,
                      element=tissue.element.name)


#: stroke grid of the model's (and the layer's) path in the figure; the slab's is solved at SLAB_PATH_POINTS
PATH_POINTS = 31
SLAB_PATH_POINTS = 7


def model_paths(cfg: Config, tissue: Tissue, model: ControllerModel, slab_answer: SceneMap) -> ModelPaths:
    """The figure's paths: each cup alone over its stroke range (others at rest) — layer, model, nominal slab.

    The slab's points are the model's own slab samples on that line when it
    has at least SLAB_PATH_POINTS of them (a one-cup surrogate's design),
    else SLAB_PATH_POINTS slab solves.
    """
    C = tissue.n_cups
    rests = np.array([t.rest for t in tissue.scene.targets]).reshape(-1, 2)
    layer_answer = ControllerModel(ModelData("layer"), tissue).scene_map()
    model_answer = model.scene_map()
    grids, modelled, layered, slab_s, slab_y = [], [], [], [], []
    for c, cup in enumerate(cfg.cups):
        grid = np.linspace(cup.stroke_mm[0], cup.stroke_mm[1], PATH_POINTS)
        order = np.argsort(np.abs(grid), kind="stable")  # outwards from rest: tracked solves start close
        on_line = np.zeros(C)
        known_s, known_y = _samples_on_line(model.data, c)
        if known_s.size < SLAB_PATH_POINTS:
            known_s = np.linspace(cup.stroke_mm[0], cup.stroke_mm[1], SLAB_PATH_POINTS)
            known_y = np.empty((known_s.size, len(rests), 2))
            for k in np.argsort(np.abs(known_s), kind="stable"):
                on_line[:] = 0.0
                on_line[c] = known_s[k]
                known_y[k] = slab_answer(on_line)[0]
        lines = []
        for answer in (layer_answer, None if model.kind == "slab" else model_answer):
            if answer is None:  # the slab model is the slab: its line joins the slab's points (no 31 more 3-D solves)
                lines.append(np.stack([[np.interp(grid, known_s, known_y[:, t, a]) for a in range(2)]
                                       for t in range(len(rests))]).transpose(2, 0, 1))
                continue
            y = np.empty((grid.size, len(rests), 2))
            for k in order:
                on_line[:] = 0.0
                on_line[c] = grid[k]
                y[k] = answer(on_line)[0]
            lines.append(y)
        grids.append(grid)
        layered.append(lines[0])
        modelled.append(lines[1])
        slab_s.append(known_s)
        slab_y.append(known_y)
    return ModelPaths(model.kind, [c.name for c in cfg.cups], [t.name for t in cfg.targets], grids, modelled, layered,
                      slab_s, slab_y, rests)


def _samples_on_line(data: ModelData, cup: int) -> tuple[np.ndarray, np.ndarray]:
    """The model's slab samples with every other cup at rest: strokes (V,) of `cup`, in-plane targets (V, T, 2)."""
    sets = []
    if data.samples is not None:
        sets += [(data.samples.strokes, data.samples.targets), (data.samples.held_strokes, data.samples.held_targets)]
    if data.calibration is not None:
        sets.append((data.calibration.strokes, data.calibration.targets))
    strokes = [s[np.all(np.delete(s, cup, axis=1) == 0.0, axis=1)] for s, _ in sets]
    targets = [y[np.all(np.delete(s, cup, axis=1) == 0.0, axis=1), :, :2] for s, y in sets]
    if not sets or not sum(len(s) for s in strokes):
        return np.zeros(0), np.zeros((0, 0, 2))
    s, y = np.concatenate([s[:, cup] for s in strokes]), np.concatenate(targets)
    order = np.argsort(s)
    return s[order], y[order]
