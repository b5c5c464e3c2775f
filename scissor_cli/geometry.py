"""Plane geometry on plain arrays: polygons, segments, distances.

The lowest layer of scissor: it imports nothing from the package, so the
config validation, the mesher and the needle planner share one definition of
"inside", "on the boundary" and "clearance". All lengths in mm.
"""

from __future__ import annotations

import numpy as np

SIDES = ("bottom", "top", "left", "right")
#: Outward normal of each named side of a layer; for a curved or polygonal
#: outline a side is the part of the boundary whose normal is within 45° of it.
SIDE_NORMALS = {
    "bottom": np.array([0.0, -1.0]),
    "top": np.array([0.0, 1.0]),
    "left": np.array([-1.0, 0.0]),
    "right": np.array([1.0, 0.0]),
}


def cross2(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """z of the cross product of 2-D vectors (..., 2) × (..., 2) (numpy's np.cross dropped 2-D vectors)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def signed_area(poly: np.ndarray) -> float:
    """Signed area (mm²) of a closed polygon (K, 2); positive when counter-clockwise."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def ccw(poly: np.ndarray) -> np.ndarray:
    """The polygon (K, 2) with counter-clockwise vertex order."""
    poly = np.asarray(poly, dtype=float)
    return poly if signed_area(poly) > 0 else poly[::-1].copy()


def circle_polygon(center, radius: float, n: int) -> np.ndarray:
    """n vertices (n, 2), counter-clockwise, on a circle of `radius` mm."""
    return ellipse_polygon(center, (radius, radius), n)


def ellipse_polygon(center, radii, n: int) -> np.ndarray:
    """n vertices (n, 2), counter-clockwise, on an axis-aligned ellipse."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    c = np.asarray(center, dtype=float)
    return np.column_stack([c[0] + radii[0] * np.cos(t), c[1] + radii[1] * np.sin(t)])


def edges(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end points (K, 2), (K, 2) of the closed polygon's edges."""
    return poly, np.roll(poly, -1, axis=0)


def points_in_polygon(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Crossing-number test: (K,) bool, True strictly inside (boundary is ambiguous)."""
    p = np.atleast_2d(np.asarray(points, dtype=float))
    a, b = edges(np.asarray(poly, dtype=float))
    px, py = p[:, 0:1], p[:, 1:2]
    ay, by = a[None, :, 1], b[None, :, 1]
    straddles = (ay > py) != (by > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = a[None, :, 0] + (py - ay) * (b[None, :, 0] - a[None, :, 0]) / (by - ay)
    return np.count_nonzero(straddles & (px < x_cross), axis=1) % 2 == 1


def closest_on_segments(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The closest points (K, S, 2) in mm on each segment a→b (S, 2) to each point (K, 2)."""
    p = np.atleast_2d(np.asarray(points, dtype=float))[:, None, :]
    a, b = np.atleast_2d(a)[None], np.atleast_2d(b)[None]
    ab = b - a
    len2 = np.maximum(np.sum(ab * ab, axis=-1), 1e-300)
    t = np.clip(np.sum((p - a) * ab, axis=-1) / len2, 0.0, 1.0)
    return a + t[..., None] * ab


def point_segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (K, S) in mm from each point (K, 2) to each segment a→b (S, 2)."""
    p = np.atleast_2d(np.asarray(points, dtype=float))[:, None, :]
    return np.linalg.norm(p - closest_on_segments(points, a, b), axis=-1)


def nearest_on_boundary(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """The nearest points (K, 2) in mm on the polygon outline to points (K, 2)."""
    q = closest_on_segments(points, *edges(np.asarray(poly, dtype=float)))
    d = np.linalg.norm(q - np.atleast_2d(np.asarray(points, dtype=float))[:, None, :], axis=-1)
    return q[np.arange(len(q)), np.argmin(d, axis=1)]


def distance_to_boundary(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Unsigned distance (K,) in mm from points to the polygon outline."""
    a, b = edges(np.asarray(poly, dtype=float))
    return point_segment_distance(points, a, b).min(axis=1)


def segments_intersect(p1, p2, q1, q2) -> np.ndarray:
    """Whether segments p1→p2 (K, 2) and q1→q2 (S, 2) properly cross: (K, S) bool."""
    p1, p2 = np.atleast_2d(p1)[:, None], np.atleast_2d(p2)[:, None]
    q1, q2 = np.atleast_2d(q1)[None], np.atleast_2d(q2)[None]

    def orient(a, b, c):
        return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (
            c[..., 0] - a[..., 0]
        )

    d1, d2 = orient(q1, q2, p1), orient(q1, q2, p2)
    d3, d4 = orient(p1, p2, q1), orient(p1, p2, q2)
    return (d1 * d2 < 0) & (d3 * d4 < 0)


def segment_polygon_distance(a, b, poly: np.ndarray) -> float:
    """Distance (mm) from segment a→b to a polygon region; 0 if they touch or overlap."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    pa, pb = edges(np.asarray(poly, dtype=float))
    if segments_intersect(a, b, pa, pb).any() or points_in_polygon(a[None], poly)[0]:
        return 0.0
    d_vertices = point_segment_distance(pa, a[None], b[None]).min()
    d_ends = point_segment_distance(np.stack([a, b]), pa, pb).min()
    return float(min(d_vertices, d_ends))


def polygons_overlap(p: np.ndarray, q: np.ndarray) -> bool:
    """Whether two simple polygons share interior: crossing edges or containment."""
    pa, pb = edges(p)
    qa, qb = edges(q)
    if segments_intersect(pa, pb, qa, qb).any():
        return True
    return bool(points_in_polygon(p[:1], q)[0] or points_in_polygon(q[:1], p)[0])


def is_simple(poly: np.ndarray) -> bool:
    """Whether a closed polygon has no self-crossing edges."""
    a, b = edges(poly)
    cross = segments_intersect(a, b, a, b)
    return not cross.any()


def outward_normals(poly: np.ndarray) -> np.ndarray:
    """Unit outward normals (K, 2) of the edges of a counter-clockwise polygon."""
    a, b = edges(poly)
    d = b - a
    n = np.column_stack([d[:, 1], -d[:, 0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def side_edge_mask(poly: np.ndarray, side: str) -> np.ndarray:
    """(K,) bool: the edges of a CCW polygon that belong to a named side.

    An edge belongs to a side when its outward normal is within 45° of the
    side's normal, so for a rectangle a side is exactly its edge and for an
    ellipse it is the quarter arc facing that way.
    """
    return outward_normals(poly) @ SIDE_NORMALS[side] > np.cos(np.pi / 4) + 1e-9


#: thickness ratio of neighbouring prism layers of the slab away from the simulated layer (docs/model.md §13)
LEVEL_GROWTH = 1.5


def graded_levels(height_mm: float, layer_z_mm: float, first_mm: float, max_layer_mm: float) -> tuple[np.ndarray, int]:
    """z levels (L,) mm from 0 to H with one at layer_z, and that level's index.

    Prism layers are `first_mm` thick next to layer_z, then LEVEL_GROWTH times
    thicker each, at most max_layer_mm, on either side; each side is scaled
    to fit exactly. A side of zero length (the layer on a face) has none.
    """
    first = min(first_mm, max_layer_mm)

    def side(length: float) -> np.ndarray:
        if length <= 0:
            return np.zeros(0)
        steps, h, total = [], first, 0.0
        while total < length * (1 - 1e-9):
            steps.append(h)
            total += h
            h = min(h * LEVEL_GROWTH, max_layer_mm)
        steps = np.array(steps)
        if len(steps) > 1 and steps.sum() - length > 0.5 * steps[-1]:
            steps = steps[:-1]  # drop a last layer mostly outside, stretch the rest
        return np.cumsum(steps * (length / steps.sum()))

    up = side(height_mm - layer_z_mm)
    down = side(layer_z_mm)
    levels = np.concatenate([layer_z_mm - down[::-1], [layer_z_mm], layer_z_mm + up])
    levels[0], levels[-1] = 0.0, height_mm  # exact faces, not layer_z ± a rounded sum
    return levels, len(down)
