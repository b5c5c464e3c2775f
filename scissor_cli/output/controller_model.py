"""/controller_model in results.h5 and its figure: the model's predicted target path against the slab's (docs/model.md §15)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from scissor_cli.layer3d.calibration import Calibration
from scissor_cli.layer3d.controller_model import ModelData, ModelPaths
from scissor_cli.layer3d.surrogate import SurrogateSamples

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


def _samples(g, name: str, strokes: np.ndarray, targets: np.ndarray, target_names: list[str]) -> None:
    s = g.create_group(name)
    s.create_dataset("strokes", data=np.asarray(strokes, float))
    t = s.create_group("targets")
    for k, target in enumerate(target_names):
        t.create_dataset(target, data=np.asarray(targets[:, k], float))


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
        surrogate = SurrogateSamples(strokes, targets, held_strokes, held_targets, np.asarray(a["stroke_min_mm"], float),
                                     np.asarray(a["stroke_max_mm"], float), float(a["build_time_s"]))
    return ModelData(str(a["kind"]), float(a["build_time_s"]), error, calibration, surrogate)


def controller_model_figure(paths: ModelPaths, title: str):
    """One column per cup, rows: each target's x and y motion from rest against the stroke — layer, model, slab."""
    import matplotlib.pyplot as plt  # noqa: PLC0415

    C, T = len(paths.cup_names), len(paths.target_names)
    fig, axes = plt.subplots(2, max(C, 1), figsize=(5.0 * max(C, 1), 6.5), squeeze=False, sharex="col")
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for c in range(C):
        for row, axis_name in enumerate("xy"):
            ax = axes[row, c]
            for t in range(T):
                colour = colours[t % len(colours)]
                rest = 0.0 if paths.rest is None else paths.rest[t, row]
                ax.plot(paths.strokes[c], paths.layer[c][:, t, row] - rest, "--", color=colour, alpha=0.5, lw=1)
                ax.plot(paths.strokes[c], paths.model[c][:, t, row] - rest, "-", color=colour, lw=1.5,
                        label=f"{paths.target_names[t]}: {paths.kind}")
                ax.plot(paths.slab_strokes[c], paths.slab[c][:, t, row] - rest, "o", color=colour, ms=4,
                        label=f"{paths.target_names[t]}: slab")
            ax.set_ylabel(f"target {axis_name} motion from rest (mm)")
            ax.grid(alpha=0.3)
        axes[1, c].set_xlabel(f"stroke of {paths.cup_names[c]} (mm), other cups at rest")
    axes[0, 0].plot([], [], "--", color="grey", label="layer (dashed)")
    axes[0, 0].legend(fontsize=7, ncol=2)
    fig.suptitle(f"{title}: the {paths.kind} model's target path against the nominal slab's")
    fig.tight_layout()
    return fig


def save_controller_model_figure(paths: ModelPaths, title: str, location: Path) -> Path:
    from scissor_cli.output import figures  # noqa: PLC0415

    return figures.save(controller_model_figure(paths, title), Path(location) / "controller_model.png")
