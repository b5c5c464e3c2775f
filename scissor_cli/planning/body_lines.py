"""Straight needle lines in the 3-D body: the allowed directions, where a line leaves the skin, its clearance
(docs/model.md §19, "Plan").

The geometry of one state of the body, given its node positions x (N, 3):

* a **line** through the lesion's centre c along a direction n is the
  needle's path; it enters where the ray c − t n (t > 0) first crosses the
  body's boundary triangles at x. That crossing must be on the skin: a
  line that leaves through the held base, or that crosses the body again
  farther out (a fold of a surface body the needle would pierce first),
  is no line;
* its **clearance** is the smallest distance from the shaft (entry → c) to
  an obstacle's surface, less the needle's radius and the margin.
  Obstacles are tissue: their points are carried by the rest tetrahedra
  holding them (`mesh.probe`), so they are judged where the deformation
  puts them. A vessel is only the part of its polyline inside the body
  (cut where it crosses the rest boundary, as the mesh's regions are); a
  cyst whose centre lies outside follows the affine map of the tetrahedron
  nearest it (its smallest barycentric coordinate the largest).

Everything is evaluated for all directions and all boundary triangles at
once (`geometry3d.ray_triangle_hits`, `geometry3d.segment_segment_distance`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scissor_cli import geometry3d as g3
from scissor_cli.mesh.probe import TargetProbe, probe_points, target_positions

#: azimuths on each ring of the cone of directions, the rings at 1/3, 2/3 and 3/3 of its half-angle
RING_AZIMUTHS = (8, 12, 16)
#: what became of a line: it enters through the skin; it leaves the body nowhere; through the held base; it
#: crosses the body again outside its entry
LINE_OK, NO_EXIT, THROUGH_BASE, RECROSSES = 0, 1, 2, 3
#: crossings of one line this close (× the body's size) are one crossing (an edge or a corner shared by faces)
SAME_CROSSING = 1e-7


def cone_directions(axis, cone_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The allowed insertion directions: unit vectors (D, 3) within cone_deg of the unit `axis` (3,), and their
    angles (D,) rad from it. The axis first, then rings at k/3 of cone_deg (k = 1, 2, 3) with 8, 12 and 16
    azimuths, the first along axis × z (horizontal; axis × x for a vertical axis), so every ring holds the two
    horizontal tilts of a horizontal axis (the puncture module's needle is horizontal, docs/model.md §11).
    cone_deg = 0: the axis alone. Deterministic: the same inputs give the same directions in the same order."""
    a = np.asarray(axis, float).reshape(3)
    a = a / np.linalg.norm(a)
    if cone_deg <= 0:
        return a[None].copy(), np.zeros(1)
    e1 = np.cross(a, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-9:
        e1 = np.cross(a, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    tilt = np.concatenate([np.full(n, np.deg2rad(cone_deg) * (k + 1) / len(RING_AZIMUTHS))
                           for k, n in enumerate(RING_AZIMUTHS)])
    phi = np.concatenate([2 * np.pi * np.arange(n) / n for n in RING_AZIMUTHS])
    ring = (np.cos(tilt)[:, None] * a + np.sin(tilt)[:, None] * (np.cos(phi)[:, None] * e1
                                                               + np.sin(phi)[:, None] * e2))
    dirs = np.concatenate([a[None], ring])
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True), np.concatenate([[0.0], tilt])


def skin_entries(x: np.ndarray, triangles: np.ndarray, base: np.ndarray, centre: np.ndarray,
                 directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each line through centre (3,) along directions (D, 3) enters the body at node positions x (N, 3):
    entries (D, 3) mm (NaN where none), depths (D,) mm from the entry to the centre, and codes (D,) (LINE_OK,
    NO_EXIT, THROUGH_BASE, RECROSSES). `triangles` (S, 3) are the boundary faces, `base` (S,) marks the held ones."""
    a, b, c = (x[triangles[:, i]] for i in range(3))
    size = float(np.ptp(x, axis=0).max())
    t = g3.ray_triangle_hits(np.broadcast_to(centre, directions.shape), -directions, a, b, c)  # (D, S)
    t = np.where(t > SAME_CROSSING * size, t, np.inf)
    first = t.min(axis=1)
    near = t <= (first + SAME_CROSSING * size)[:, None]
    code = np.where(~np.isfinite(first), NO_EXIT,
                    np.where(np.any(near & base[None], axis=1), THROUGH_BASE,
                             np.where(np.any(np.isfinite(t) & ~near, axis=1), RECROSSES, LINE_OK)))
    depth = np.where(np.isfinite(first), first, np.nan)
    return centre - depth[:, None] * directions, depth, code


@dataclass(frozen=True)
class CarriedObstacles:
    """The obstacles as R segments (spheres: a segment of one point), their end points carried by the body."""

    names: tuple[str, ...]
    probe: TargetProbe  # of the 2R end points, start then end of each segment
    owner: np.ndarray  # (R,) index into names
    radius: np.ndarray  # (R,) mm

    def segments(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The segments' ends (R, 3) and (R, 3) at node positions x (N, 3)."""
        p = target_positions(self.probe, x)
        return p[0::2], p[1::2]


def _inside_pieces(p0: np.ndarray, p1: np.ndarray, nodes: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray,
                                                                                                         np.ndarray]:
    """The pieces (starts, ends (Q, 3)) of segments p0 → p1 (R, 3) inside the closed surface, with (Q,) the
    segment each came from, cut where they cross it."""
    t = g3.ray_triangle_hits(p0, p1 - p0, *(nodes[triangles[:, i]] for i in range(3)))  # (R, S)
    cuts = [np.unique(np.round(np.concatenate([[0.0], row[(row > 0) & (row < 1)], [1.0]]), 12)) for row in t]
    seg = np.concatenate([np.full(len(c) - 1, i) for i, c in enumerate(cuts)])
    lo = np.concatenate([c[:-1] for c in cuts])
    hi = np.concatenate([c[1:] for c in cuts])
    d = p1[seg] - p0[seg]
    start, end = p0[seg] + lo[:, None] * d, p0[seg] + hi[:, None] * d
    keep = g3.inside_surface(0.5 * (start + end), nodes, triangles) & (hi - lo > 1e-9)
    return start[keep], end[keep], seg[keep]


def carry_obstacles(obstacles, nodes: np.ndarray, tetrahedra: np.ndarray,
                    boundary_triangles: np.ndarray) -> CarriedObstacles:
    """The scene's obstacles (`scene.body_scene.Inclusion`s) as carried segments of the rest mesh."""
    starts, ends, owner, radius = [np.zeros((0, 3))], [np.zeros((0, 3))], [np.zeros(0, np.int64)], [np.zeros(0)]
    for k, ob in enumerate(obstacles):
        if ob.kind == "sphere":
            s, e = ob.points[:1], ob.points[:1]
        else:
            s, e, _ = _inside_pieces(ob.points[:-1], ob.points[1:], nodes, boundary_triangles)
        starts.append(s)
        ends.append(e)
        owner.append(np.full(len(s), k, np.int64))
        radius.append(np.full(len(s), ob.radius_mm))
    ends_pts = np.stack([np.concatenate(starts), np.concatenate(ends)], axis=1).reshape(-1, 3)
    probe = probe_points(nodes, tetrahedra, ends_pts, extrapolate=True) if len(ends_pts) else \
        TargetProbe(np.zeros(0, np.int64), np.zeros((0, 4), np.int64), np.zeros((0, 4)))
    return CarriedObstacles(tuple(o.name for o in obstacles), probe, np.concatenate(owner), np.concatenate(radius))


def shaft_clearance(entries: np.ndarray, tip: np.ndarray, q0: np.ndarray, q1: np.ndarray, radius: np.ndarray,
                    allowance_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Clearance (D,) mm of shafts entries (D, 3) → tip (3,) against segments q0 → q1 (R, 3) of radii (R,): the
    smallest distance to a segment's surface less allowance_mm (the needle's radius and the margin), +inf without
    segments; and the segment (D,) that sets it (−1 without)."""
    d = len(entries)
    if len(q0) == 0:
        return np.full(d, np.inf), np.full(d, -1)
    gap = g3.segment_segment_distance(entries, np.broadcast_to(tip, entries.shape), q0, q1) - radius[None]
    k = np.argmin(gap, axis=1)
    return gap[np.arange(d), k] - allowance_mm, k


@dataclass(frozen=True)
class Lines:
    """Every allowed line at one state of the body (docs/model.md §19, "Plan")."""

    centre: np.ndarray  # (3,) mm: the lesion's centre the lines go through
    directions: np.ndarray  # (D, 3) unit, the needle's travel
    angle: np.ndarray  # (D,) rad from the configured axis
    entry: np.ndarray  # (D, 3) mm on the skin, NaN where the line has no entry
    depth: np.ndarray  # (D,) mm entry → centre
    code: np.ndarray  # (D,) LINE_OK, NO_EXIT, THROUGH_BASE, RECROSSES
    clearance: np.ndarray  # (D,) mm, NaN where code != LINE_OK, +inf without obstacles
    nearest: np.ndarray  # (D,) the obstacle (index into the scene's) that sets the clearance, −1 none

    def ranked(self) -> np.ndarray:
        """The lines that enter through the skin, largest clearance first, ties closest to the axis."""
        ok = np.flatnonzero(self.code == LINE_OK)
        return ok[np.lexsort((self.angle[ok], -self.clearance[ok]))]


def needle_lines(x: np.ndarray, mesh, centre: np.ndarray, directions: np.ndarray, angle: np.ndarray,
                 obstacles: CarriedObstacles, allowance_mm: float) -> Lines:
    """The lines through centre (3,) along directions (D, 3) at node positions x (N, 3) of the body's mesh
    (`mesh.body_mesh.BodyMesh`), judged against the obstacles carried to x."""
    entry, depth, code = skin_entries(x, mesh.boundary_triangles, mesh.boundary_base, centre, directions)
    ok = code == LINE_OK
    clearance = np.full(len(directions), np.nan)
    nearest = np.full(len(directions), -1)
    q0, q1 = obstacles.segments(x)
    c, k = shaft_clearance(entry[ok], centre, q0, q1, obstacles.radius, allowance_mm)
    clearance[ok] = c
    nearest[ok] = np.where(k >= 0, obstacles.owner[np.maximum(k, 0)] if len(q0) else -1, -1)
    return Lines(np.asarray(centre, float), directions, angle, entry, depth, code, clearance, nearest)
