"""Figures written by the commands (matplotlib, Agg; no display needed).

Every figure is built on a `matplotlib.figure.Figure` directly, so nothing
here touches pyplot's global state and figures can be made from worker
processes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Polygon
from matplotlib.ticker import NullFormatter

TISSUE = "#f3d9c9"
OBSTACLE = "#3b6fd8"


def save(fig: Figure, path: Path | str) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=130, bbox_inches="tight")
    return Path(path)


def _mesh_lines(ax, nodes: np.ndarray, triangles: np.ndarray, **kw) -> None:
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    ax.add_collection(LineCollection(nodes[edges], **kw))


def _outline(ax, poly: np.ndarray, **kw) -> None:
    ax.add_patch(Polygon(poly, closed=True, **kw))


def forward_case_figure(
    title: str,
    rest: np.ndarray,
    deformed: np.ndarray,
    triangles: np.ndarray,
    outline_rest: np.ndarray,
    outline_deformed: np.ndarray,
    obstacles_rest: list[tuple[str, np.ndarray]],
    obstacles_deformed: list[np.ndarray],
    targets_rest: dict[str, np.ndarray],
    targets_deformed: dict[str, np.ndarray],
    cup_nodes: list[np.ndarray],
    fixed_nodes: np.ndarray,
) -> Figure:
    """The deformed mesh of a forward case with obstacles and targets before and after (mm)."""
    fig = Figure(figsize=(8, 5.2))
    ax = fig.add_subplot(1, 1, 1)
    _outline(ax, outline_rest, fill=False, ls="--", lw=0.8, ec="0.5", label="tissue at rest")
    _outline(ax, outline_deformed, fc=TISSUE, ec="0.3", lw=0.8, zorder=0)
    _mesh_lines(ax, deformed, triangles, colors="0.55", linewidths=0.25, zorder=1)
    for k, ((name, poly), poly_def) in enumerate(zip(obstacles_rest, obstacles_deformed)):
        _outline(ax, poly, fill=False, ls="--", ec=OBSTACLE, lw=0.9, zorder=2,
                 label="obstacle at rest" if k == 0 else None)
        _outline(ax, poly_def, fc=OBSTACLE, alpha=0.45, ec=OBSTACLE, zorder=2,
                 label="obstacle deformed" if k == 0 else None)
        ax.annotate(name, poly_def.mean(axis=0), fontsize=7, ha="center", va="center", zorder=5)
    for k, name in enumerate(targets_rest):
        r, d = targets_rest[name], targets_deformed[name]
        ax.plot(*r, "o", color="red", ms=5, zorder=4, label="target at rest" if k == 0 else None)
        ax.plot(*d, "o", color="green", ms=5, zorder=4, label="target deformed" if k == 0 else None)
        ax.annotate("", d, r, arrowprops={"arrowstyle": "->", "color": "k", "lw": 0.8}, zorder=4)
        ax.annotate(name, d, textcoords="offset points", xytext=(4, 4), fontsize=8, zorder=5)
    for k, nodes in enumerate(cup_nodes):
        ax.plot(*deformed[nodes].T, "s", color="purple", ms=3, zorder=3, label="cup grip" if k == 0 else None)
    ax.plot(*rest[fixed_nodes].T, "^", color="k", ms=2.5, zorder=3, label="fixed")
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    return fig


CORRIDOR_BEFORE = "#8e44ad"  # the paper's purple needle path before manipulation
CORRIDOR_AFTER = "0.35"  # and its grey one after


def _corridor_band(entry: np.ndarray, end: np.ndarray, radius: float) -> np.ndarray:
    """The corridor entry → end dilated by radius, as a rectangle (4, 2) mm."""
    d = np.asarray(end, float) - np.asarray(entry, float)
    n = np.array([-d[1], d[0]]) / max(float(np.linalg.norm(d)), 1e-12) * radius
    return np.array([entry + n, end + n, end - n, entry - n])


def _corridor(ax, segment, radius: float, color, label: str) -> None:
    if segment is None or not np.all(np.isfinite(np.asarray(segment, float))):
        return
    entry, end = np.asarray(segment, float)
    _outline(ax, _corridor_band(entry, end, radius), fc=color, ec=color, alpha=0.3, lw=0.8, zorder=3, label=label)
    ax.plot(*np.array([entry, end]).T, color=color, lw=0.8, ls="-.", zorder=3)


@dataclass(frozen=True)
class ManipulationDrawing:
    """What the paper's Fig. 11 draws of one target's manipulation (mm).

    Before: the rest tissue (`rest` (N, 2), `outline_rest`), the obstacles
    at rest (`obstacles_rest`: (name, outline)), the needle corridor through
    the rest target (`corridor_before` = [entry, target] (2, 2)) and the rest
    target. After: the deformed tissue (`deformed`, `outline_deformed`), the
    deformed obstacles (their rest outlines dashed), the corridor through the
    reached target (`corridor_after`), the reached target and the desired
    position. Corridors are drawn corridor_radius_mm wide on each side; a
    None or NaN corridor is left out.
    """

    title: str
    triangles: np.ndarray
    rest: np.ndarray
    deformed: np.ndarray
    outline_rest: np.ndarray
    outline_deformed: np.ndarray
    obstacles_rest: list[tuple[str, np.ndarray]]
    obstacles_deformed: list[np.ndarray]
    target_rest: np.ndarray
    target_reached: np.ndarray
    desired: np.ndarray
    corridor_radius_mm: float
    corridor_before: np.ndarray | None = None
    corridor_after: np.ndarray | None = None
    cup_nodes: list[np.ndarray] | None = None
    subtitles: tuple[str, str] = ("before manipulation", "after manipulation")


def manipulation_figure(d: ManipulationDrawing) -> Figure:
    """The paper's Fig. 11 for one target: the scene before | after manipulation (`ManipulationDrawing`)."""
    fig = Figure(figsize=(12, 4.6))
    axes = fig.subplots(1, 2, sharex=True, sharey=True)
    states = [
        (axes[0], d.rest, d.outline_rest, [p for _, p in d.obstacles_rest], d.corridor_before, CORRIDOR_BEFORE,
         "needle corridor before", d.target_rest, "red", "target at rest"),
        (axes[1], d.deformed, d.outline_deformed, d.obstacles_deformed, d.corridor_after, CORRIDOR_AFTER,
         "needle corridor after", d.target_reached, "green", "target reached"),
    ]
    for ax, nodes, outline, obstacles, corridor, c_color, c_label, target, t_color, t_label in states:
        _outline(ax, outline, fc=TISSUE, ec="0.3", lw=0.8, zorder=0)
        _mesh_lines(ax, nodes, d.triangles, colors="0.6", linewidths=0.2, zorder=1)
        for k, ((name, _), poly) in enumerate(zip(d.obstacles_rest, obstacles)):
            _outline(ax, poly, fc=OBSTACLE, alpha=0.45, ec=OBSTACLE, lw=0.8, zorder=2,
                     label="vessel / nerve" if k == 0 else None)
            ax.annotate(name, np.asarray(poly).mean(axis=0), fontsize=7, ha="center", va="center", zorder=6)
        _corridor(ax, corridor, d.corridor_radius_mm, c_color, c_label)
        if d.cup_nodes:
            for k, cn in enumerate(d.cup_nodes):
                ax.plot(*nodes[cn].T, "s", color="purple", ms=2.5, zorder=4, label="cup grip" if k == 0 else None)
        ax.plot(*target, "o", color=t_color, ms=6, mec="k", mew=0.5, zorder=5, label=t_label)
    ax_after = axes[1]
    for k, (_, poly) in enumerate(d.obstacles_rest):
        _outline(ax_after, poly, fill=False, ls="--", ec=OBSTACLE, lw=0.7, zorder=2,
                 label="obstacle at rest" if k == 0 else None)
    ax_after.plot(*np.asarray(d.desired, float), "o", mfc="none", mec="k", ms=10, mew=1.2, zorder=5, label="desired")
    ax_after.plot(*np.asarray(d.target_rest, float), "o", color="red", ms=3, alpha=0.6, zorder=5)
    ax_after.annotate("", d.target_reached, d.target_rest, arrowprops={"arrowstyle": "->", "color": "k", "lw": 0.7},
                      zorder=5)
    for ax, sub in zip(axes, d.subtitles):
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_xlabel("x (mm)")
        ax.set_title(sub, fontsize=9)
    axes[0].set_ylabel("y (mm)")
    handles = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.legend(list(handles.values()), list(handles.keys()), loc="lower center", ncol=min(len(handles), 5),
               fontsize=8, frameon=False, bbox_to_anchor=(0.5, -0.02))
    fig.suptitle(d.title, fontsize=10)
    fig.subplots_adjust(bottom=0.2, wspace=0.08)
    return fig


def error_boxplots(panels: list[tuple[str, dict[str, np.ndarray]]]) -> Figure:
    """Box plots of the final error in x and y (and z in a body) per target, like the paper's Fig. 14.

    panels: [(title, {target: errors (T, d) mm})], one row of x|y(|z) axes per
    panel (e.g. prosthesis, ex vivo). Box 25–75 %, black median line, solid
    triangle at the mean, whiskers at the minimum and maximum.
    """
    width = max((np.asarray(e).shape[1] for _, errors in panels for e in errors.values()), default=2)
    axes = "xyz"[:width]  # x, y (and z in a body)
    fig = Figure(figsize=(4.5 * width, 3.4 * len(panels)))
    for row, (title, errors) in enumerate(panels):
        names = list(errors)
        for col, axis in enumerate(axes):
            ax = fig.add_subplot(len(panels), width, width * row + col + 1)
            data = [np.asarray(errors[n])[:, col] for n in names]
            data = [d[np.isfinite(d)] for d in data]
            ax.boxplot(
                data, whis=(0, 100), widths=0.5, patch_artist=True, showmeans=True,
                boxprops={"facecolor": "#9ec5e8", "edgecolor": "k"}, medianprops={"color": "k", "lw": 1.5},
                meanprops={"marker": "^", "markerfacecolor": "k", "markeredgecolor": "k", "markersize": 6},
            )
            ax.set_xticks(range(1, len(names) + 1), names)
            ax.axhline(0.0, color="0.6", lw=0.6, zorder=0)
            ax.set_ylabel(f"error in {axis.upper()} (mm)")
            worst = max((np.abs(d).max() for d in data if len(d)), default=0.0)
            ax.set_title(f"{title}: {axis.upper()} (max |e| {worst:.2f} mm)", fontsize=9)
    fig.tight_layout()
    return fig


def iterations_histogram(iterations: dict[str, np.ndarray], title: str) -> Figure:
    """Histogram of control iterations per trial, stacked by target."""
    fig = Figure(figsize=(6, 3.6))
    ax = fig.add_subplot(1, 1, 1)
    values = [np.asarray(v)[np.asarray(v) >= 0] for v in iterations.values()]
    top = max((int(v.max()) for v in values if len(v)), default=1)
    ax.hist(values, bins=np.arange(-0.5, top + 1.5), stacked=True, label=list(iterations), edgecolor="k", lw=0.4)
    ax.set_xlabel("control iterations")
    ax.set_ylabel("trials")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8, frameon=False)
    return fig


SOLVER_STYLE = {"newton": ("o", "-"), "admm": ("s", "--"), "admm+anderson": ("^", ":")}
MODEL_COLOUR = {"linear": "#2a9d8f", "neo_hookean": "#e9c46a", "neo_hookean_fiber": "#e76f51"}


def speed_error_figure(title: str, curves: dict[tuple[str, str, str], tuple[np.ndarray, np.ndarray]],
                       front: tuple[np.ndarray, np.ndarray]) -> Figure:
    """Log–log wall time against target error: one curve per (solver, model, mesh kind), Pareto front marked.

    curves[(solver, model, kind)] = (error_mm (K,), time_s (K,)); front = (error_mm, time_s).
    """
    fig = Figure(figsize=(8.5, 5.5))
    ax = fig.add_subplot(1, 1, 1)
    for (solver, model, kind), (err, t) in sorted(curves.items()):
        ok = np.isfinite(err) & np.isfinite(t) & (err > 0)
        if not ok.any():
            continue
        order = np.argsort(t[ok])
        marker, ls = SOLVER_STYLE.get(solver, ("x", "-"))
        ax.plot(err[ok][order], t[ok][order], marker=marker, ls=ls, color=MODEL_COLOUR.get(model, "k"),
                mfc="none" if kind == "uniform" else MODEL_COLOUR.get(model, "k"), ms=5, lw=1,
                label=f"{solver}, {model}, {kind}")
    if len(front[0]):
        ax.plot(front[0], front[1], "k-", lw=2.5, alpha=0.35, zorder=0, label="Pareto front")
    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis in (ax.xaxis, ax.yaxis):  # labelled decades only: minor labels overlap on short ranges
        axis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("target error against the reference (mm)")
    ax.set_ylabel("wall time (s)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", lw=0.3, alpha=0.5)
    ax.legend(fontsize=6.5, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return fig
