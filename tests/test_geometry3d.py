"""Space geometry (scissor_cli/geometry3d.py): nearest points on triangles, inside a closed surface, the dome."""

from __future__ import annotations

import numpy as np
import pytest

from scissor_cli import geometry3d as g3


def _brute_closest(p, a, b, c, n=120):
    """The nearest of a dense sample of the triangle (u, v ≥ 0, u + v ≤ 1)."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    keep = u + v <= 1
    q = a + u[keep, None] * (b - a) + v[keep, None] * (c - a)
    return q[np.argmin(np.linalg.norm(q - p, axis=1))]


def test_closest_points_on_triangles_are_the_nearest_of_a_dense_sample():
    rng = np.random.default_rng(1)
    tri = rng.normal(size=(10, 3, 3))
    p = rng.normal(scale=2.0, size=(8, 3))
    q = g3.closest_on_triangles(p[:, None, :], tri[:, 0], tri[:, 1], tri[:, 2])
    for i in range(len(p)):
        for t in range(len(tri)):
            ref = _brute_closest(p[i], *tri[t])
            # the exact point is at least as near as any sample, and the sample's spacing away from it
            assert np.linalg.norm(q[i, t] - p[i]) <= np.linalg.norm(ref - p[i]) + 1e-12
            assert np.linalg.norm(q[i, t] - ref) <= 0.05 * np.ptp(tri[t], axis=0).max() + 1e-9


def test_the_dome_surface_is_closed_and_outward_and_its_inside_is_the_spheroid_cap():
    nodes, tris = g3.spheroid_cap_surface(60.0, 35.0, 5.0)
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    assert np.all(count == 2)  # closed, manifold
    a, b, c = (nodes[tris[:, i]] for i in range(3))
    volume = np.sum(np.einsum("ij,ij->i", a, np.cross(b, c))) / 6.0
    assert volume == pytest.approx(2 / 3 * np.pi * 60.0 ** 2 * 35.0, rel=0.02)  # outward: a positive volume
    rng = np.random.default_rng(2)
    p = rng.uniform([-65, -65, -5], [65, 65, 40], size=(400, 3))
    exact = g3.inside_spheroid_cap(p, 60.0, 35.0)
    inside = g3.inside_surface(p, nodes, tris)
    # away from the surface (where the facets cut the curve) the two agree
    _, dist, _ = g3.nearest_on_surface(p, nodes, tris)
    far = dist > 0.5
    assert far.sum() > 300 and np.array_equal(inside[far], exact[far])


def test_distances_to_segments():
    a, b = np.array([[0.0, 0, 0]]), np.array([[10.0, 0, 0]])
    p = np.array([[5.0, 3, 4], [-3.0, 4, 0], [12.0, 0, 0]])
    np.testing.assert_allclose(g3.point_segment_distance(p, a, b)[:, 0], [5.0, 5.0, 2.0])
    q0, q1 = np.array([[5.0, -5, 2], [20.0, 0, 0]]), np.array([[5.0, 5, 2], [30.0, 0, 0]])
    np.testing.assert_allclose(g3.segment_segment_distance(a, b, q0, q1)[0], [2.0, 10.0])


@pytest.mark.parametrize("r, h", [(60.0, 35.0), (20.0, 45.0), (30.0, 30.0)])
def test_the_nearest_point_on_the_dome_is_the_nearest_of_a_dense_sample(r, h):
    rng = np.random.default_rng(3)
    p = rng.uniform([-1.3 * r, -1.3 * r, -0.2 * h], [1.3 * r, 1.3 * r, 1.3 * h], size=(60, 3))
    p[:3] = [[0, 0, 0.5 * h], [0.3 * r, 0, 0], [0, 0, 2 * h]]  # on the axis, on the platform
    q, d = g3.spheroid_cap_nearest(p, r, h)
    assert np.allclose((q[:, 0] ** 2 + q[:, 1] ** 2) / r ** 2 + q[:, 2] ** 2 / h ** 2, 1.0)
    assert np.all(q[:, 2] >= 0)
    lat, lon = np.meshgrid(np.linspace(0, np.pi / 2, 400), np.linspace(0, 2 * np.pi, 800))
    s = np.stack([r * np.cos(lat) * np.cos(lon), r * np.cos(lat) * np.sin(lon), h * np.sin(lat)], -1).reshape(-1, 3)
    ref = np.min(np.linalg.norm(s[None] - p[:, None], axis=-1), axis=1)
    assert np.all(d <= ref + 1e-9)
    assert np.all(d >= ref - 0.6 * max(r, h) * np.pi / 800)  # within the sample's spacing


def test_segment_distances_against_a_dense_sample_degenerate_segments_included():
    rng = np.random.default_rng(4)
    p0, p1 = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    q0, q1 = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    p1[0], q1[0] = p0[0], q0[0]  # points
    d = g3.segment_segment_distance(p0, p1, q0, q1)
    u = np.linspace(0, 1, 400)
    for i in range(6):
        for j in range(5):
            P = p0[i] + u[:, None] * (p1[i] - p0[i])
            Q = q0[j] + u[:, None] * (q1[j] - q0[j])
            ref = np.min(np.linalg.norm(P[:, None] - Q[None], axis=-1))
            assert d[i, j] <= ref + 1e-12 and d[i, j] >= ref - 0.01


def test_lines_through_triangles_cross_where_a_linear_solve_puts_them():
    rng = np.random.default_rng(4)
    tri = rng.normal(size=(30, 3, 3))
    origins = rng.normal(scale=3.0, size=(40, 3))
    # half the lines aimed at a point inside a triangle, so that there are hits as well as misses
    u, v = rng.uniform(0.05, 0.45, size=(2, 20))
    aim = tri[:20, 0] + u[:, None] * (tri[:20, 1] - tri[:20, 0]) + v[:, None] * (tri[:20, 2] - tri[:20, 0])
    directions = np.concatenate([aim - origins[:20], rng.normal(size=(20, 3))])
    t = g3.ray_triangle_hits(origins, directions, tri[:, 0], tri[:, 1], tri[:, 2])
    np.testing.assert_allclose(np.diag(t)[:20], 1.0, atol=1e-9)
    # independently: o + t d = a + u (b − a) + w (c − a) solved as a 3 × 3 system for every pair
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    A = np.stack(np.broadcast_arrays(e1[None], e2[None], -directions[:, None]), axis=-1)  # (40, 30, 3, 3)
    uwt = np.linalg.solve(A, (origins[:, None] - tri[None, :, 0])[..., None])[..., 0]
    inside = (uwt[..., 0] >= 0) & (uwt[..., 1] >= 0) & (uwt[..., 0] + uwt[..., 1] <= 1)
    clear = np.min(np.stack([uwt[..., 0], uwt[..., 1], 1 - uwt[..., 0] - uwt[..., 1]]), axis=0)
    decided = np.abs(clear) > 1e-6  # not within round-off of an edge
    assert inside[decided].sum() > 25 and (~inside[decided]).sum() > 500
    np.testing.assert_array_equal(np.isfinite(t)[decided], inside[decided])
    np.testing.assert_allclose(t[decided & inside], uwt[..., 2][decided & inside], rtol=1e-9, atol=1e-9)


def test_a_line_through_an_edge_hits_a_triangle_that_shares_it_and_parallel_lines_miss():
    a, b, c, d = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    t = g3.ray_triangle_hits(np.array([[0.5, 0.5, 2.0]]), np.array([[0.0, 0, -1]]), np.array([a, b]),
                             np.array([b, d]), np.array([c, c]))
    assert np.all(t == pytest.approx(2.0))  # through the shared edge b–c: both count
    t = g3.ray_triangle_hits(np.array([[0.2, 0.2, 1.0]]), np.array([[1.0, 0, 0]]), a[None], b[None], c[None])
    assert np.isinf(t).all()


def test_one_triangle_per_point_is_the_diagonal_of_every_pair():
    rng = np.random.default_rng(4)
    tri = rng.normal(size=(12, 3, 3))
    p = rng.normal(scale=2.0, size=(12, 3))
    every = g3.closest_on_triangles(p[:, None, :], tri[:, 0], tri[:, 1], tri[:, 2])
    paired = g3.closest_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
    np.testing.assert_allclose(paired, every[np.arange(12), np.arange(12)], atol=1e-12)
