"""What an insertion reads of the tissue besides the needle: the target and the obstacles (docs/model.md §12, §20).

* In the **layer** the target's probe and the obstacles' outlines live on
  its own mesh; in the **slab** they are the layer's, carried by the
  slab's nodes at the layer's level (`layer_points`). The shaft's
  clearance is measured in the layer's plane.
* In a **body** the lesion is probed in its rest tetrahedron and the
  obstacles (spheres, vessels) are segments whose ends the body carries
  (`planning.body_lines.carry_obstacles`, as the planner judges them); the
  clearance is the shaft's 3-D distance to their surfaces.

Both answer the same three things: `probe` (the target's), `clearance(x, p0,
tip, radius_mm)` and `has_obstacles`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from scissor_cli.geometry import segment_polygon_distance
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.outlines import deformed_outlines, embed_outlines
from scissor_cli.mesh.probe import TargetProbe, probe_targets
from scissor_cli.planning.body_lines import carry_obstacles, shaft_clearance


def is_body(tissue: Tissue) -> bool:
    """A 3-D body (tetrahedra meshed from its shape), not the layer or the slab the layer extrudes."""
    return tissue.dim == 3 and not hasattr(tissue.mesh, "plane")


def layer_points(tissue: Tissue, target_rest: np.ndarray, obstacles: list):
    """The target's probe and the obstacles' embedding on the plant's nodes.

    In the layer, on its own mesh; in the slab, the 2-D ones on the slab's
    plane (the 2-D mesh it extruded: the layer's or its own coarser one)
    carried to the slab's nodes at the layer's level (its triangles are
    faces of the slab's tetrahedra there, so the weights are exact).
    """
    if tissue.dim == 2:
        return probe_targets(tissue.mesh, target_rest[None]), embed_outlines(tissue.mesh, obstacles)
    plane = tissue.mesh.plane
    offset = tissue.mesh.node(tissue.mesh.layer_level, 0)
    p = probe_targets(plane, target_rest[None])
    e = embed_outlines(plane, obstacles)
    return (TargetProbe(p.tri_idx, p.nodes + offset, p.bary),
            dataclasses.replace(e, triangles=e.triangles + offset))


class LayerPoints:
    """The layer's (or the slab's layer's) target and obstacle outlines."""

    def __init__(self, tissue: Tissue, target_rest: np.ndarray):
        self.probe, self._embedding = layer_points(tissue, target_rest, [o.outline for o in tissue.scene.obstacles])
        self.has_obstacles = bool(self._embedding.splits)

    def clearance(self, x: np.ndarray, p0: np.ndarray, tip: np.ndarray, radius_mm: float) -> float:
        """Shaft p0 → tip to the nearest deformed obstacle in the layer's plane, less radius_mm (mm); +inf
        without obstacles."""
        outlines = deformed_outlines(self._embedding, x)
        if not outlines:
            return float("inf")
        return min(segment_polygon_distance(p0[:2], tip[:2], poly[:, :2]) for poly in outlines) - radius_mm


class BodyPoints:
    """A body's lesion and its carried obstacle segments."""

    def __init__(self, tissue: Tissue, target_rest: np.ndarray):
        mesh = tissue.mesh
        self.probe = tissue.probe(np.asarray(target_rest, float)[None])
        self._carried = carry_obstacles(tissue.scene.obstacles, mesh.nodes, mesh.tetrahedra, mesh.boundary_triangles)
        self.has_obstacles = bool(len(self._carried.radius))

    def clearance(self, x: np.ndarray, p0: np.ndarray, tip: np.ndarray, radius_mm: float) -> float:
        """Shaft p0 → tip (3,) to the nearest obstacle's surface where x (N, 3) carries it, less radius_mm (mm)."""
        q0, q1 = self._carried.segments(x)
        gap, _ = shaft_clearance(np.asarray(p0, float)[None], np.asarray(tip, float), q0, q1, self._carried.radius,
                                 radius_mm)
        return float(gap[0])


def needle_points(tissue: Tissue, target_rest: np.ndarray) -> LayerPoints | BodyPoints:
    """The target and obstacles an insertion into `tissue` reads."""
    return BodyPoints(tissue, target_rest) if is_body(tissue) else LayerPoints(tissue, target_rest)
