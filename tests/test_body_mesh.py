"""3-D bodies meshed into tetrahedra with gmsh (mesh/body_mesh.py): geometry, regions, quality, determinism, cache,
the element estimate, and surface bodies tagged by centroid."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scenes.body_surfaces import box, icosphere, write_stl

import scissor_cli.mesh.mesh
from scissor_cli.config.surface_file import checked_surface, read_surface
from scissor_cli.mesh import body_geometry, body_gmsh, body_mesh, body_quality
from scissor_cli.mesh.body_field import Features, density_integral, polyline_distance
from scissor_cli.mesh.body_mesh import (
    MIN_DIHEDRAL_DEG,
    BodyShape,
    BodySizing,
    MeshError,
    Sphere,
    Tube,
    estimate_tetrahedra,
)

A, H, SKIN = 60.0, 35.0, 1.5
LESION = Sphere("lesion", np.array([10.0, 20.0, 15.0]), 2.0)
# beside the lesion (2.3 mm from it), leaving the dome through its skin
VESSEL = Tube("vessel", np.array([[15.0, 18.0, 14.0], [30.0, 40.0, 16.0], [45.0, 60.0, 18.0]]), 1.2)
DOME = BodyShape("dome", A, H, skin_thickness_mm=SKIN)
SIZING = BodySizing(0.8, 10.0, 0.6)
COARSE = (BodyShape("dome", A, H), (Sphere("cyst", np.array([-10.0, 5.0, 12.0]), 5.0),), BodySizing(2.0, 15.0, 0.6))


def _volumes(mesh) -> np.ndarray:
    return body_quality.signed_volumes(mesh.nodes, mesh.tetrahedra)


def _rho(p: np.ndarray, a: float = A, h: float = H) -> np.ndarray:
    return np.sqrt((p[..., 0] ** 2 + p[..., 1] ** 2) / a**2 + p[..., 2] ** 2 / h**2)


@pytest.fixture(scope="module")
def dome():
    return body_mesh.body_mesh(DOME, (LESION, VESSEL), SIZING)


@pytest.fixture(scope="module")
def sphere_body(tmp_path_factory):
    # through a binary STL file, as a scan arrives: every corner repeated, float32
    path = write_stl(tmp_path_factory.mktemp("body") / "sphere.stl", *icosphere(30.0, subdivisions=3))
    nodes, triangles = read_surface(path)
    shape = BodyShape("surface", surface_nodes=nodes, surface_triangles=triangles, skin_thickness_mm=SKIN)
    inclusions = (Sphere("lesion", np.array([5.0, 5.0, 0.0]), 4.0),
                  Tube("vessel", np.array([[-10.0, -8.0, 0.0], [10.0, -8.0, 3.0], [45.0, -8.0, 6.0]]), 1.5))
    sizing = BodySizing(1.0, 10.0, 0.6, ((nodes[0], 4.0),))
    return shape, inclusions, sizing, body_mesh.body_mesh(shape, inclusions, sizing)


def test_the_dome_is_a_half_spheroid_of_positive_tetrahedra(dome):
    assert dome.nodes.dtype == np.float64 and dome.tetrahedra.dtype == np.int64 and dome.region.dtype == np.int64
    volumes = _volumes(dome)
    assert np.all(volumes > 0)
    assert volumes.sum() == pytest.approx(2 / 3 * np.pi * A**2 * H, rel=0.02)
    # every node is used, numbered compactly
    assert np.array_equal(np.unique(dome.tetrahedra), np.arange(dome.n_nodes))
    assert dome.n_elements == len(dome.tetrahedra) and dome.n_nodes == len(dome.nodes)


def test_the_boundary_is_the_base_and_the_spheroid_facing_out(dome):
    faces = dome.boundary_triangles
    p = dome.nodes[faces]
    base = dome.boundary_base
    assert base.any() and (~base).any()
    assert np.all(p[base][:, :, 2] == pytest.approx(0.0, abs=1e-9))
    curved = np.unique(faces[~base])
    assert np.all(np.abs(_rho(dome.nodes[curved]) - 1) < 1e-6)
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(normals[base][:, 2] < 0)
    # outward: the divergence theorem over the boundary gives the mesh's volume
    assert np.sum(np.einsum("ij,ij->i", p.mean(axis=1), normals)) / 6 == pytest.approx(_volumes(dome).sum())
    # and the boundary is closed: every edge in exactly two faces, once each way
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert len(np.unique(edges, axis=0)) == len(edges)
    assert {tuple(e) for e in edges.tolist()} == {tuple(e) for e in edges[:, ::-1].tolist()}


def test_every_region_holds_its_volume(dome):
    assert dome.region_names == ("body", "skin", "lesion", "vessel")
    volumes = _volumes(dome)
    by_region = np.bincount(dome.region, weights=volumes, minlength=4)
    assert by_region[2] == pytest.approx(4 / 3 * np.pi * LESION.radius_mm**3, rel=0.10)
    # the vessel's region is its part inside the dome: capsules along the polyline, clipped (Monte Carlo)
    rng = np.random.default_rng(0)
    lo, hi = VESSEL.points_mm.min(axis=0) - 1.2, VESSEL.points_mm.max(axis=0) + 1.2
    q = rng.uniform(lo, hi, (400_000, 3))
    in_tube = polyline_distance(q, VESSEL.points_mm) <= VESSEL.radius_mm
    tube = np.prod(hi - lo) * np.mean(in_tube & (_rho(q) <= 1))
    assert by_region[3] == pytest.approx(tube, rel=0.10)
    # the skin shell: outer half-spheroid minus the inner one, less what the vessel takes of it
    shell = 2 / 3 * np.pi * (A**2 * H - (A - SKIN) ** 2 * (H - SKIN))
    vessel_in_shell = np.prod(hi - lo) * np.mean(in_tube & (_rho(q) <= 1) & (_rho(q, A - SKIN, H - SKIN) > 1))
    assert by_region[1] == pytest.approx(shell - vessel_in_shell, rel=0.02)
    # conforming: the skin's elements lie in the shell, the body's inside the inner half-spheroid
    centroid = dome.nodes[dome.tetrahedra].mean(axis=1)
    inner = _rho(centroid, A - SKIN, H - SKIN)
    assert np.all(inner[dome.region == 1] >= 1 - 1e-9) and np.all(inner[dome.region == 0] <= 1 + 1e-9)


def test_quality_is_above_the_bound(dome):
    angles = body_quality.min_dihedral_deg(dome.nodes, dome.tetrahedra)
    assert dome.min_dihedral_deg == pytest.approx(angles.min())
    assert dome.min_dihedral_deg >= MIN_DIHEDRAL_DEG


def test_the_mesh_follows_the_size_field(dome):
    shape, inclusions, sizing = body_mesh._checked(DOME, (LESION, VESSEL), SIZING)
    features = body_mesh._features(shape, inclusions, sizing)
    p = dome.nodes[dome.tetrahedra]
    edge = np.linalg.norm(p[:, [0, 0, 0, 1, 1, 2]] - p[:, [1, 2, 3, 2, 3, 3]], axis=2).mean(axis=1)
    ratio = edge / features.edge_length(p.mean(axis=1))
    # gmsh meets the field it is given: a different field (or none) moves these by factors of 2 and more
    assert 0.7 < np.median(ratio) < 1.4
    assert np.mean((ratio > 0.5) & (ratio < 2.0)) > 0.9


def test_the_same_inputs_give_the_same_mesh(dome):
    again = body_mesh.body_mesh(DOME, (LESION, VESSEL), SIZING)
    for name in ("nodes", "tetrahedra", "region", "boundary_triangles", "boundary_base"):
        assert np.array_equal(getattr(again, name), getattr(dome, name)), name
    assert again.min_dihedral_deg == dome.min_dihedral_deg


def test_the_cache_returns_the_mesh_without_meshing(tmp_path, monkeypatch):
    shape, inclusions, sizing = COARSE
    made = []
    real = body_gmsh.mesh_dome

    def counting(*args, **kwargs):
        made.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(body_gmsh, "mesh_dome", counting)
    first = body_mesh.body_mesh(shape, inclusions, sizing, cache_dir=tmp_path)
    assert len(made) == 1 and len(list(tmp_path.glob("*.npz"))) == 1

    def refuse(*args, **kwargs):
        raise AssertionError("meshed although the mesh is cached")

    monkeypatch.setattr(body_gmsh, "mesh_dome", refuse)
    cached = body_mesh.body_mesh(shape, inclusions, sizing, cache_dir=tmp_path)
    for name in ("nodes", "tetrahedra", "region", "boundary_triangles", "boundary_base"):
        assert np.array_equal(getattr(cached, name), getattr(first, name)), name
    assert cached.region_names == first.region_names and cached.min_dihedral_deg == first.min_dihedral_deg
    # another input is another key: a moved cyst is meshed, not served from the cache
    moved = (Sphere("cyst", np.array([-10.0, 5.0, 12.5]), 5.0),)
    with pytest.raises(AssertionError, match="meshed although"):
        body_mesh.body_mesh(shape, moved, sizing, cache_dir=tmp_path)
    # a damaged cache file is made again
    monkeypatch.setattr(body_gmsh, "mesh_dome", counting)
    next(tmp_path.glob("*.npz")).write_bytes(b"not an npz")
    again = body_mesh.body_mesh(shape, inclusions, sizing, cache_dir=tmp_path)
    assert len(made) == 2 and np.array_equal(again.tetrahedra, first.tetrahedra)


def test_the_estimate_is_within_a_factor_2(dome, sphere_body):
    shape, inclusions, sizing = COARSE
    coarse = body_mesh.body_mesh(shape, inclusions, sizing)
    box_nodes, box_triangles = checked_surface(*box((-40, -30, 0), (40, 30, 35)))
    box_shape = BodyShape("surface", surface_nodes=box_nodes, surface_triangles=box_triangles)
    box_sizing = BodySizing(1.0, 8.0, 0.4)
    box_inclusions = (Sphere("lesion", np.array([5.0, 5.0, 10.0]), 3.0),)
    boxed = body_mesh.body_mesh(box_shape, box_inclusions, box_sizing)
    cases = [(DOME, (LESION, VESSEL), SIZING, dome), (*COARSE, coarse), (*sphere_body,),
             (box_shape, box_inclusions, box_sizing, boxed)]
    for shape, inclusions, sizing, mesh in cases:
        estimate = estimate_tetrahedra(shape, inclusions, sizing)
        assert 0.5 < mesh.n_elements / estimate < 2.0, (shape.kind, mesh.n_elements, estimate)


def test_a_surface_body_is_tagged_by_centroid(sphere_body):
    shape, inclusions, sizing, mesh = sphere_body
    assert mesh.region_names == ("body", "skin", "lesion", "vessel")
    volumes = _volumes(mesh)
    assert np.all(volumes > 0)
    enclosed = body_geometry.surface_volume(shape.surface_nodes, shape.surface_triangles)
    assert volumes.sum() == pytest.approx(enclosed, rel=0.01)
    assert not mesh.boundary_base.any()
    # the remeshed boundary lies on the given surface
    nodes = mesh.nodes[np.unique(mesh.boundary_triangles)]
    depth = body_geometry.surface_depth(shape.surface_nodes, shape.surface_triangles, 5.0)(nodes)
    assert np.all(depth < 1e-6)
    # every element's region is the centroid rule's, the first inclusion winning over the skin
    centroid = mesh.nodes[mesh.tetrahedra].mean(axis=1)
    expected = np.zeros(len(centroid), np.int64)
    expected[body_geometry.within_distance(centroid, shape.surface_nodes, shape.surface_triangles, SKIN)] = 1
    expected[polyline_distance(centroid, inclusions[1].points_mm) <= inclusions[1].radius_mm] = 3
    expected[np.linalg.norm(centroid - inclusions[0].center_mm, axis=1) <= inclusions[0].radius_mm] = 2
    assert np.array_equal(mesh.region, expected)
    by_region = np.bincount(mesh.region, weights=volumes, minlength=4)
    assert by_region[2] == pytest.approx(4 / 3 * np.pi * 4.0**3, rel=0.15)
    assert by_region[1] == pytest.approx(enclosed - body_geometry.surface_volume(
        *checked_surface(*icosphere(30.0 - SKIN, subdivisions=3))), rel=0.25)
    assert mesh.min_dihedral_deg >= MIN_DIHEDRAL_DEG


def test_a_flat_tetrahedron_is_a_mesh_error(monkeypatch):
    monkeypatch.setattr(body_mesh, "MIN_DIHEDRAL_DEG", 80.0)
    with pytest.raises(MeshError, match=r"dihedral angle of .*° \(in '(body|cyst)' at x, y, z = .*'cyst'.*min_edge_mm"):
        body_mesh.body_mesh(*COARSE)


def test_an_inclusion_outside_the_dome_is_a_mesh_error_and_gmsh_is_released():
    import gmsh

    outside = (Sphere("far", np.array([0.0, 0.0, 80.0]), 3.0),)
    with pytest.raises(MeshError, match="far.* wholly outside the dome"):
        body_mesh.body_mesh(COARSE[0], outside, COARSE[2])
    assert not gmsh.isInitialized()
    assert body_mesh.MeshError is scissor_cli.mesh.mesh.MeshError


def test_importing_loads_no_gmsh():
    code = "import sys, scissor_cli.mesh.body_mesh; print('gmsh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize("shape, inclusions, sizing, words", [
    (BodyShape("cone", 60, 35), (), BodySizing(1, 5, 0.3), "'dome' or 'surface'"),
    (BodyShape("dome", 60, 35, skin_thickness_mm=40), (), BodySizing(1, 5, 0.3), "thinner"),
    (BodyShape("dome", 60, 35), (LESION, LESION), BodySizing(1, 5, 0.3), "names must differ"),
    (BodyShape("dome", 60, 35), (Sphere("skin", np.zeros(3), 1),), BodySizing(1, 5, 0.3), "names must differ"),
    (BodyShape("dome", 60, 35), (Tube("t", np.ones((3, 3)), 1),), BodySizing(1, 5, 0.3), "two distinct points"),
    (BodyShape("dome", 60, 35), (), BodySizing(5, 1, 0.3), "min_edge_mm <= max_edge_mm"),
    (BodyShape("dome", np.nan, 35), (), BodySizing(1, 5, 0.3), "positive number"),
    (BodyShape("surface"), (), BodySizing(1, 5, 0.3), "surface_nodes and surface_triangles"),
])
def test_inputs_no_caller_should_pass(shape, inclusions, sizing, words):
    with pytest.raises(ValueError, match=words):
        estimate_tetrahedra(shape, inclusions, sizing)


def test_the_size_field_and_its_integral():
    f = Features(ball_center=np.array([[0.0, 0.0, 10.0]]), ball_radius=np.array([2.0]), seg_a=np.array([[20.0, 0, 5]]),
                 seg_b=np.array([[30.0, 0, 5]]), seg_radius=np.array([1.0]), min_edge=0.5, max_edge=6.0, grading=0.25)
    p = np.array([[0.0, 0, 10], [0, 0, 13], [25, 3, 5], [34, 0, 5], [0, 0, 100]])
    assert np.allclose(f.edge_length(p), [0.5, 0.5 + 0.25 * 1, 0.5 + 0.25 * 2, 0.5 + 0.25 * 3, 6.0])
    # with no grading h is min_edge everywhere: the integral is the volume over one regular tetrahedron's
    flat = Features(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), 3.0, 9.0, 0.0)
    inside = body_geometry.dome_inside(A, H)
    count = density_integral(flat, inside, np.array([-A, -A, 0]), np.array([A, A, H]))
    assert count == pytest.approx(2 / 3 * np.pi * A**2 * H / (3.0**3 / (6 * np.sqrt(2))), rel=0.02)


def test_a_tube_turns_along_arcs_tangent_to_its_segments():
    points = np.array([[0.0, 0, 0], [10, 0, 0], [10, 10, 0], [12, 10, 9]])
    pieces = body_gmsh.tube_path("v", points, 1.0, 0.5)
    assert [center is None for center, _ in pieces] == [True, False, True, False, True]
    ends = [points[0]] + [end for _, end in pieces]
    for k in (1, 3):  # each arc: both ends at its radius from the centre, which is at least the tube's radius
        center = pieces[k][0]
        r0, r1 = np.linalg.norm(ends[k] - center), np.linalg.norm(ends[k + 1] - center)
        assert r0 == pytest.approx(r1) and r0 >= 1.0
        # tangent: the radius to each end is perpendicular to the straight pieces on either side
        assert np.dot(ends[k] - center, ends[k] - ends[k - 1]) == pytest.approx(0, abs=1e-9)
        assert np.dot(ends[k + 1] - center, ends[k + 2] - ends[k + 1]) == pytest.approx(0, abs=1e-9)
    with pytest.raises(MeshError, match="too sharply"):
        body_gmsh.tube_path("v", np.array([[0.0, 0, 0], [3, 0, 0], [0.2, 0.1, 0]]), 1.0, 0.5)


def test_where_inclusions_overlap_the_first_given_wins():
    first = Sphere("first", np.array([-10.0, 5.0, 12.0]), 5.0)
    second = Sphere("second", np.array([-4.0, 5.0, 12.0]), 5.0)
    lens = np.pi * (4 * 5.0 + 6.0) * (2 * 5.0 - 6.0) ** 2 / 12  # the two balls' common volume, centres 6 mm apart
    ball = 4 / 3 * np.pi * 5.0**3
    mesh = body_mesh.body_mesh(BodyShape("dome", A, H), (first, second), BodySizing(1.0, 15.0, 0.8))
    by_region = np.bincount(mesh.region, weights=_volumes(mesh), minlength=3)
    assert by_region[1] == pytest.approx(ball, rel=0.05) and by_region[2] == pytest.approx(ball - lens, rel=0.05)
    # and by centroid, as a surface body's regions are tagged
    q = np.array([[-7.0, 5.0, 12.0], [-12.0, 5.0, 12.0], [-1.0, 5.0, 12.0], [20.0, 5.0, 12.0]])
    assert body_geometry.centroid_regions(q, (first, second), None, np.zeros((0, 3)), np.zeros((0, 3), int)).tolist() \
        == [1, 1, 2, 0]


def test_tetrahedra_turned_positive_renumbered_and_bounded():
    # a unit cube as six tetrahedra around its diagonal 0-7, half of them given inside out, and an unused node 8
    nodes = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)] + [[5, 5, 5]], float)
    tets = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
    tets[::2] = tets[::2][:, [0, 2, 1, 3]]
    assert np.sum(body_quality.signed_volumes(nodes, tets) < 0) == 3
    turned = body_quality.oriented(nodes, tets)
    assert np.allclose(body_quality.signed_volumes(nodes, turned), 1 / 6)
    assert np.array_equal(np.sort(turned, axis=1), np.sort(tets, axis=1))
    kept, renumbered = body_quality.compacted(nodes, turned)
    assert len(kept) == 8 and np.array_equal(kept[renumbered], nodes[turned])
    faces = body_quality.boundary_faces(renumbered)
    p = kept[faces]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert len(faces) == 12  # two triangles per side of the cube, each pointing away from its centre
    assert np.all(np.einsum("ij,ij->i", normals, p.mean(axis=1) - 0.5) > 0)
    # a right-angled corner of the cube: dihedral angles of 90° at the three edges there
    angles = body_quality.dihedral_angles_deg(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]),
                                              np.array([[0, 1, 2, 3]]))
    assert np.allclose(np.sort(angles[0]), [np.degrees(np.arccos(1 / np.sqrt(3)))] * 3 + [90.0] * 3)
