"""The manipulation-point plan in a run: `/manipulation_points/<target>` and the response figure (docs/contract.md).

Per target, a table of every candidate (contact point, inward normal, the
predicted target response per unit force and per mm of stroke, the score)
with attrs `chosen` (cups, 2), `predicted` (2,) and `verified` (2,): the
target motion at the test stroke predicted by the adjoint response and
found by the full nonlinear solve with the cup gripping at the chosen point.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from scissor_cli.output.results import FILL, ResultsFile

COLUMNS = ["contact_x", "contact_y", "normal_x", "normal_y", "response_x", "response_y",
           "per_stroke_x", "per_stroke_y", "score"]


def write_manipulation_points(out: ResultsFile, plan) -> None:
    """/manipulation_points/<target> for every target of a `planning.manipulation_points.GripPlan`."""
    c = plan.candidates
    out.attrs("manipulation_points", {
        "search_s": plan.search_s, "verify_s": plan.verify_s, "candidates": len(c),
        "chosen": plan.contacts, "axes": plan.axes, "test_stroke_mm": plan.test_strokes,
        "notes": "; ".join(plan.notes) or "none",
    })
    for tr in plan.targets:
        table = np.column_stack([c.points, c.normals, tr.response, tr.per_stroke, tr.score]).astype(np.float64)
        out.dataset(f"manipulation_points/{tr.target}", table, "mm, mm/mN, mm/mm", columns=COLUMNS,
                    chosen=np.asarray(tr.chosen, float), predicted=_finite(tr.predicted),
                    verified=_finite(tr.verified), needle_axis=tr.axis, miss_direction=tr.miss_direction,
                    description="candidate grips: contact point, inward normal, target response per mN and "
                                "per mm of stroke, score = |miss component| per mm of stroke")


def _finite(v) -> np.ndarray:
    v = np.asarray(v, float)
    return np.where(np.isfinite(v), v, FILL)


def grip_figure(plan, outline: np.ndarray, obstacles: list[tuple[str, np.ndarray]],
                targets: dict[str, np.ndarray], title: str) -> Figure:
    """Left: the layer with the candidates coloured by the scene's score and the chosen grip(s);
    right: each target's score (mm of miss per mm of stroke) along the boundary (arc length)."""
    c = plan.candidates
    fig = Figure(figsize=(12.5, 4.6), layout="constrained")  # keeps the colour bar's label off the right panel
    ax, bx = fig.subplots(1, 2)
    closed = np.vstack([outline, outline[:1]])
    ax.plot(closed[:, 0], closed[:, 1], "k-", lw=1)
    for name, poly in obstacles:
        p = np.vstack([poly, poly[:1]])
        ax.fill(p[:, 0], p[:, 1], color="tab:red", alpha=0.3)
        ax.annotate(name, p.mean(axis=0), fontsize=8, ha="center")
    total = np.zeros(len(c))
    for tr in plan.targets:
        total += tr.score / max(tr.score.max(), 1e-300)
    sc = ax.scatter(c.points[:, 0], c.points[:, 1], c=total, cmap="viridis", s=18, zorder=3)
    fig.colorbar(sc, ax=ax, label="score (sum over targets of score / best)")
    for p, n in zip(plan.contacts, plan.axes):
        ax.annotate("", p + 6 * n, p, arrowprops=dict(arrowstyle="->", color="tab:orange", lw=2))
        ax.plot(*p, "o", ms=10, mfc="none", mec="tab:orange", mew=2, label="chosen grip")
    for name, y in targets.items():
        ax.plot(*y, "k+", ms=9)
        ax.annotate(name, y, xytext=(3, 3), textcoords="offset points", fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(title)
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(handles[:1], labels[:1], loc="lower right", fontsize=8)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c.points, axis=0), axis=1))])
    for tr in plan.targets:
        bx.plot(arc, tr.score, "-", label=tr.target)
    for k in plan.chosen:
        bx.axvline(arc[k], color="tab:orange", ls="--")
    # the candidates run the boundary's way (counter-clockwise), so say where the distance starts
    start = ", ".join(f"{v:.0f}" for v in c.points[0])
    bx.set_xlabel(f"candidate: distance along the accessible boundary from ({start}) (mm)")
    bx.set_ylabel("miss motion per stroke (mm/mm)")
    bx.set_title("response across the needle, by adjoint solves")
    if plan.targets:
        bx.legend(fontsize=8)
    return fig


def save_grip_figure(plan, scene, directory: Path) -> Path:
    from scissor_cli.output.figures import save  # noqa: PLC0415

    fig = grip_figure(plan, scene.outline, [(o.name, o.outline) for o in scene.obstacles],
                      {t.name: t.rest for t in scene.targets}, f"{len(plan.candidates)} candidate grips")
    return save(fig, Path(directory) / "manipulation_points.png")
