"""Scatterers carried by the tissue as material points, and seen in the probe's frame (docs/ultrasound.md §6).

A scatterer is a point of the tissue: it is located once, at rest, on the
mesh the true tissue is solved on, and every frame it moves with that
mesh's nodes.

* **In the layer** (a 2-D mesh) it keeps the barycentric weights of its
  rest triangle; its deformed position is the same combination of the
  deformed vertices, exactly as `mesh.probe.TargetProbe` carries a target.
  It lies in the imaging plane (elevation 0).
* **In the slab** (the prism extrusion of a 2-D mesh, `plane`, into
  `levels_mm`) it keeps the barycentric weights of its triangle of the
  plane, and its rest height z between the two levels that bracket it,
  t = (z - z_l) / (z_{l+1} - z_l). Its deformed position is
  (1 - t) sum_j b_j x[node(l, v_j)] + t sum_j b_j x[node(l + 1, v_j)]:
  linear in-plane on each level and linear in z between them (six nodes
  of its prism). This is the prism's own interpolation, not that of the
  tetrahedron it lies in; the two agree on the prism's faces, so the
  motion is continuous, and both converge with the mesh. Its elevation,
  across the imaging plane, is its deformed z minus the layer's height
  (the probe does not move), so motion across the plane moves it through
  the elevation beam.

The probe frame is (lateral, depth) along the true pose's lateral and
axis (`transducer.ProbePose`). `carry_to_probe` writes the lateral, depth
and elevation of every scatterer in one compiled pass over the nodes'
positions, without the (S, 6, 3) temporaries a gather would need.

A mesh is read by its attributes only (`nodes`, `triangles`; the slab's
`plane`, `levels_mm`, `layer_level`, `node`), so this layer does not
import the slab's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from scissor_cli.sensing.ultrasound.transducer import ProbePose


def is_slab(mesh) -> bool:
    """True for the slab's mesh (an extrusion with a `plane` and levels), False for a 2-D mesh."""
    return getattr(mesh, "plane", None) is not None and getattr(mesh, "levels_mm", None) is not None


def locate_points(mesh, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Containing triangle (K,) (-1: outside the mesh) and barycentric weights (K, 3) of points (K, 2) mm.

    A point-location structure (matplotlib's trapezoid map) over the 2-D
    mesh's triangles: fast for the hundreds of thousands of scatterers a
    trial draws, where `mesh.mesh.locate` tests every triangle.
    """
    import matplotlib.tri as mtri  # noqa: PLC0415  (only the sensor that carries scatterers needs it)

    p = np.asarray(points_mm, dtype=float).reshape(-1, 2)
    nodes, tris = np.asarray(mesh.nodes, float), np.asarray(mesh.triangles)
    finder = mtri.Triangulation(nodes[:, 0], nodes[:, 1], tris).get_trifinder()
    tri = np.asarray(finder(p[:, 0], p[:, 1]), dtype=np.int64)
    bary = np.zeros((len(p), 3))
    inside = tri >= 0
    v = nodes[tris[tri[inside]]]  # (k, 3, 2)
    a, b, c = v[:, 0], v[:, 1], v[:, 2]
    q = p[inside]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    l1 = ((q[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (q[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])) / det
    l2 = ((b[:, 0] - a[:, 0]) * (q[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (q[:, 0] - a[:, 0])) / det
    bary[inside] = np.column_stack([1.0 - l1 - l2, l1, l2])
    return tri, bary


@dataclass(frozen=True)
class CarriedScatterers:
    """Scatterers as material points of one mesh (module docstring).

    nodes (S, J) int64 and weights (S, J): the J = 3 (layer) or 6 (slab)
    nodes each scatterer follows and their weights (rows sum to 1);
    layer_z_mm: the imaging plane's height (slab; 0 in the layer); kept
    (S0,) bool: which of the scatterers handed in lie inside the mesh (the
    others are dropped; S = kept.sum()).
    """

    nodes: np.ndarray
    weights: np.ndarray
    layer_z_mm: float
    kept: np.ndarray

    def __len__(self) -> int:
        return len(self.nodes)

    def to_probe(self, x_mm: np.ndarray, pose: ProbePose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lateral (S,), true depth (S,), elevation (S,)) mm in the probe's frame for node positions x (N, d) mm."""
        x = np.ascontiguousarray(x_mm, dtype=np.float64)
        S = len(self.nodes)
        lat, dep, ele = np.empty(S), np.empty(S), np.empty(S)
        carry_to_probe(self.nodes, self.weights, x, pose.position_mm, pose.lateral, pose.axis, self.layer_z_mm,
                       lat, dep, ele)
        return lat, dep, ele


def carry_on(mesh, positions_mm: np.ndarray, elevation_mm: np.ndarray) -> CarriedScatterers:
    """Scatterers at rest, in-plane positions (S, 2) mm and elevations (S,) mm, as material points of `mesh`.

    In the slab the rest height is the layer's plus the elevation; a
    scatterer outside the slab's height, or outside the mesh in the plane,
    is dropped (`kept`).
    """
    p = np.asarray(positions_mm, dtype=float).reshape(-1, 2)
    y = np.asarray(elevation_mm, dtype=float).reshape(-1)
    if not is_slab(mesh):
        tri, bary = locate_points(mesh, p)
        kept = tri >= 0
        nodes = np.asarray(mesh.triangles)[tri[kept]]
        return CarriedScatterers(np.ascontiguousarray(nodes, np.int64), np.ascontiguousarray(bary[kept]), 0.0, kept)
    levels = np.asarray(mesh.levels_mm, dtype=float)
    z_layer = float(levels[mesh.layer_level])
    z = z_layer + y
    tri, bary = locate_points(mesh.plane, p)
    kept = (tri >= 0) & (z >= levels[0]) & (z <= levels[-1])
    tri, bary, z = tri[kept], bary[kept], z[kept]
    lev = np.clip(np.searchsorted(levels, z, side="right") - 1, 0, len(levels) - 2)
    t = (z - levels[lev]) / (levels[lev + 1] - levels[lev])
    verts = np.asarray(mesh.plane.triangles)[tri]  # (S, 3)
    nodes = np.concatenate([mesh.node(lev[:, None], verts), mesh.node(lev[:, None] + 1, verts)], axis=1)
    weights = np.concatenate([(1.0 - t)[:, None] * bary, t[:, None] * bary], axis=1)
    return CarriedScatterers(np.ascontiguousarray(nodes, np.int64), np.ascontiguousarray(weights), z_layer, kept)


@njit(cache=True, nogil=True, boundscheck=False)
def carry_to_probe(nodes, weights, x, origin, lateral, axis, layer_z, out_lateral, out_depth, out_elevation):
    """Each scatterer's deformed position sum_j w_j x[n_j] in the probe frame: lateral, depth, elevation (mm).

    x (N, 2) (elevation 0) or (N, 3) (elevation z - layer_z); origin,
    lateral, axis (2,) the pose's array centre and unit vectors.
    """
    S, J = nodes.shape
    d = x.shape[1]
    for s in range(S):
        px = 0.0
        py = 0.0
        pz = 0.0
        for j in range(J):
            n = nodes[s, j]
            w = weights[s, j]
            px += w * x[n, 0]
            py += w * x[n, 1]
            if d == 3:
                pz += w * x[n, 2]
        px -= origin[0]
        py -= origin[1]
        out_lateral[s] = px * lateral[0] + py * lateral[1]
        out_depth[s] = px * axis[0] + py * axis[1]
        out_elevation[s] = pz - layer_z if d == 3 else 0.0
