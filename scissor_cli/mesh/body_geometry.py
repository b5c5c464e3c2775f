"""Geometry of a 3-D body in numpy: inside tests, volumes, distances to its surface, regions by element centroid.

The dome is analytic (the half-spheroid x²/a² + y²/a² + z²/h² ≤ 1, z ≥ 0);
a surface body is a closed, outward triangulation (config/surface_file.py
checked it), tested by ray parity and measured by point-triangle distances,
both over candidate pairs from a grid broad phase instead of all pairs.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.config.surface_file import overlapping_boxes
from scissor_cli.geometry3d import closest_on_triangles
from scissor_cli.mesh.body_field import polyline_distance

#: points per batch in the surface queries (bounds the pair arrays)
_BATCH = 65536


def dome_inside(radius: float, height: float):
    """inside(points (K, 3)) -> (K,) bool for the half-spheroid of base radius `radius` and apex `height`."""

    def inside(p: np.ndarray) -> np.ndarray:
        rho = (p[:, 0] ** 2 + p[:, 1] ** 2) / radius**2 + p[:, 2] ** 2 / height**2
        return (p[:, 2] >= 0) & (rho <= 1.0)

    return inside


def dome_volume(radius: float, height: float) -> float:
    return 2.0 / 3.0 * np.pi * radius**2 * height


def surface_volume(nodes: np.ndarray, triangles: np.ndarray) -> float:
    """Volume (mm³) enclosed by a closed, outward triangulation (the divergence theorem)."""
    p = nodes[triangles]
    return float(np.sum(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2]))) / 6.0)


def surface_inside(nodes: np.ndarray, triangles: np.ndarray):
    """inside(points (K, 3)) -> (K,) bool for a closed triangulation: odd crossings of a ray towards +z.

    The ray's foot is nudged by a billionth of the surface's size along an
    irrational direction, so a ray through a vertex or an edge (regular
    grids of points against a box-shaped surface) does not count it twice.
    """
    p = nodes[triangles]
    lo, hi = p[:, :, :2].min(axis=1), p[:, :, :2].max(axis=1)
    cell = float(np.median(np.max(hi - lo, axis=1)))
    nudge = 1e-9 * float(np.linalg.norm(np.ptp(nodes, axis=0))) * np.array([np.sqrt(2.0), np.sqrt(3.0) - 1.0])
    a, b, c = p[:, 0, :2], p[:, 1, :2], p[:, 2, :2]
    det = _cross2(b - a, c - a)

    def inside(q: np.ndarray) -> np.ndarray:
        out = np.zeros(len(q), bool)
        for start in range(0, len(q), _BATCH):
            chunk = q[start:start + _BATCH]
            xy = chunk[:, :2] + nudge
            i, j = overlapping_boxes(xy, xy, lo, hi, cell=cell)
            keep = det[j] != 0  # a face seen edge-on from below is crossed by no ray
            i, j = i[keep], j[keep]
            l1 = _cross2(xy[i] - a[j], c[j] - a[j]) / det[j]
            l2 = _cross2(b[j] - a[j], xy[i] - a[j]) / det[j]
            l0 = 1.0 - l1 - l2
            z = l0 * p[j, 0, 2] + l1 * p[j, 1, 2] + l2 * p[j, 2, 2]
            crossed = (l0 > 0) & (l1 > 0) & (l2 > 0) & (z > chunk[i, 2])
            out[start:start + _BATCH] = np.bincount(i[crossed], minlength=len(chunk)) % 2 == 1
        return out

    return inside


def _cross2(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]


def surface_depth(nodes: np.ndarray, triangles: np.ndarray, cap: float):
    """depth(points (K, 3)) -> (K,): the distance to the triangulated surface, at most `cap`.

    Exact (point-triangle distances) within a band of two grid steps of the
    surface; beyond it, interpolated in a grid of the distance carried inward
    from the band along grid steps (a chamfer distance transform: within 8 %
    of the Euclidean distance, and cheap however deep the body is). The grid
    has about 12 steps over `cap`, at most 64 along the body's widest side.
    """
    lo, hi = nodes.min(axis=0), nodes.max(axis=0)
    step = max(cap / 12.0, float(np.max(hi - lo)) / 64.0, 1e-9)
    band = 2.0 * step
    near = _near_distance(nodes, triangles, band)
    shape = tuple(int(n) for n in np.ceil((hi - lo) / step).astype(int) + 1)
    grid = np.stack(np.meshgrid(*[lo[k] + step * np.arange(shape[k]) for k in range(3)], indexing="ij"), axis=-1)
    field = near(grid.reshape(-1, 3)).reshape(shape)
    _chamfer(field, step, cap)

    def depth(q: np.ndarray) -> np.ndarray:
        d = near(q)
        far = ~(d <= band)
        d[far] = _trilinear(field, (q[far] - lo) / step)
        return np.minimum(d, cap)

    return depth


def _near_distance(nodes: np.ndarray, triangles: np.ndarray, band: float):
    """distance(points) -> (K,): to the surface where it is within `band`, inf elsewhere."""
    p = nodes[triangles]
    lo_t, hi_t = p.min(axis=1), p.max(axis=1)
    cell = max(float(np.median(np.max(hi_t - lo_t, axis=1))), band)

    def distance(q: np.ndarray) -> np.ndarray:
        out = np.full(len(q), np.inf)
        for start in range(0, len(q), _BATCH):
            chunk = q[start:start + _BATCH]
            # points against the triangles' boxes grown by the band: a point falls in one grid cell only
            i, j = overlapping_boxes(chunk, chunk, lo_t - band, hi_t + band, cell=cell)
            d = np.linalg.norm(chunk[i] - closest_on_triangles(chunk[i], p[j, 0], p[j, 1], p[j, 2]), axis=1)
            np.minimum.at(out, start + i[d <= band], d[d <= band])
        return out

    return distance


def _chamfer(field: np.ndarray, step: float, cap: float) -> None:
    """Carry the finite distances of the grid `field` (inf elsewhere) to every node, in place, up to `cap`."""
    offsets = [np.array(o) for o in np.ndindex(3, 3, 3) if o != (1, 1, 1)]
    for _ in range(int(np.ceil(cap / step)) + 2):  # a front moves at least one step per sweep
        before = field.copy()
        for o in offsets:  # 26 neighbours, each a shifted view of the whole grid
            o = o - 1
            dst = tuple(slice(max(k, 0), field.shape[a] + min(k, 0)) for a, k in enumerate(o))
            src = tuple(slice(max(-k, 0), field.shape[a] + min(-k, 0)) for a, k in enumerate(o))
            np.minimum(field[dst], field[src] + step * float(np.linalg.norm(o)), out=field[dst])
        if np.array_equal(before, field):
            break
    np.minimum(field, cap, out=field)


def _trilinear(field: np.ndarray, x: np.ndarray) -> np.ndarray:
    """field interpolated at grid coordinates x (K, 3) (clamped into the grid)."""
    upper = np.array(field.shape) - 1
    x = np.clip(x, 0, upper)
    i = np.minimum(np.floor(x).astype(int), np.maximum(upper - 1, 0))
    f = x - i
    out = np.zeros(len(x))
    for corner in np.ndindex(2, 2, 2):  # eight corners, each vectorised over all points
        c = np.array(corner)
        weight = np.prod(np.where(c, f, 1 - f), axis=1)
        index = np.minimum(i + c, upper)
        out += weight * field[index[:, 0], index[:, 1], index[:, 2]]
    return out


def within_distance(q: np.ndarray, nodes: np.ndarray, triangles: np.ndarray, limit: float) -> np.ndarray:
    """(K,) whether each point lies within `limit` mm of the triangulated surface."""
    return np.isfinite(_near_distance(nodes, triangles, limit)(q))


def centroid_regions(centroids: np.ndarray, inclusions: tuple, skin_thickness_mm: float | None,
                     nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Region (M,) of every element of a surface body by its centroid: 0 body, 1 skin, then the inclusions.

    The skin is what lies within its thickness of the outer surface; an
    inclusion holds the centroids inside its sphere or within its radius of
    its polyline, and takes them from the skin and from any later inclusion
    (the one given first wins where two overlap).
    """
    region = np.zeros(len(centroids), np.int64)
    first = 1
    if skin_thickness_mm:
        region[within_distance(centroids, nodes, triangles, skin_thickness_mm)] = 1
        first = 2
    for k in reversed(range(len(inclusions))):  # a handful of inclusions, each vectorised over all elements
        region[inside_inclusion(inclusions[k], centroids)] = first + k
    return region


def inside_inclusion(inclusion, p: np.ndarray) -> np.ndarray:
    """(K,) whether points lie in a Sphere (within its radius of the centre) or a Tube (of its polyline)."""
    if hasattr(inclusion, "center_mm"):
        return np.linalg.norm(p - inclusion.center_mm, axis=1) <= inclusion.radius_mm
    return polyline_distance(p, inclusion.points_mm) <= inclusion.radius_mm
