"""The arguments of the manipulation figure (the paper's Fig. 11) from one manipulation's result."""

from __future__ import annotations

from typing import Optional

import numpy as np

from scissor_cli.control.corridor_check import Corridor, corridor_at
from scissor_cli.control.result import LoopResult
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.outlines import boundary_loop, deformed_outlines, embed_outlines
from scissor_cli.output.figures import ManipulationDrawing


def manipulation_figure_inputs(tissue: Tissue, result: LoopResult, target_rest: np.ndarray,
                               corridor: Optional[Corridor] = None) -> ManipulationDrawing:
    """What `figures.manipulation_figure` draws of one manipulation.

    tissue: the truth the result was simulated on (its mesh and obstacles);
    the "before" corridor runs through the rest target along the planned
    direction on the rest scene, the "after" one through the reached true
    target on the final true state.
    """
    mesh, scene = tissue.mesh, tissue.scene
    loop = boundary_loop(mesh)
    x = result.final_x if result.final_x is not None else mesh.nodes
    obstacles = embed_outlines(mesh, [o.outline for o in scene.obstacles])
    target_rest = np.asarray(target_rest, float)
    before = after = None
    if corridor is not None:
        entry0, _ = corridor_at(tissue, mesh.nodes, target_rest, corridor, obstacles)
        before = np.array([entry0, target_rest])
        after = np.array([result.corridor_entry, result.final_position])
    clearance = "" if corridor is None else f", clearance {result.clearance_mm:.2f} mm"
    title = (
        f"{scene.name} — {result.target}: {result.mode} loop, {result.iterations} iterations ({result.stop_reason}), "
        f"final error ({result.final_error[0]:+.2f}, {result.final_error[1]:+.2f}) mm{clearance}"
    )
    return ManipulationDrawing(
        title=title, triangles=mesh.triangles, rest=mesh.nodes, deformed=x,
        outline_rest=mesh.nodes[loop], outline_deformed=x[loop],
        obstacles_rest=[(o.name, o.outline) for o in scene.obstacles],
        obstacles_deformed=deformed_outlines(obstacles, x),
        target_rest=target_rest, target_reached=result.final_position, desired=result.desired,
        corridor_radius_mm=float("nan") if corridor is None else corridor.radius_mm,
        corridor_before=before, corridor_after=after, cup_nodes=list(tissue.cup_nodes),
    )
