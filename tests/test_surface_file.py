"""A body's surface file (config/surface_file.py): read, merged, oriented outward, and refused with a reason."""

from __future__ import annotations

import meshio
import numpy as np
import pytest
from scenes.body_surfaces import box, icosphere, write_stl

from scissor_cli.config import surface_file
from scissor_cli.config.surface_file import (
    SurfaceFileError,
    checked_surface,
    connected_labels,
    overlapping_boxes,
    read_surface,
    triangles_intersect,
)


def _volume(v: np.ndarray, t: np.ndarray) -> float:
    p = v[t]
    return float(np.sum(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2]))) / 6.0)


def _refused(tmp_path, v, t, *words, name="s.stl"):
    path = write_stl(tmp_path / name, v, t)
    with pytest.raises(SurfaceFileError) as info:
        read_surface(path)
    message = str(info.value)
    for word in words:
        assert word in message, message
    assert str(path) in message
    return message


def test_an_stl_sphere_is_merged_and_kept_outward(tmp_path):
    v, t = icosphere(30.0, (5.0, -2.0, 40.0), subdivisions=2)
    for name, faces in (("out.stl", t), ("inside_out.stl", t[:, [0, 2, 1]])):
        nodes, triangles = read_surface(write_stl(tmp_path / name, v, faces))
        assert nodes.dtype == np.float64 and triangles.dtype == np.int64
        # STL stores three corners per face: 320 faces, 960 corners, 162 distinct vertices
        assert nodes.shape == (162, 3) and triangles.shape == (320, 3)
        assert _volume(nodes, triangles) == pytest.approx(_volume(v, t), rel=1e-6)
        assert _volume(nodes, triangles) > 0


def test_every_suffix_reads_the_same_surface(tmp_path):
    v, t = box((0, 0, 0), (80, 60, 40))
    expected = _volume(v, t)
    write_stl(tmp_path / "ascii.stl", v, t, binary=False)
    for suffix in (".obj", ".ply", ".vtk", ".vtu"):
        meshio.write(tmp_path / f"b{suffix}", meshio.Mesh(v, [("triangle", t)]))
    for name in ("ascii.stl", "b.obj", "b.ply", "b.vtk", "b.vtu"):
        nodes, triangles = read_surface(tmp_path / name)
        assert len(nodes) == 8 and len(triangles) == 12, name
        assert _volume(nodes, triangles) == pytest.approx(expected, rel=1e-6), name


def test_vertices_a_rounding_error_apart_are_one(tmp_path):
    v, t = icosphere(30.0, subdivisions=1)
    corners = v[t].reshape(-1, 3)  # every face its own corners, as in STL
    corners = corners + np.random.default_rng(0).uniform(-1e-7, 1e-7, corners.shape)
    nodes, triangles = checked_surface(corners, np.arange(len(corners)).reshape(-1, 3))
    assert len(nodes) == 42 and len(triangles) == 80


def test_a_missing_file_or_another_suffix(tmp_path):
    with pytest.raises(SurfaceFileError, match="does not exist"):
        read_surface(tmp_path / "nowhere.stl")
    (tmp_path / "body.step").write_text("ISO-10303-21;")
    with pytest.raises(SurfaceFileError, match="a surface file is one of"):
        read_surface(tmp_path / "body.step")


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply", ".vtk", ".vtu"])
def test_garbage_bytes_are_an_unreadable_file(tmp_path, suffix, capsys):
    path = tmp_path / f"garbage{suffix}"
    path.write_bytes(bytes(range(256)) * 3)
    with pytest.raises(SurfaceFileError, match="cannot read .* damaged or not in that format"):
        read_surface(path)
    assert capsys.readouterr().out == ""  # meshio's own chatter is not passed on


def test_a_file_without_triangles(tmp_path):
    meshio.write(tmp_path / "lines.vtk", meshio.Mesh(np.eye(3), [("line", np.array([[0, 1], [1, 2]]))]))
    with pytest.raises(SurfaceFileError, match=r"no triangles \(only line cells\)"):
        read_surface(tmp_path / "lines.vtk")


def test_an_open_surface_says_how_many_boundary_edges(tmp_path):
    v, t = icosphere(30.0, subdivisions=1)
    _refused(tmp_path, v, t[1:], "open", "3 boundary edges")


def test_a_fin_is_non_manifold(tmp_path):
    v, t = icosphere(30.0, subdivisions=1)
    a, b = t[0, 0], t[0, 1]
    fin = np.vstack([v, 0.5 * (v[a] + v[b]) * 1.5])
    _refused(tmp_path, fin, np.vstack([t, [[a, b, len(v)]]]), "non-manifold", "more than two faces")


def test_a_face_turned_the_other_way_is_non_manifold(tmp_path):
    v, t = icosphere(30.0, subdivisions=1)
    t = t.copy()
    t[5] = t[5, [0, 2, 1]]
    _refused(tmp_path, v, t, "non-manifold", "not consistently oriented")


def test_two_overlapping_boxes_are_self_intersecting(tmp_path):
    (v1, t1), (v2, t2) = box((0, 0, 0), (40, 40, 40)), box((20, 20, 20), (60, 60, 60))
    _refused(tmp_path, np.vstack([v1, v2]), np.vstack([t1, t2 + 8]), "self-intersecting")


def test_a_corner_pushed_through_the_far_side_is_self_intersecting(tmp_path):
    v, t = icosphere(30.0, subdivisions=2)
    v = v.copy()
    v[0] = -1.2 * v[0]  # one piece, closed and manifold, folded through itself
    _refused(tmp_path, v, t, "self-intersecting")


def test_a_zero_area_face_is_degenerate(tmp_path):
    v, t = icosphere(30.0, subdivisions=1)
    a, b, c = t[0]
    d = t[np.flatnonzero(np.any(t == a, axis=1) & np.any(t == b, axis=1))[1]]
    d = int(d[~np.isin(d, [a, b])][0])
    m = len(v)
    keep = ~(np.all(np.isin(t, [a, b, c]), axis=1) | np.all(np.isin(t, [a, b, d]), axis=1))
    # face abc split at the midpoint m of ab, and the sliver a-b-m closing the crack: closed, manifold, no area
    faces = np.vstack([t[keep], [[a, m, c], [m, b, c], [b, a, d], [a, b, m]]])
    message = _refused(tmp_path, np.vstack([v, 0.5 * (v[a] + v[b])]), faces, "degenerate", "zero area")
    assert message.count("1 of") == 1


def test_separate_pieces_and_a_pinched_corner(tmp_path):
    (v1, t1), (v2, t2) = box((0, 0, 0), (10, 10, 10)), box((20, 0, 0), (30, 10, 10))
    _refused(tmp_path, np.vstack([v1, v2]), np.vstack([t1, t2 + 8]), "2 separate pieces", name="two.stl")
    # two tetrahedra that share one corner: every edge has two faces, but the corner joins two sheets
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [-10, 0, 0], [0, -10, 0], [0, 0, -10]], float)
    tet = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    other = np.array([[0, 5, 4], [0, 4, 6], [0, 6, 5], [4, 5, 6]])
    _refused(tmp_path, v, np.vstack([tet, other]), "non-manifold at a vertex", name="pinched.stl")


def test_absurd_coordinates_and_sizes(tmp_path, monkeypatch):
    v, t = icosphere(30.0, subdivisions=1)
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(SurfaceFileError, match="not finite"):
        checked_surface(bad, t)
    _refused(tmp_path, v * 100.0, t, "spans", "more than 1000 mm", name="huge.stl")
    _refused(tmp_path, v / 1000.0, t, "metres", name="tiny.stl")
    monkeypatch.setattr(surface_file, "MAX_TRIANGLES", 50)
    _refused(tmp_path, v, t, "80 triangles is more than the 50", name="many.stl")


def test_triangle_pairs_that_touch_cross_or_miss():
    base = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0]], float)
    others = {
        "pierces": ([[0.5, 0.5, -1], [0.5, 0.5, 1], [0.6, 0.4, 1]], True),
        "above": ([[0.5, 0.5, 0.1], [0.5, 0.6, 1], [0.6, 0.4, 1]], False),
        "crosses the plane beside it": ([[3, 3, -1], [3, 3, 1], [3.1, 2.9, 1]], False),
        "a corner on the face": ([[0.5, 0.5, 0], [0.5, 0.6, 1], [0.6, 0.4, 1]], True),
        "coplanar, overlapping": ([[0.5, 0.5, 0], [3, 0.5, 0], [0.5, 3, 0]], True),
        "coplanar, inside": ([[0.1, 0.1, 0], [0.3, 0.1, 0], [0.1, 0.3, 0]], True),
        "coplanar, apart": ([[3, 3, 0], [4, 3, 0], [3, 4, 0]], False),
        "an edge in the plane, outside": ([[1.5, 1.5, 0], [3, 3, 0], [2, 2, 1]], False),
        "an edge in the plane, across": ([[0.5, 0.5, 0], [3, 0.5, 0], [1, 1, 1]], True),
    }
    q = np.array([o for o, _ in others.values()], float)
    p = np.broadcast_to(base, q.shape)
    expected = np.array([hit for _, hit in others.values()])
    assert np.array_equal(triangles_intersect(p, q), expected)
    assert np.array_equal(triangles_intersect(q, p), expected)


def test_box_pairs_match_every_pair_checked():
    rng = np.random.default_rng(1)
    lo_a = rng.uniform(0, 10, (400, 3))
    hi_a = lo_a + rng.uniform(0, 1, (400, 3))
    lo_b = rng.uniform(0, 10, (300, 3))
    hi_b = lo_b + rng.uniform(0, 4, (300, 3))
    i, j = overlapping_boxes(lo_a, hi_a, lo_b, hi_b)
    brute = np.argwhere(np.all((lo_a[:, None] <= hi_b[None]) & (lo_b[None] <= hi_a[:, None]), axis=2))
    assert len(i) == len(brute) > 0
    assert sorted(zip(i.tolist(), j.tolist())) == sorted(map(tuple, brute.tolist()))


def test_components_of_a_graph():
    # a path 0-1-2-3, a pair 5-6 and a lone 4, with edges in no helpful order
    labels = connected_labels(7, np.array([3, 6, 1, 2]), np.array([2, 5, 0, 1]))
    assert labels.tolist() == [0, 0, 0, 0, 4, 5, 5]
