"""The grips chosen over a body's skin in a run: `/manipulation_points` and its figure (docs/contract.md, 3-D scenes).

Per lesion, a table of every candidate (contact point on the skin, inward
normal, the lesion's motion per mm of stroke, the candidate's score as a
single cup) with attrs `predicted` and `verified` (N, 3): each chosen cup's
motion of the lesion at its test stroke, predicted by the adjoint response
and found by the full nonlinear solve on the re-meshed body.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from scissor_cli.output.figures import save
from scissor_cli.output.results import ResultsFile

COLUMNS = ["contact_x", "contact_y", "contact_z", "normal_x", "normal_y", "normal_z",
           "per_stroke_x", "per_stroke_y", "per_stroke_z", "score"]


def write_body_grips(out: ResultsFile, plan) -> None:
    """/manipulation_points and /manipulation_points/<lesion> of a `planning.body_grips.BodyGripPlan`."""
    c = plan.candidates
    out.attrs("manipulation_points", {
        "search_s": plan.search_s, "verify_s": plan.verify_s, "candidates": len(c), "chosen": plan.contacts,
        "axes": plan.axes, "test_stroke_mm": plan.test_strokes, "score": plan.score, "controls": plan.controls,
        "notes": "none"})
    for t, name in enumerate(plan.targets):
        table = np.column_stack([c.points, c.normals, plan.per_stroke[t], plan.single_score]).astype(np.float64)
        out.dataset(f"manipulation_points/{name}", table, "mm, mm/mm", columns=COLUMNS,
                    chosen=plan.contacts, predicted=plan.predicted[:, t], verified=plan.verified[:, t],
                    needle_axis=plan.axes_needle[t],
                    description="candidate grips on the skin: contact point, inward normal, the lesion's motion "
                                "per mm of stroke (adjoint), score as a single cup (relative to the best)")


def body_grips_figure(plan, tissue, title: str) -> Figure:
    """Left: the skin with the candidates coloured by their score as a single cup, the chosen patches and their
    push; right: each chosen cup's motion of every lesion at its test stroke, predicted against solved."""
    mesh, c = tissue.mesh, plan.candidates
    fig = Figure(figsize=(12.5, 5.2), layout="constrained")
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    skin = mesh.boundary_triangles[~mesh.boundary_base]
    ax.add_collection3d(Poly3DCollection(mesh.nodes[skin], facecolors="#f2d4c4", edgecolors="none", alpha=0.15))
    dots = ax.scatter(*c.points.T, c=plan.single_score, cmap="viridis", s=14, depthshade=False)
    fig.colorbar(dots, ax=ax, shrink=0.6, label="score as a single cup (relative)")
    for k, (p, a) in enumerate(zip(plan.contacts, plan.axes)):
        ax.scatter(*p, s=80, facecolors="none", edgecolors="k", linewidths=1.5, label="chosen" if k == 0 else None)
        ax.quiver(*(p - 12.0 * a), *(10.0 * a), color="k", arrow_length_ratio=0.3)
    for t in tissue.scene.targets:
        ax.scatter(*t.rest, s=30, color="tab:red", marker="*", label="lesion" if t is tissue.scene.targets[0] else None)
    lo, hi = mesh.nodes.min(axis=0), mesh.nodes.max(axis=0)
    ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-6)))
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.legend(loc="upper left", fontsize=7)
    ax.set_title(f"{len(c)} candidates; {len(plan.chosen)} chosen for {plan.controls}", fontsize=9)
    bx = fig.add_subplot(1, 2, 2)
    labels, width = [f"cup {k + 1}\n{name}" for k in range(len(plan.chosen)) for name in plan.targets], 0.38
    pred = np.linalg.norm(plan.predicted, axis=2).ravel()
    solved = np.linalg.norm(plan.verified, axis=2).ravel()
    x = np.arange(len(labels))
    bx.bar(x - width / 2, pred, width, label="predicted (adjoint, linear)")
    bx.bar(x + width / 2, solved, width, label="solved (re-meshed body)")
    bx.set_xticks(x, labels, fontsize=7)
    bx.set_ylabel("lesion motion at the test stroke (mm)")
    bx.legend(fontsize=8, loc="upper right")
    bx.set_title("each chosen cup at half its largest stroke", fontsize=9)
    fig.suptitle(title, fontsize=10)
    return fig


def save_body_grips_figure(plan, tissue, directory: Path) -> Path:
    return save(body_grips_figure(plan, tissue, f"{tissue.scene.name}: where the cups grip"),
                Path(directory) / "manipulation_points.png")
