"""workspace.h5 and workspace.png of `scissor workspace` (docs/contract.md)."""

from __future__ import annotations

import json
import os
from typing import Optional

import numpy as np

from scissor_cli.robot.workspace import WorkspaceResult


def _attr_value(v):
    """h5py-storable attribute value (None → skipped by the caller)."""
    if isinstance(v, (str, bytes, int, float, bool, np.generic, np.ndarray)):
        return v
    if isinstance(v, (list, tuple)) and all(isinstance(x, (int, float, np.generic)) for x in v):
        return np.asarray(v)
    return json.dumps(v, default=str)


def write_workspace_h5(path, result: WorkspaceResult, attrs: Optional[dict] = None) -> None:
    """workspace.h5 of docs/contract.md: /workspace/{joints, tip, axis} and the box
    and coverage attributes; `attrs` (provenance) go on the root. Written to
    path + ".tmp" and renamed, so a reader never sees a partial file."""
    import h5py

    path = os.fspath(path)
    tmp = path + ".tmp"
    cov, reach = result.coverage, result.reachable
    with h5py.File(tmp, "w") as f:
        for k, v in (attrs or {}).items():
            if v is not None:
                f.attrs[k] = _attr_value(v)
        g = f.create_group("workspace")
        d = g.create_dataset("joints", data=np.asarray(result.joints, dtype=np.float64))
        d.attrs["units"] = "mm, mm, mm, rad, mm"
        d.attrs["columns"] = ", ".join(result.joint_names)
        d = g.create_dataset("tip", data=np.asarray(result.tip, dtype=np.float64))
        d.attrs["units"] = "mm"
        d.attrs["frame"] = "robot base"
        d = g.create_dataset("axis", data=np.asarray(result.axis, dtype=np.float64))
        d.attrs["units"] = "1"
        d.attrs["meaning"] = "unit needle axis, the direction the needle travels"
        g.attrs["box_min"] = np.asarray(result.box_min, dtype=np.float64)
        g.attrs["box_max"] = np.asarray(result.box_max, dtype=np.float64)
        g.attrs["coverage"] = cov.coverage
        g.attrs["coverage_multi_direction"] = cov.coverage_multi_direction
        g.attrs["coverage_summary"] = cov.summary
        if reach is not None:
            g.attrs["coverage_reachable"] = reach.coverage
            g.attrs["coverage_multi_direction_reachable"] = reach.coverage_multi_direction
            g.attrs["coverage_reachable_summary"] = reach.summary
        g.attrs["min_directions"] = cov.min_directions
        g.attrs["direction_bin_deg"] = cov.direction_bin_deg
        g.attrs["voxel_mm"] = result.voxel_mm
        g.attrs["voxel_size_mm"] = cov.grid.size
        g.attrs["samples"] = result.samples
        g.attrs["seed"] = result.seed
        g.attrs["method"] = result.method
    os.replace(tmp, path)


def plot_workspace(result: WorkspaceResult, path) -> None:
    """Fig. 8: xoz and xoy projections of the tip cloud (a 2-D histogram,
    log density) with the breast box outlined; voxel columns the robot cannot
    reach (IK-based) are shaded orange."""
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    tip = result.tip
    fig = Figure(figsize=(12, 5.5), layout="constrained")
    panels = [((0, 2), "xoz projection", "z (mm)"), ((0, 1), "xoy projection", "y (mm)")]
    for k, ((i, j), title, ylabel) in enumerate(panels):
        ax = fig.add_subplot(1, 2, k + 1)
        lo = np.minimum(tip[:, [i, j]].min(axis=0), result.box_min[[i, j]]) - 10
        hi = np.maximum(tip[:, [i, j]].max(axis=0), result.box_max[[i, j]]) + 10
        H, xe, ye = np.histogram2d(tip[:, i], tip[:, j], bins=(220, 220), range=[[lo[0], hi[0]], [lo[1], hi[1]]])
        H = np.ma.masked_equal(H.T, 0)
        if H.count():
            im = ax.imshow(H, origin="lower", extent=(xe[0], xe[-1], ye[0], ye[-1]), cmap="Blues",
                           norm=LogNorm(vmin=1, vmax=max(H.max(), 2)), interpolation="nearest", aspect="equal")
            fig.colorbar(im, ax=ax, shrink=0.8, label="tips per bin")
        reach = result.reachable
        if reach is not None and reach.coverage < 1:
            # missed footprint: voxel columns with any unreachable centre
            missed = ~(reach.hits > 0)
            other = 3 - i - j
            foot = missed.any(axis=other)  # indexed by (i, j) in axis order
            g = reach.grid
            ax.imshow(np.ma.masked_equal(foot.T.astype(float), 0), origin="lower", cmap="autumn", alpha=0.45,
                      extent=(g.box_min[i], g.box_max[i], g.box_min[j], g.box_max[j]), aspect="equal",
                      interpolation="nearest", vmin=0, vmax=1)
            ax.add_patch(Rectangle((np.nan, np.nan), 0, 0, color="yellow", alpha=0.6,
                                   label="unreachable voxels (IK)"))  # legend proxy
        ax.add_patch(Rectangle(result.box_min[[i, j]], *(result.box_max - result.box_min)[[i, j]],
                               fill=False, edgecolor="red", linewidth=1.8, label="breast box"))
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.legend(loc="upper right", fontsize=8)
    cov = result.coverage
    text = (f"Puncture-module workspace, {result.samples:,} samples — box coverage {cov.coverage:.1%} sampled"
            f" ({cov.coverage_multi_direction:.1%} from ≥{cov.min_directions} directions)")
    if result.reachable is not None:
        text += (f", {result.reachable.coverage:.1%} reachable by IK"
                 f" ({result.reachable.coverage_multi_direction:.1%} ≥{cov.min_directions} directions)")
    fig.suptitle(text, fontsize=10)
    fig.savefig(os.fspath(path), dpi=120)
