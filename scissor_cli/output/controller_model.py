"""/controller_model in results.h5 and its figure: the model's predicted target path against the slab's
(docs/model.md §15)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import h5py
import numpy as np

from scissor_cli.insertion.steering import NeedleModel
from scissor_cli.layer3d.calibration import Calibration
from scissor_cli.layer3d.surrogate import SurrogateSamples
from scissor_cli.layer3d.tissue_models import ModelData, ModelPaths

GROUP = "controller_model"


def write_controller_model(h5, data: ModelData, target_names: list[str], jacobian_update: str) -> None:
    """/controller_model: attrs, and the slab samples it was fitted to (per target (S, 3) mm)."""
    if GROUP in h5:
        del h5[GROUP]
    g = h5.create_group(GROUP)
    g.attrs.update({
        "kind": data.kind, "build_time_s": float(data.build_time_s), "jacobian_update": jacobian_update,
        "validation_error_mm": float("nan") if data.validation_error_mm is None else float(data.validation_error_mm),
    })
    if data.calibration is not None:
        g.attrs["transmission"] = data.calibration.transmission
        _samples(g, "samples", data.calibration.strokes, data.calibration.targets, target_names)
    if data.samples is not None:
        s = data.samples
        g.attrs.update({"stroke_min_mm": s.lo, "stroke_max_mm": s.hi})
        _samples(g, "samples", s.strokes, s.targets, target_names)
        _samples(g, "held_out", s.held_strokes, s.held_targets, target_names)
    for target, model in (data.needle or {}).items():
        n = g.require_group("needle").create_group(target)
        for name, values, unit in (("depth_mm", model.depth_mm, "mm"), ("target", model.target_mm, "mm"),
                                   ("jacobian", model.jacobian, "mm/mm")):
            n.create_dataset(name, data=np.asarray(values, float)).attrs["units"] = unit
        n.attrs.update({"entry_height_mm": model.entry_height_mm, "steered_height_mm": model.steered_height_mm,
                        "end_height_mm": model.end_height_mm})


def _samples(g, name: str, strokes: np.ndarray, targets: np.ndarray, target_names: list[str]) -> None:
    s = g.create_group(name)
    s.create_dataset("strokes", data=np.asarray(strokes, float))
    t = s.create_group("targets")
    for k, target in enumerate(target_names):
        t.create_dataset(target, data=np.asarray(targets[:, k], float))


def write_paths(h5, paths: ModelPaths) -> None:
    """/controller_model/paths/<cup>: the figure's lines (`ModelPaths`), so `report` can draw several models at once."""
    g = h5[GROUP].require_group("paths")
    g.attrs.update({"kind": paths.kind, "targets": np.array(paths.target_names, dtype="S"), "units": "mm"})
    if paths.rest is not None:
        g.attrs["rest"] = np.asarray(paths.rest, float)
    for c, cup in enumerate(paths.cup_names):
        if cup in g:
            del g[cup]
        line = g.create_group(cup)
        for name, values in (("strokes", paths.strokes[c]), ("model", paths.model[c]), ("layer", paths.layer[c]),
                             ("slab_strokes", paths.slab_strokes[c]), ("slab", paths.slab[c])):
            line.create_dataset(name, data=np.asarray(values, float))


def read_paths(h5) -> Optional[ModelPaths]:
    """The `ModelPaths` a run stored (/controller_model/paths), or None (a layer model, or a run before they were)."""
    if GROUP not in h5 or "paths" not in h5[GROUP]:
        return None
    g = h5[GROUP]["paths"]
    cups = list(g.keys())
    lines = {name: [g[c][name][()] for c in cups] for name in ("strokes", "model", "layer", "slab_strokes", "slab")}
    rest = np.asarray(g.attrs["rest"], float) if "rest" in g.attrs else None
    names = [t.decode() if isinstance(t, bytes) else str(t) for t in g.attrs["targets"]]
    return ModelPaths(str(g.attrs["kind"]), cups, names, lines["strokes"], lines["model"], lines["layer"],
                      lines["slab_strokes"], lines["slab"], rest)


def read_controller_model(h5, target_names: list[str]) -> Optional[ModelData]:
    """The ModelData a run stored (for a resume), or None when it has none."""
    if GROUP not in h5:
        return None
    g = h5[GROUP]
    a = g.attrs
    error = float(a["validation_error_mm"])
    error = None if np.isnan(error) else error

    def samples(name):
        s = g[name]
        return s["strokes"][()], np.stack([s["targets"][t][()] for t in target_names], axis=1)

    calibration = surrogate = None
    if "transmission" in a:
        strokes, targets = samples("samples")
        calibration = Calibration(np.asarray(a["transmission"], float), strokes, targets, error)
    elif "samples" in g:
        strokes, targets = samples("samples")
        held_strokes, held_targets = samples("held_out")
        surrogate = SurrogateSamples(strokes, targets, held_strokes, held_targets,
                                     np.asarray(a["stroke_min_mm"], float), np.asarray(a["stroke_max_mm"], float),
                                     float(a["build_time_s"]))
    needle = None
    if "needle" in g:
        needle = {t: NeedleModel(n["depth_mm"][()], n["target"][()], n["jacobian"][()],
                                 float(n.attrs["entry_height_mm"]), float(n.attrs["steered_height_mm"]))
                  for t, n in g["needle"].items()}
    return ModelData(str(a["kind"]), float(a["build_time_s"]), error, calibration, surrogate, needle)


def save_controller_model_figure(paths: ModelPaths, title: str, location: Path) -> Path:
    from scissor_cli.output import figures  # noqa: PLC0415

    return figures.save(controller_models_figure([paths], title), Path(location) / "controller_model.png")


MODEL_STYLES = {"calibrated": ("tab:orange", "-."), "surrogate": ("tab:blue", "-"), "slab": ("tab:green", ":")}


def controller_models_figure(paths: list[ModelPaths], title: str):
    """Every model's target path against the nominal slab's (the slab's points) and the layer's (dashed), one
    column per cup and target, rows: x and y motion from rest. paths: one `ModelPaths` per model kind, all of
    the same scene (one: a run's own `controller_model.png`)."""
    import matplotlib.pyplot as plt  # noqa: PLC0415

    first = paths[0]
    columns = [(c, t) for c in range(len(first.cup_names)) for t in range(len(first.target_names))]
    fig, axes = plt.subplots(2, len(columns), figsize=(3.6 * len(columns), 6.0), squeeze=False, sharex="col")
    for k, (c, t) in enumerate(columns):
        for row, axis_name in enumerate("xy"):
            ax = axes[row, k]
            rest = 0.0 if first.rest is None else first.rest[t, row]
            ax.plot(first.slab_strokes[c], first.slab[c][:, t, row] - rest, "o", color="black", ms=3.5,
                    label="nominal slab", zorder=3)
            ax.plot(first.strokes[c], first.layer[c][:, t, row] - rest, "--", color="grey", lw=1.2, label="layer")
            for p in paths:
                colour, style = MODEL_STYLES.get(p.kind, ("tab:red", "-"))
                ax.plot(p.strokes[c], p.model[c][:, t, row] - rest, style, color=colour, lw=1.5, label=p.kind)
            ax.grid(alpha=0.3)
            if k == 0:
                ax.set_ylabel(f"target {axis_name} motion from rest (mm)")
        axes[0, k].set_title(f"{first.target_names[t]}", fontsize=10)
        axes[1, k].set_xlabel(f"stroke of {first.cup_names[c]} (mm)")
    axes[0, 0].legend(fontsize=7)
    whose = f"the {first.kind} model's" if len(paths) == 1 else "each controller model's"
    fig.suptitle(f"{title}: {whose} target path against the nominal slab's")
    fig.tight_layout()
    return fig


def report_models_figure(runs: list[tuple[str, Path]], out_dir: Path) -> list[Path]:
    """controller_models.png of the runs that stored their model's paths, one model kind each (the first run of a
    kind; +Broyden runs share their model), grouped by scene; [] when none did."""
    from scissor_cli.output import figures  # noqa: PLC0415

    scenes: dict[str, dict[str, ModelPaths]] = {}
    for label, path in runs:
        with h5py.File(path, "r") as f:
            paths = read_paths(f)
        if paths is not None:
            scene = label.split(" (")[0]
            scenes.setdefault(scene, {}).setdefault(paths.kind, paths)
    files = []
    if scenes:
        out_dir.mkdir(parents=True, exist_ok=True)
    for k, (scene, kinds) in enumerate(scenes.items()):
        name = "controller_models.png" if len(scenes) == 1 else f"controller_models_{k + 1}.png"
        files.append(figures.save(controller_models_figure(list(kinds.values()), scene), out_dir / name))
    return files
