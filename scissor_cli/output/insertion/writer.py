"""The figures of one target's insertions: force against depth, the target's path, the GIF (docs/contract.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scissor_cli.mesh.outlines import deformed_outlines, embed_outlines
from scissor_cli.mesh.probe import probe_targets, target_positions
from scissor_cli.output.insertion.figures import (
    insertion_animation,
    needle_force_figure,
    pick_frames,
    save,
    target_path_figure,
)


def insertion_outputs(ins, out_dir: Path) -> list[Path]:
    """insertion_force_<target>.png, insertion_path_<target>.png and, with `ins.animate`, insertion_<target>.gif."""
    name = ins.tissue.scene.name
    done = [r for r in ins.results if r.steps]
    paths = [
        save(needle_force_figure(f"{name} — {ins.target}: axial needle force", done),
             out_dir / f"insertion_force_{ins.target}.png"),
        save(target_path_figure(f"{name} — {ins.target}: target during insertion", done, ins.desired,
                                across=ins.tissue.dim == 3 and ins.layer is None),  # a body's: across its needle
             out_dir / f"insertion_path_{ins.target}.png"),
    ]
    if ins.animate and done:
        paths.append(_animation(ins, done[-1], out_dir / f"insertion_{ins.target}.gif"))
    return paths


def _animation(ins, r, path: Path) -> Path:
    """Manipulation (the cups ramping to the plan) then insertion under strategy r.strategy, in the layer's plane."""
    tissue = ins.tissue
    mesh = tissue.mesh
    probe = probe_targets(mesh, np.asarray(ins.target_rest, float)[None])
    emb = embed_outlines(mesh, [o.outline for o in tissue.scene.obstacles])
    frames, targets, needles, labels = [], [], [], []
    for k, x in enumerate(ins.manipulation_frames):
        frames.append(x)
        targets.append(target_positions(probe, x)[0])
        needles.append(None)
        labels.append(f"manipulation {k + 1}/{len(ins.manipulation_frames)}")
    for k in pick_frames(r.steps):
        if ins.layer is None:
            x = mesh.nodes + r.displacement[k]
        else:  # in the slab: the layer's level, in its plane
            x = mesh.nodes + ins.layer.positions(r.displacement[k])[:, :2]
        frames.append(x)
        targets.append(r.target[k][:2])
        needles.append(np.array([r.entry[:2], r.tip[k][:2]]))
        labels.append(f"insertion ({r.strategy}): depth {r.depth_mm[k]:.1f} mm, force {r.needle_force_mN[k]:.0f} mN")
    obstacles = [deformed_outlines(emb, x) for x in frames]
    return insertion_animation(path, f"{tissue.scene.name} — {ins.target}", mesh.triangles, frames, targets,
                               needles, labels, obstacles)
