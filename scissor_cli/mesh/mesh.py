"""Quality triangulation of a scene with Shewchuk's Triangle (docs/model.md §2, §9).

Fine only where the scene needs it: the target edge length is `min_edge_mm`
at targets, obstacle outlines and cup contacts and grows by `grading` per mm
of distance up to `max_edge_mm`. Obstacle outlines are mesh segments, so each
element is wholly inside or outside an obstacle; targets are mesh vertices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import triangle

from scissor_cli import geometry
from scissor_cli.config import MeshConfig
from scissor_cli.config.mesh_file import read_mesh_arrays
from scissor_cli.scene.scene import Scene


class MeshError(RuntimeError):
    """Triangle could not mesh the scene as asked."""


@dataclass(frozen=True)
class SizeField:
    """Target edge length h(p) = clip(min + grading·d(p), min, max), all in mm."""

    points: np.ndarray  # (P, 2) point features
    seg_a: np.ndarray  # (S, 2) segment features, start
    seg_b: np.ndarray  # (S, 2) end
    min_edge_mm: float
    max_edge_mm: float
    grading: float
    graded: bool

    def __call__(self, p: np.ndarray) -> np.ndarray:
        """Edge length (K,) in mm at points (K, 2)."""
        p = np.atleast_2d(p)
        if not self.graded:
            return np.full(len(p), self.min_edge_mm)
        d = np.full(len(p), np.inf)
        for lo in range(0, len(p), 4096):  # chunks bound the (K, S) temporaries
            chunk = p[lo : lo + 4096]
            if len(self.points):
                d[lo : lo + 4096] = np.linalg.norm(chunk[:, None] - self.points[None], axis=-1).min(axis=1)
            if len(self.seg_a):
                ds = geometry.point_segment_distance(chunk, self.seg_a, self.seg_b).min(axis=1)
                d[lo : lo + 4096] = np.minimum(d[lo : lo + 4096], ds)
        return np.clip(self.min_edge_mm + self.grading * d, self.min_edge_mm, self.max_edge_mm)


@dataclass(frozen=True)
class Mesh:
    nodes: np.ndarray  # (N, 2) mm, rest positions
    triangles: np.ndarray  # (M, 3) int64, counter-clockwise
    element_obstacle: np.ndarray  # (M,) int64: index into scene.obstacles, -1 for plain tissue
    boundary_edges: np.ndarray  # (B, 2) int64, oriented with the domain on the left

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_elements(self) -> int:
        return len(self.triangles)

    def angles_deg(self) -> np.ndarray:
        """Interior angles (M, 3) in degrees."""
        p = self.nodes[self.triangles]
        out = np.empty((self.n_elements, 3))
        for k in range(3):  # three corners, each vectorised over all elements
            u = p[:, (k + 1) % 3] - p[:, k]
            v = p[:, (k + 2) % 3] - p[:, k]
            cos = np.sum(u * v, axis=1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
            out[:, k] = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        return out

    def edge_lengths(self) -> np.ndarray:
        """Edge lengths (M, 3) in mm."""
        p = self.nodes[self.triangles]
        return np.linalg.norm(p - np.roll(p, -1, axis=1), axis=2)

    def boundary_nodes_on_sides(self, sides) -> np.ndarray:
        """Sorted nodes (F,) of the boundary edges that face the named sides."""
        a, b = self.nodes[self.boundary_edges[:, 0]], self.nodes[self.boundary_edges[:, 1]]
        d = b - a
        normal = np.column_stack([d[:, 1], -d[:, 0]]) / np.linalg.norm(d, axis=1, keepdims=True)
        mask = np.zeros(len(d), bool)
        for side in sides:
            mask |= normal @ geometry.SIDE_NORMALS[side] > np.cos(np.pi / 4) + 1e-9
        return np.unique(self.boundary_edges[mask])

    def boundary_nodes_near(self, point: np.ndarray, radius_mm: float) -> np.ndarray:
        """Sorted boundary nodes (C,) within radius_mm of a point."""
        nodes = np.unique(self.boundary_edges)
        near = np.linalg.norm(self.nodes[nodes] - point, axis=1) <= radius_mm * (1 + 1e-9)
        return nodes[near]


def grip_ends(scene: Scene) -> np.ndarray:
    """Where each cup's grip ends on the outline: points (K, 2) at exactly radius_mm from the contact.

    They become mesh vertices, so every mesh grips the same stretch of
    boundary and the solution converges under refinement instead of
    following the last gripped node.
    """
    a, b = geometry.edges(scene.outline)
    d = b - a
    out = []
    for cup in scene.cups:
        f = a - cup.contact
        qa, qb, qc = np.sum(d * d, axis=1), 2 * np.sum(f * d, axis=1), np.sum(f * f, axis=1) - cup.radius_mm**2
        disc = qb * qb - 4 * qa * qc
        ok = disc >= 0
        for sign in (-1.0, 1.0):
            t = (-qb[ok] + sign * np.sqrt(disc[ok])) / (2 * qa[ok])
            inside = (t >= 0) & (t <= 1)
            out.append(a[ok][inside] + t[inside, None] * d[ok][inside])
    pts = np.concatenate(out) if out else np.zeros((0, 2))
    return np.unique(np.round(pts, 9), axis=0)


def size_field(scene: Scene, min_edge_mm: float, max_edge_mm: float, grading: float, graded: bool) -> SizeField:
    points = [t.rest for t in scene.targets] + [c.contact for c in scene.cups] + list(grip_ends(scene))
    seg_a = [o.outline for o in scene.obstacles]
    seg_b = [np.roll(o.outline, -1, axis=0) for o in scene.obstacles]
    return SizeField(
        points=np.array(points, float).reshape(-1, 2),
        seg_a=np.concatenate(seg_a) if seg_a else np.zeros((0, 2)),
        seg_b=np.concatenate(seg_b) if seg_b else np.zeros((0, 2)),
        min_edge_mm=min_edge_mm,
        max_edge_mm=max_edge_mm,
        grading=grading,
        graded=graded,
    )


def _discretise_closed(poly: np.ndarray, h: SizeField, breaks: np.ndarray | None = None) -> np.ndarray:
    """Points along a closed polygon spaced by the size field; vertices and breaks kept."""
    pts = [poly]
    if breaks is not None and len(breaks):
        pts.append(breaks)
    closed = np.vstack([poly, poly[:1]])
    # Arc-length parameter of every polygon vertex and break point.
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s_vertex = np.concatenate([[0.0], np.cumsum(seg)])
    total = s_vertex[-1]
    keep = list(s_vertex[:-1])
    if breaks is not None:
        for b in breaks:
            a_, b_ = closed[:-1], closed[1:]
            dist = geometry.point_segment_distance(b[None], a_, b_)[0]
            k = int(np.argmin(dist))
            keep.append(s_vertex[k] + np.linalg.norm(b - closed[k]))
    keep = np.unique(np.round(np.asarray(keep), 12))
    # Between fixed points, place points at equal steps of ∫ ds / h.
    fine = np.linspace(0.0, total, max(int(total / (h.min_edge_mm / 8)), 64) + 1)
    fine_xy = np.column_stack([np.interp(fine, s_vertex, closed[:, 0]), np.interp(fine, s_vertex, closed[:, 1])])
    inv_h = 1.0 / h(fine_xy)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (inv_h[1:] + inv_h[:-1]) * np.diff(fine))])
    s_all = []
    bounds = np.append(keep, total)
    for s0, s1 in zip(bounds[:-1], bounds[1:]):
        c0, c1 = np.interp([s0, s1], fine, cum)
        n = max(int(np.ceil(c1 - c0 - 1e-9)), 1)
        s_all.append(np.interp(np.linspace(c0, c1, n + 1)[:-1], cum, fine))
    s_all = np.concatenate(s_all)
    return np.column_stack([np.interp(s_all, s_vertex, closed[:, 0]), np.interp(s_all, s_vertex, closed[:, 1])])


def build_mesh(
    scene: Scene,
    min_edge_mm: float,
    max_edge_mm: float,
    min_angle_deg: float = 28.0,
    grading: float = 0.3,
    graded: bool = True,
    max_refinements: int = 12,
) -> Mesh:
    """Triangulate the scene's layer with a graded size field.

    The outline and obstacle outlines become segments discretised to the
    local size; Triangle then refines interior triangles whose area exceeds
    that of an equilateral triangle of the local edge length, with the
    minimum-angle bound, until none does.
    """
    h = size_field(scene, min_edge_mm, max_edge_mm, grading, graded)
    breaks = np.vstack([np.array([c.contact for c in scene.cups]).reshape(-1, 2), grip_ends(scene)])
    loops = [_discretise_closed(scene.outline, h, breaks)] + [_discretise_closed(o.outline, h) for o in scene.obstacles]
    vertices, segments, offset = [], [], 0
    for loop in loops:
        n = len(loop)
        vertices.append(loop)
        idx = np.arange(n) + offset
        segments.append(np.column_stack([idx, np.roll(idx, -1)]))
        offset += n
    targets = np.array([t.rest for t in scene.targets]).reshape(-1, 2)
    outline_points = np.vstack(vertices)
    # a target on an outline's vertex is that vertex already: a second copy would be a node of no triangle
    near = np.linalg.norm(targets[:, None] - outline_points[None], axis=-1).min(axis=1) <= 1e-9 if len(targets) else []
    vertices.append(targets[~np.asarray(near, bool)])
    pslg = {"vertices": np.vstack(vertices), "segments": np.vstack(segments)}
    quality = f"q{min_angle_deg:g}"
    tri = triangle.triangulate(pslg, f"p{quality}Q")
    for _ in range(max_refinements):
        nodes, tris = tri["vertices"], tri["triangles"]
        centroid = nodes[tris].mean(axis=1)
        allowed = np.sqrt(3) / 4 * h(centroid) ** 2
        area = 0.5 * np.abs(geometry.cross2(nodes[tris[:, 1]] - nodes[tris[:, 0]],
                                            nodes[tris[:, 2]] - nodes[tris[:, 0]]))
        if np.all(area <= 1.5 * allowed):
            break
        tri = triangle.triangulate(
            {**tri, "triangle_max_area": allowed.reshape(-1, 1)}, f"rp{quality}aQ"
        )
    else:
        raise MeshError(f"size field not met after {max_refinements} refinements")
    return mesh_from_arrays(scene, tri["vertices"], tri["triangles"])


def mesh_from_arrays(scene: Scene, nodes: np.ndarray, triangles: np.ndarray) -> Mesh:
    """The `Mesh` of nodes (N, 2) mm and triangles (M, 3): counter-clockwise, obstacles by centroid, boundary edges."""
    nodes = np.asarray(nodes, float)
    tris = np.array(triangles, np.int64)
    # Triangle returns counter-clockwise triangles; make sure rather than trust (a mesh file may not).
    flip = geometry.cross2(nodes[tris[:, 1]] - nodes[tris[:, 0]], nodes[tris[:, 2]] - nodes[tris[:, 0]]) < 0
    tris[flip] = tris[flip][:, [0, 2, 1]]
    centroid = nodes[tris].mean(axis=1)
    owner = np.full(len(tris), -1, np.int64)
    for k, obstacle in enumerate(scene.obstacles):
        owner[geometry.points_in_polygon(centroid, obstacle.outline)] = k
    return Mesh(nodes=nodes, triangles=tris, element_obstacle=owner, boundary_edges=_boundary_edges(tris))


def mesh_for_config(scene: Scene, mesh_cfg: MeshConfig, scale: float | None = None) -> Mesh:
    """The mesh a config's `tissue.mesh` section asks for (scale overrides its `scale`).

    With `file` the run's own mesh is read from it (config.mesh_file, checked
    when the config was validated); other scales (the study's levels) are meshed.
    """
    s = mesh_cfg.scale if scale is None else scale
    if mesh_cfg.file is not None and s == mesh_cfg.scale:
        return mesh_from_arrays(scene, *read_mesh_arrays(mesh_cfg.file))
    return build_mesh(
        scene,
        min_edge_mm=mesh_cfg.min_edge_mm * s,
        max_edge_mm=mesh_cfg.max_edge_mm * s,
        min_angle_deg=mesh_cfg.min_angle_deg,
        grading=mesh_cfg.grading,
        graded=mesh_cfg.graded,
    )


def _boundary_edges(tris: np.ndarray) -> np.ndarray:
    """Edges (B, 2) used by one triangle only, in that triangle's CCW order."""
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    key = np.sort(e, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return e[counts[inverse.ravel()] == 1]


def locate(mesh: Mesh, points: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Containing triangle (K,) and barycentric coordinates (K, 3) of points (K, 2).

    Raises ValueError naming the first point outside the mesh.
    """
    points = np.atleast_2d(np.asarray(points, float))
    p = mesh.nodes[mesh.triangles]  # (M, 3, 2)
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    det = geometry.cross2(b - a, c - a)  # (M,)
    tri_idx = np.empty(len(points), np.int64)
    bary = np.empty((len(points), 3))
    for lo in range(0, len(points), 256):  # chunks bound the (K, M) temporaries
        q = points[lo : lo + 256, None, :]
        l1 = geometry.cross2(q - a, c - a) / det
        l2 = geometry.cross2(b - a, q - a) / det
        l0 = 1 - l1 - l2
        worst = np.minimum(np.minimum(l0, l1), l2)  # (k, M): >= 0 inside
        best = np.argmax(worst, axis=1)
        rows = np.arange(len(best))
        if np.any(worst[rows, best] < -tol):
            bad = lo + int(np.flatnonzero(worst[rows, best] < -tol)[0])
            raise ValueError(f"point {points[bad].tolist()} mm is outside the mesh")
        tri_idx[lo : lo + 256] = best
        bary[lo : lo + 256] = np.column_stack([l0[rows, best], l1[rows, best], l2[rows, best]])
    return tri_idx, bary


def interpolate(positions: np.ndarray, triangles: np.ndarray, tri_idx: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Points (K, 2) carried by barycentric coordinates on node positions (N, 2)."""
    return np.einsum("kj,kjd->kd", bary, positions[triangles[tri_idx]])


#: meshio's cell type by (dimension, nodes per cell): what export writes, what an element's `cell_type` names
MESHIO_CELLS: dict[tuple[int, int], str] = {(2, 3): "triangle", (3, 4): "tetra", (2, 6): "triangle6",
                                            (3, 10): "tetra10"}


def meshio_cell_type(dim: int, nodes_per_cell: int) -> str:
    """meshio's name of a cell with these nodes in d = `dim` (ValueError for one it has no name for)."""
    try:
        return MESHIO_CELLS[dim, nodes_per_cell]
    except KeyError:
        raise ValueError(f"no meshio cell of {nodes_per_cell} nodes in {dim}-D") from None
