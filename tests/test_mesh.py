"""Meshing: quality, grading, obstacles as segments, barycentric tracking."""

import numpy as np
import pytest

from scissor_cli import geometry
from scissor_cli.config import load_config, parse_config
from scissor_cli.experiments.build import scene_of
from scissor_cli.mechanics.tissue import build_tissue
from scissor_cli.mesh.mesh import grip_ends, interpolate, locate, mesh_for_config

from helpers import EXAMPLE


@pytest.fixture(scope="module")
def example():
    cfg = load_config(EXAMPLE)
    scene = scene_of(cfg)
    return cfg, scene, mesh_for_config(scene, cfg.tissue.mesh)


def test_quality_and_size_field(example):
    cfg, scene, mesh = example
    assert mesh.angles_deg().min() >= cfg.tissue.mesh.min_angle_deg - 1e-6
    lengths = mesh.edge_lengths()
    assert lengths.max() <= 1.5 * cfg.tissue.mesh.max_edge_mm
    # graded: edges touching a target are near min_edge, the mesh is coarse far away
    for t in scene.targets:
        node = np.argmin(np.linalg.norm(mesh.nodes - t.rest, axis=1))
        near = np.any(mesh.triangles == node, axis=1)
        assert lengths[near].mean() <= 1.6 * cfg.tissue.mesh.min_edge_mm
    assert np.median(lengths) > 2 * cfg.tissue.mesh.min_edge_mm


#: the example scene's mesh as recorded (2026-11-25, triangle 20250106, x86-64): what may vary between
#: machines is a refinement decision or two on a floating-point tie, so counts are checked within 3 %
EXAMPLE_NODES, EXAMPLE_TRIANGLES = 1377, 2661


def test_what_is_portable_of_the_example_mesh(example):
    """Counts within a few per cent, the size field's edge range, every area accounted for."""
    cfg, scene, mesh = example
    assert abs(mesh.n_nodes - EXAMPLE_NODES) <= 0.03 * EXAMPLE_NODES
    assert abs(mesh.n_elements - EXAMPLE_TRIANGLES) <= 0.03 * EXAMPLE_TRIANGLES
    lengths = mesh.edge_lengths()
    m = cfg.tissue.mesh
    assert lengths.min() >= 0.3 * m.min_edge_mm and lengths.max() <= 1.5 * m.max_edge_mm
    p = mesh.nodes[mesh.triangles]
    area = 0.5 * geometry.cross2(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert area.min() > 0  # counter-clockwise, none degenerate
    assert area.sum() == pytest.approx(abs(geometry.signed_area(scene.outline)), rel=1e-9)
    for k, obstacle in enumerate(scene.obstacles):
        assert area[mesh.element_obstacle == k].sum() == pytest.approx(abs(geometry.signed_area(obstacle.outline)),
                                                                        rel=1e-9)


def test_graded_mesh_is_much_smaller_than_uniform(example):
    cfg, scene, mesh = example
    uniform = mesh_for_config(scene, cfg.tissue.mesh.model_copy(update={"graded": False}))
    assert uniform.n_elements > 3 * mesh.n_elements


def test_targets_are_vertices_and_obstacles_are_resolved(example):
    cfg, scene, mesh = example
    for t in scene.targets:
        assert np.min(np.linalg.norm(mesh.nodes - t.rest, axis=1)) < 1e-12
    for k, obstacle in enumerate(scene.obstacles):
        inside = mesh.element_obstacle == k
        assert inside.sum() > 10
        # every element is wholly inside or outside: all its vertices agree (up to the outline)
        d = geometry.distance_to_boundary(mesh.nodes[mesh.triangles[inside]].reshape(-1, 2), obstacle.outline)
        in_poly = geometry.points_in_polygon(mesh.nodes[mesh.triangles[inside]].reshape(-1, 2), obstacle.outline)
        assert np.all(in_poly | (d < 1e-9))
    tissue = build_tissue(scene, mesh)
    assert np.allclose(tissue.element_E_kPa[mesh.element_obstacle == 0], 30.0)
    assert np.allclose(tissue.element_E_kPa[mesh.element_obstacle == -1], 10.0)


def test_boundary_conditions(example):
    cfg, scene, mesh = example
    tissue = build_tissue(scene, mesh)
    assert np.allclose(mesh.nodes[tissue.fixed_nodes, 1], 0.0)
    assert np.isclose(mesh.nodes[tissue.fixed_nodes, 0].min(), 0)
    assert np.isclose(mesh.nodes[tissue.fixed_nodes, 0].max(), 100)
    grip = mesh.nodes[tissue.cup_nodes[0]]
    assert np.allclose(grip[:, 1], 60.0)
    # the grip ends are vertices: every mesh grips exactly contact ± radius
    assert np.isclose(grip[:, 0].min(), 45.0) and np.isclose(grip[:, 0].max(), 55.0)
    assert len(grip_ends(scene)) == 2


def test_locate_and_interpolate_round_trip(example):
    _, _, mesh = example
    rng = np.random.default_rng(0)
    pts = rng.uniform([1, 1], [99, 59], size=(200, 2))
    tri, bary = locate(mesh, pts)
    assert np.allclose(bary.sum(axis=1), 1) and np.all(bary > -1e-9)
    assert np.allclose(interpolate(mesh.nodes, mesh.triangles, tri, bary), pts)
    # an affine motion is carried exactly
    A = np.array([[1.1, 0.2], [-0.1, 0.9]])
    assert np.allclose(interpolate(mesh.nodes @ A.T + 3, mesh.triangles, tri, bary), pts @ A.T + 3)
    with pytest.raises(ValueError, match="outside the mesh"):
        locate(mesh, np.array([[150.0, 10.0]]))


@pytest.mark.parametrize(
    "tissue",
    [
        "{shape: ellipse, size_mm: [80, 50], fixed: [bottom]}",
        "{shape: polygon, polygon_mm: [[0, 0], [90, 0], [80, 50], [10, 50]], fixed: [bottom]}",
    ],
)
def test_other_layer_shapes(tissue):
    cfg = parse_config(f"tissue: {tissue}\ncups: [{{name: c, contact_mm: [40, 50], axis: [0, -1]}}]\n"
                       "targets: [{name: t, position_mm: [40, 25]}]\n")
    scene = scene_of(cfg)
    mesh = mesh_for_config(scene, cfg.tissue.mesh)
    assert mesh.angles_deg().min() >= cfg.tissue.mesh.min_angle_deg - 1e-6
    area = build_tissue(scene, mesh).ops.area.sum()
    assert np.isclose(area, abs(geometry.signed_area(scene.outline)), rtol=1e-9)
    tissue_model = build_tissue(scene, mesh)
    assert len(tissue_model.fixed_nodes) > 3 and len(tissue_model.cup_nodes[0]) >= 3
