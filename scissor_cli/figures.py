"""Figures written by the commands (matplotlib, Agg; no display needed).

Every figure is built on a `matplotlib.figure.Figure` directly, so nothing
here touches pyplot's global state and figures can be made from worker
processes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Polygon

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
