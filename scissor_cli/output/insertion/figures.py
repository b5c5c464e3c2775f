"""Insertion figures (docs/contract.md, docs/model.md §12): force against depth, the target's path, a GIF.

Built on `matplotlib.figure.Figure` directly, like `output.figures`; the
animation uses `matplotlib.animation.FuncAnimation` with the Pillow writer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.animation import FuncAnimation, PillowWriter
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from scissor_cli.output.figures import OBSTACLE, TISSUE, save

COLORS = {"none": "#d1495b", "depth": "#edae49", "loop": "#00798c"}
#: the GIF keeps at most this many insertion frames (evenly spaced steps)
MAX_FRAMES = 40


def needle_force_figure(title: str, results: list) -> Figure:
    """Axial needle force (mN) against depth (mm) per strategy; stick–slip shows as a saw-tooth."""
    fig = Figure(figsize=(7, 4.2))
    ax = fig.add_subplot(1, 1, 1)
    for r in results:
        ax.plot(r.depth_mm, r.needle_force_mN, "-", lw=1.2, color=COLORS.get(r.strategy),
                label=f"{r.strategy} ({r.steps} steps)")
    ax.set_xlabel("depth (mm)")
    ax.set_ylabel("axial needle force (mN)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def target_path_figure(title: str, results: list, desired: np.ndarray, across: bool = False) -> Figure:
    """The true target's path during the insertion per strategy, with the needle line and the planned position.

    Drawn in the layer's plane: an insertion in the slab (target (K, 3))
    shows its in-plane part. across: a body's insertion, drawn in the plane
    across the needle through the planned position (the needle seen end-on
    at the origin: the distance from it is the miss).
    """
    if across and results:
        return _across_figure(title, results, desired)
    fig = Figure(figsize=(7, 4.6))
    ax = fig.add_subplot(1, 1, 1)
    desired = np.asarray(desired, float)[:2]
    paths = [np.asarray(r.target, float)[:, :2] for r in results]
    pts = [desired[None]] + [p for r, p in zip(results, paths) if r.steps]
    allp = np.vstack(pts)
    span = max(float(np.ptp(allp, axis=0).max()), 0.5)
    lo, hi = allp.min(0) - 0.3 * span, allp.max(0) + 0.3 * span
    if results:
        r0 = results[0]
        t = np.linspace(-5 * span, 5 * span, 2)
        line = desired[None] + t[:, None] * np.asarray(r0.direction, float)[None, :2]
        ax.plot(line[:, 0], line[:, 1], "-", color="0.6", lw=1, label="needle line")
    for r, path in zip(results, paths):
        if not r.steps:
            continue
        ax.plot(path[:, 0], path[:, 1], "-", color=COLORS.get(r.strategy), lw=1.3,
                label=f"{r.strategy}: miss {r.miss_mm:.2f} mm, depth error {r.depth_error_mm:+.2f} mm")
        ax.plot(*path[-1], "o", color=COLORS.get(r.strategy), ms=5)
    ax.plot(*desired, "k+", ms=10, label="planned (start of insertion)")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="best")
    return fig


def _across_figure(title: str, results: list, desired: np.ndarray) -> Figure:
    """`target_path_figure` of a body: the target in the plane across the needle, its axes `transverse_basis`."""
    from scissor_cli.insertion.needle import transverse_basis  # noqa: PLC0415

    fig = Figure(figsize=(6, 5.4))
    ax = fig.add_subplot(1, 1, 1)
    r0 = results[0]
    T = transverse_basis(np.asarray(r0.direction, float))
    line = np.asarray(r0.entry, float)
    origin = line + ((np.asarray(desired, float) - line) @ r0.direction) * np.asarray(r0.direction, float)
    ax.plot(0.0, 0.0, "x", color="0.4", ms=9, label="needle line (end-on)")
    for r in results:
        if not r.steps:
            continue
        q = (np.asarray(r.target, float) - origin) @ T.T
        ax.plot(q[:, 0], q[:, 1], "-", color=COLORS.get(r.strategy), lw=1.3,
                label=f"{r.strategy}: miss {r.miss_mm:.2f} mm, depth error {r.depth_error_mm:+.2f} mm")
        ax.plot(*q[-1], "o", color=COLORS.get(r.strategy), ms=5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"across the needle, along {np.round(T[0], 2).tolist()} (mm)")
    ax.set_ylabel(f"across, along {np.round(T[1], 2).tolist()} (mm)")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="best")
    return fig


def mesh_edges(triangles: np.ndarray) -> np.ndarray:
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def insertion_animation(path: Path | str, title: str, triangles: np.ndarray, frames: list[np.ndarray],
                        targets: list[np.ndarray], needles: list[np.ndarray | None], labels: list[str],
                        obstacles: list[list[np.ndarray]], fps: int = 8) -> Path:
    """A GIF: node positions per frame (N, 2), the target (2,), the needle segment (2, 2) or None, a caption.

    obstacles: the deformed obstacle outlines of each frame.
    """
    edges = mesh_edges(triangles)
    fig = Figure(figsize=(7, 4.6))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    allx = np.vstack(frames)
    pad = 3.0
    ax.set_xlim(allx[:, 0].min() - pad, allx[:, 0].max() + pad)
    ax.set_ylim(allx[:, 1].min() - pad, allx[:, 1].max() + pad)
    ax.set_aspect("equal")
    ax.set_facecolor(TISSUE)
    mesh = LineCollection(frames[0][edges], colors="0.45", linewidths=0.3)
    ax.add_collection(mesh)
    obstacle_lines = [ax.plot([], [], "-", color=OBSTACLE, lw=1.2)[0] for _ in obstacles[0]]
    needle, = ax.plot([], [], "-", color="k", lw=2.0)
    target, = ax.plot([], [], "o", color="#d1495b", ms=6)
    caption = ax.set_title(title, fontsize=9)

    def draw(k):
        mesh.set_segments(frames[k][edges])
        for line, poly in zip(obstacle_lines, obstacles[k]):
            closed = np.vstack([poly, poly[:1]])
            line.set_data(closed[:, 0], closed[:, 1])
        seg = needles[k]
        needle.set_data(([], []) if seg is None else (seg[:, 0], seg[:, 1]))
        target.set_data([targets[k][0]], [targets[k][1]])
        caption.set_text(f"{title}\n{labels[k]}")
        return [mesh, needle, target, caption, *obstacle_lines]

    anim = FuncAnimation(fig, draw, frames=len(frames), blit=False)
    anim.save(str(path), writer=PillowWriter(fps=fps), dpi=90)
    return Path(path)


def pick_frames(steps: int, most: int = MAX_FRAMES) -> np.ndarray:
    """Indices (≤ most,) of evenly spaced steps, the last one always in."""
    if steps <= most:
        return np.arange(steps)
    return np.unique(np.linspace(0, steps - 1, most).round().astype(int))


__all__ = ["needle_force_figure", "target_path_figure", "insertion_animation", "pick_frames", "save"]
