"""Space geometry on arrays: distances to triangles and segments, lines through triangles, inside a closed surface,
the dome's surface.

The one definition of "inside the body", "distance to the skin" and
"nearest skin point" that the 3-D scene's checks (config), its build
(scene, mechanics) and its planner share (docs/model.md §19). Everything
works on all points and triangles at once.
"""

from __future__ import annotations

import numpy as np

#: (points × triangles) pairs per chunk of the kernels below: bounds their temporaries
CHUNK_PAIRS = 65_536


def _step(n_triangles: int) -> int:
    return max(1, CHUNK_PAIRS // max(n_triangles, 1))


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points (..., 3) on triangles a-b-c to points p (Ericson's Voronoi regions); p, a, b, c (..., 3)
    broadcast against each other: p[:, None] against (T, 3) corners gives every pair (K, T, 3), equal shapes one
    triangle per point."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.sum(ab * ap, -1), np.sum(ac * ap, -1)
    bp = p - b
    d3, d4 = np.sum(ab * bp, -1), np.sum(ac * bp, -1)
    cp = p - c
    d5, d6 = np.sum(ab * cp, -1), np.sum(ac * cp, -1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in, w_in = vb / denom, vc / denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    out = a + v_in[..., None] * ab + w_in[..., None] * ac  # inside the face
    regions = [  # (condition, point), the later overriding the earlier where both hold: vertices last
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + t_bc[..., None] * (c - b)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + t_ac[..., None] * ac),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + t_ab[..., None] * ab),
        ((d6 >= 0) & (d5 <= d6), np.broadcast_to(c, out.shape)),
        ((d3 >= 0) & (d4 <= d3), np.broadcast_to(b, out.shape)),
        ((d1 <= 0) & (d2 <= 0), np.broadcast_to(a, out.shape)),
    ]
    for cond, q in regions:
        out = np.where(cond[..., None], q, out)
    return out


def nearest_on_surface(points: np.ndarray, nodes: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                               np.ndarray]:
    """For points (K, 3): the nearest point (K, 3) on a triangulated surface (nodes (V, 3), triangles (T, 3)),
    its distance (K,) mm and the triangle (K,) it lies on."""
    points = np.atleast_2d(np.asarray(points, float))
    a, b, c = (nodes[triangles[:, i]] for i in range(3))
    best = np.empty((points.shape[0], 3))
    dist = np.empty(points.shape[0])
    tri = np.empty(points.shape[0], np.int64)
    step = _step(len(triangles))
    for lo in range(0, points.shape[0], step):
        chunk = points[lo:lo + step]
        q = closest_on_triangles(chunk[:, None, :], a, b, c)  # (k, T, 3)
        d2 = np.sum((q - chunk[:, None, :]) ** 2, -1)
        k = np.argmin(d2, axis=1)
        rows = np.arange(chunk.shape[0])
        best[lo:lo + chunk.shape[0]] = q[rows, k]
        dist[lo:lo + chunk.shape[0]] = np.sqrt(d2[rows, k])
        tri[lo:lo + chunk.shape[0]] = k
    return best, dist, tri


def winding_numbers(points: np.ndarray, nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """The generalised winding number (K,) of a closed, outward-oriented surface at points (K, 3): 1 inside, 0
    outside (Van Oosterom–Strackee solid angles summed over the triangles, / 4π)."""
    points = np.atleast_2d(np.asarray(points, float))
    out = np.empty(points.shape[0])
    step = _step(len(triangles))
    for lo in range(0, points.shape[0], step):
        p = points[lo:lo + step, None, :]
        a, b, c = (nodes[triangles[:, i]][None] - p for i in range(3))
        la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
        det = np.sum(a * np.cross(b, c), -1)
        div = la * lb * lc + np.sum(a * b, -1) * lc + np.sum(a * c, -1) * lb + np.sum(b * c, -1) * la
        out[lo:lo + step] = 2.0 * np.arctan2(det, div).sum(axis=1) / (4.0 * np.pi)
    return out


def inside_surface(points: np.ndarray, nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(K,) bool: the points lie inside the closed surface (winding number above one half)."""
    return winding_numbers(points, nodes, triangles) > 0.5


def rotation_matrix(rotation_vector) -> np.ndarray:
    """(3, 3): the rotation by a rotation vector (3,) rad (Rodrigues' formula; the identity for a zero vector)."""
    v = np.asarray(rotation_vector, float)
    theta = float(np.linalg.norm(v))
    if theta < 1e-15:
        return np.eye(3)
    k = v / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * K @ K


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (K, S) from points p (K, 3) to segments a→b (S, 3 each)."""
    p = np.atleast_2d(p)[:, None, :]
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def segment_segment_distance(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Distances (S, R) between segments p0→p1 (S, 3) and q0→q1 (R, 3), either of which may be a point (Ericson,
    "Real-Time Collision Detection" §5.1.9: the closest parameters, clamped)."""
    d1 = (p1 - p0)[:, None, :]
    d2 = (q1 - q0)[None, :, :]
    r = p0[:, None, :] - q0[None, :, :]
    a, e = np.sum(d1 * d1, -1), np.sum(d2 * d2, -1)
    b, c, f = np.sum(d1 * d2, -1), np.sum(d1 * r, -1), np.sum(d2 * r, -1)
    eps = 1e-24
    a_safe, e_safe = np.where(a > eps, a, 1.0), np.where(e > eps, e, 1.0)
    denom = a * e - b * b
    # both proper segments: s on the infinite lines, clamped; then t, and s again where t was clamped
    s = np.where(denom > 1e-12 * np.maximum(a * e, eps), np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0),
                                                                  0.0, 1.0), 0.0)
    t = (b * s + f) / e_safe
    s = np.where(t < 0, np.clip(-c / a_safe, 0, 1), np.where(t > 1, np.clip((b - c) / a_safe, 0, 1), s))
    t = np.clip(t, 0.0, 1.0)
    # a point for the second: t = 0; for the first: s = 0; for both: 0, 0
    s = np.where(e <= eps, np.clip(-c / a_safe, 0, 1), s)
    t = np.where(e <= eps, 0.0, t)
    t = np.where(a <= eps, np.clip(f / e_safe, 0, 1), t)
    s = np.where(a <= eps, 0.0, s)
    t = np.where((a <= eps) & (e <= eps), 0.0, t)
    return np.linalg.norm(r + s[..., None] * d1 - t[..., None] * d2, axis=-1)


def ray_triangle_hits(origins: np.ndarray, directions: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray,
                      tol: float = 1e-9) -> np.ndarray:
    """Ray parameters t (K, T) at which the lines origin + t·direction (K, 3 each) cross triangles (a, b, c each
    (T, 3)), +inf where a line misses one or runs parallel to it (Möller–Trumbore). t may be negative (behind the
    origin): the caller keeps the side it wants. A crossing within tol (barycentric) of a triangle's edge counts,
    so a line through an edge or a corner hits at least one of the triangles that share it."""
    origins, directions = np.atleast_2d(origins), np.atleast_2d(directions)
    e1, e2 = b - a, c - a
    scale = np.linalg.norm(np.cross(e1, e2), axis=1)  # (T,): |det| below 1e-12 of this × |d| is parallel
    out = np.empty((origins.shape[0], a.shape[0]))
    step = _step(len(a))
    for lo in range(0, origins.shape[0], step):
        d = directions[lo:lo + step, None, :]
        pvec = np.cross(d, e2)  # (k, T, 3)
        det = np.sum(e1 * pvec, -1)
        ok = np.abs(det) > 1e-12 * scale * np.linalg.norm(d, axis=-1)
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tvec = origins[lo:lo + step, None, :] - a
        u = np.sum(tvec * pvec, -1) * inv
        qvec = np.cross(tvec, e1)
        v = np.sum(d * qvec, -1) * inv
        t = np.sum(e2 * qvec, -1) * inv
        hit = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1.0 + tol)
        out[lo:lo + step] = np.where(hit, t, np.inf)
    return out


def spheroid_cap_surface(radius_mm: float, height_mm: float, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The dome (the half-spheroid x²/r² + y²/r² + z²/h² ≤ 1, z ≥ 0) as a closed, outward triangulation: its curved
    skin and its base disc on z = 0, with edges of about spacing_mm. Returns nodes (V, 3), triangles (T, 3) and
    is what the checks of a dome scene use as its surface (the mesh follows the exact shape)."""
    r, h = float(radius_mm), float(height_mm)
    arc = 0.5 * np.pi * max(r, h)
    n_lat = max(4, int(np.ceil(arc / spacing_mm)))
    n_lon = max(8, int(np.ceil(2 * np.pi * r / spacing_mm)))
    phi = np.linspace(0.0, 0.5 * np.pi, n_lat + 1)[:-1]  # elevation of each ring, from the base up (apex apart)
    lon = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack([np.outer(np.cos(phi), np.cos(lon)).ravel() * r, np.outer(np.cos(phi), np.sin(lon)).ravel() * r,
                     np.repeat(np.sin(phi) * h, n_lon)], axis=1)
    apex = np.array([[0.0, 0.0, h]])
    centre = np.array([[0.0, 0.0, 0.0]])
    nodes = np.concatenate([ring, apex, centre])
    i_apex, i_centre = len(ring), len(ring) + 1
    tris = []
    j = np.arange(n_lon)
    jn = (j + 1) % n_lon
    for k in range(n_lat - 1):  # quads between rings k and k + 1, outward (counter-clockwise seen from outside)
        lo, hi = k * n_lon, (k + 1) * n_lon
        tris += [np.stack([lo + j, lo + jn, hi + jn], 1), np.stack([lo + j, hi + jn, hi + j], 1)]
    top = (n_lat - 1) * n_lon
    tris.append(np.stack([top + j, top + jn, np.full(n_lon, i_apex)], 1))
    tris.append(np.stack([jn, j, np.full(n_lon, i_centre)], 1))  # the base, facing −z
    return nodes, np.concatenate(tris).astype(np.int64)


def inside_spheroid_cap(points: np.ndarray, radius_mm: float, height_mm: float) -> np.ndarray:
    """(K,) bool: inside the dome (z ≥ 0 and x²/r² + y²/r² + z²/h² ≤ 1)."""
    p = np.atleast_2d(points)
    q = (p[:, 0] ** 2 + p[:, 1] ** 2) / radius_mm ** 2 + p[:, 2] ** 2 / height_mm ** 2
    return (p[:, 2] >= 0.0) & (q <= 1.0)


def closest_on_ellipse(y0: np.ndarray, y1: np.ndarray, e0: float, e1: float) -> tuple[np.ndarray, np.ndarray]:
    """The closest points (x0, x1) of the ellipse (x0/e0)² + (x1/e1)² = 1 to points (y0, y1) ≥ 0 (each (K,)).

    Eberly's robust method ("Distance from a point to an ellipse", 2013):
    a bisection on the Lagrange parameter, vectorised; the axes in any order.
    """
    if e0 < e1:
        x1, x0 = closest_on_ellipse(y1, y0, e1, e0)
        return x0, x1
    y0, y1 = np.abs(np.asarray(y0, float)), np.abs(np.asarray(y1, float))
    x0, x1 = np.empty_like(y0), np.empty_like(y1)
    # on the minor axis (y1 > 0, y0 = 0)
    axis1 = (y1 > 0) & (y0 <= 0)
    x0[axis1], x1[axis1] = 0.0, e1
    # on the major axis (y1 = 0)
    axis0 = y1 <= 0
    numer, denom = e0 * y0[axis0], e0 * e0 - e1 * e1
    inner = numer < denom
    xde = np.where(inner, numer / denom if denom > 0 else 0.0, 1.0)
    x0[axis0] = e0 * xde
    x1[axis0] = np.where(inner, e1 * np.sqrt(np.clip(1 - xde * xde, 0, None)), 0.0)
    # in the open quadrant: bisection on s for F(s) = (r0 z0 / (s + r0))² + (z1 / (s + 1))² − 1
    q = (y0 > 0) & (y1 > 0)
    z0, z1 = y0[q] / e0, y1[q] / e1
    g = z0 * z0 + z1 * z1 - 1.0
    r0 = (e0 / e1) ** 2
    s0 = z1 - 1.0
    s1 = np.where(g < 0, 0.0, np.hypot(r0 * z0, z1) - 1.0)
    for _ in range(200):  # halves the bracket to well below round-off
        s = 0.5 * (s0 + s1)
        f = (r0 * z0 / (s + r0)) ** 2 + (z1 / (s + 1.0)) ** 2 - 1.0
        s0 = np.where(f > 0, s, s0)
        s1 = np.where(f > 0, s1, s)
    s = np.where(g == 0, 0.0, 0.5 * (s0 + s1))
    x0[q] = r0 * y0[q] / (s + r0)
    x1[q] = y1[q] / (s + 1.0)
    return x0, x1


def spheroid_cap_nearest(points: np.ndarray, radius_mm: float, height_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The nearest points (K, 3) on the dome's curved skin (the half-spheroid's surface, z ≥ 0) to points (K, 3),
    and their distances (K,) mm."""
    p = np.atleast_2d(np.asarray(points, float))
    rho = np.hypot(p[:, 0], p[:, 1])
    x_rho, x_z = closest_on_ellipse(rho, p[:, 2], radius_mm, height_mm)
    x_z = np.where(p[:, 2] < 0, 0.0, x_z)  # below the platform: the rim is nearest
    x_rho = np.where(p[:, 2] < 0, radius_mm, x_rho)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(rho > 0, p[:, 0] / rho, 1.0)
        s = np.where(rho > 0, p[:, 1] / rho, 0.0)
    q = np.stack([x_rho * c, x_rho * s, x_z], axis=1)
    return q, np.linalg.norm(q - p, axis=1)


def spheroid_cap_normal(points: np.ndarray, radius_mm: float, height_mm: float) -> np.ndarray:
    """Outward unit normals (K, 3) of the dome's curved skin at points (K, 3) on it."""
    p = np.atleast_2d(np.asarray(points, float))
    n = np.stack([p[:, 0] / radius_mm ** 2, p[:, 1] / radius_mm ** 2, p[:, 2] / height_mm ** 2], axis=1)
    return n / np.linalg.norm(n, axis=1, keepdims=True)
