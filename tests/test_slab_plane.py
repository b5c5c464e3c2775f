"""The slab's own 2-D mesh (`layer_check.in_plane_scale`, docs/model.md §13): the layer's nodes and targets as
points of a coarser slab, a trial's perturbation carried to it, the resolution ladder over both directions."""

import numpy as np
import pytest
import yaml

from scissor_cli.config import parse_config
from scissor_cli.experiments.build import build_model
from scissor_cli.layer3d.check import plane_ladder, plane_spec, slab_spec
from scissor_cli.layer3d.slab import build_slab, layer_probe, slab_probe
from scissor_cli.mesh.mesh import locate
from scissor_cli.solvers.equilibrium import solve_equilibrium
from tests.helpers import example_dict


def _config(**layer_check):
    data = example_dict()
    data["layer_check"] = {"height_mm": 16.0, "layer_z_mm": 8.0, "first_layer_mm": 2.0, "max_layer_mm": 4.0,
                           **layer_check}
    data["tissue"]["mesh"]["scale"] = 2.0
    return parse_config(yaml.safe_dump(data), "scene.yaml")


@pytest.fixture(scope="module")
def scene_and_slabs():
    """The layer (mesh scale 2), its slab on the layer's own mesh and on a plane 3x coarser."""
    fine_cfg, coarse_cfg = _config(), _config(in_plane_scale=3.0)
    scene, mesh, model = build_model(fine_cfg)
    return (scene, mesh, model, build_slab(scene, mesh, slab_spec(fine_cfg.layer_check, fine_cfg.tissue.mesh)),
            build_slab(scene, mesh, slab_spec(coarse_cfg.layer_check, coarse_cfg.tissue.mesh)))


def test_on_the_layers_mesh_the_layer_probe_is_the_layer_nodes(scene_and_slabs):
    """Extruding the layer's own mesh, the layer's nodes are the slab's layer-level nodes, bit for bit."""
    _, mesh, _, fine, _ = scene_and_slabs
    assert fine.mesh.plane is mesh
    x = fine.rest + np.random.default_rng(0).normal(size=fine.rest.shape)
    assert np.array_equal(layer_probe(fine, mesh).positions(x), x[fine.mesh.layer_nodes])


def test_a_coarser_plane_carries_the_layer_nodes_and_targets(scene_and_slabs):
    """On a coarser plane, the layer's nodes and the targets sit at their rest positions at the layer's height;
    the plane has fewer nodes but keeps the targets as vertices."""
    scene, mesh, _, fine, coarse = scene_and_slabs
    plane = coarse.mesh.plane
    assert plane is not mesh and plane.n_nodes < 0.8 * mesh.n_nodes
    z = coarse.mesh.levels_mm[coarse.mesh.layer_level]
    at_rest = layer_probe(coarse, mesh).positions(coarse.rest)
    np.testing.assert_allclose(at_rest[:, :2], mesh.nodes, atol=1e-9)
    np.testing.assert_allclose(at_rest[:, 2], z)
    rests = np.array([t.rest for t in scene.targets])
    probe = slab_probe(coarse, rests)
    assert np.allclose(probe.bary.max(axis=1), 1.0)  # a target is a vertex of the plane
    np.testing.assert_allclose(probe.positions(coarse.rest)[:, :2], rests, atol=1e-9)


def test_a_coarser_plane_moves_the_targets_as_the_layers_mesh_does(scene_and_slabs):
    """The same strokes move the targets of the 3x coarser slab within 15 % of the fine slab's displacement (the
    in-plane discretisation error the accuracy ladder measures)."""
    scene, _, _, fine, coarse = scene_and_slabs
    rests = np.array([t.rest for t in scene.targets])
    strokes = np.array([4.0])
    u = []
    for slab in (fine, coarse):
        probe = slab_probe(slab, rests)
        u.append(probe.positions(solve_equilibrium(slab, strokes).x) - probe.positions(slab.rest))
    scale = np.linalg.norm(u[0], axis=1).max()
    assert scale > 0.1
    assert np.linalg.norm(u[1] - u[0], axis=1).max() < 0.15 * scale


def test_a_trials_e_field_reaches_the_coarser_plane(scene_and_slabs):
    """The truth's E field, one value per layer triangle, reaches each tetrahedron of a coarser slab from the
    layer triangle that holds its plane triangle's centroid; the view's layer is the layer's nodes."""
    from scissor_cli.control import TruthPerturbation
    from scissor_cli.layer3d.truth import SlabTruth

    scene, mesh, model, _, _ = scene_and_slabs
    coarse = _config(in_plane_scale=3.0)
    truth = SlabTruth(model, slab_spec(coarse.layer_check, coarse.tissue.mesh))
    sm = truth.slab.mesh
    E_field = 1.0 + np.arange(mesh.n_elements) / mesh.n_elements  # a distinct value per layer triangle
    tissue, view = truth.for_target(scene.targets[0].rest)(TruthPerturbation(E_scale=E_field))
    centroids = sm.plane.nodes[sm.plane.triangles].mean(axis=1)[sm.element_triangle]
    holder = locate(mesh, centroids)[0]
    np.testing.assert_allclose(tissue.element_E_kPa / truth.slab.element_E_kPa, E_field[holder], rtol=1e-12)
    np.testing.assert_allclose(view.layer(truth.slab.rest), mesh.nodes, atol=1e-9)


def test_plane_ladder_scales_the_layers_mesh():
    cfg = _config(in_plane_scale=1.5)
    ladder = plane_ladder(cfg.layer_check, cfg.tissue.mesh)
    assert [s for s, _ in ladder] == [1.5, 2.25, 3.0, 3.75, 4.5]
    m = cfg.tissue.mesh
    assert ladder[0][1] == plane_spec(cfg.tissue.mesh, 1.5)
    assert ladder[0][1][:2] == (m.min_edge_mm * 3.0, m.max_edge_mm * 3.0)
    assert plane_spec(_config(), 1.0) is None


def test_resolution_ladder_picks_the_smallest_slab_within_the_accuracy(scene_and_slabs):
    """Both ladders are listed, the configured slab first; the pick has the fewest tetrahedra of the candidates
    whose error is within the accuracy, and no candidate with fewer was within it (a loose accuracy, on one ladder:
    tests/test_layer_check.py)."""
    from scissor_cli.layer3d.resolution import choose_slab

    _, _, model, _, _ = scene_and_slabs
    cfg = _config()
    planes = plane_ladder(cfg.layer_check, cfg.tissue.mesh)[:3]
    accuracy = 0.02
    choice = choose_slab(model, slab_spec(cfg.layer_check, cfg.tissue.mesh), [np.array([4.0])], accuracy, planes=planes)
    rungs = choice.candidates
    assert rungs[0].in_plane_scale == 1.0 and {r.in_plane_scale for r in rungs} == {1.0, 1.5, 2.0}
    within = [r for r in rungs if 0 <= r.error_mm <= accuracy]
    assert choice.chosen.n_tetrahedra == min(r.n_tetrahedra for r in within)
    tried = [r for r in rungs if r.error_mm >= 0]
    assert all(r.error_mm > accuracy for r in tried if r.n_tetrahedra < choice.chosen.n_tetrahedra)
    assert min(r.n_tetrahedra for r in rungs) < rungs[0].n_tetrahedra / 4


def test_the_slab_budget_counts_the_coarser_plane():
    """A slab too large on the layer's mesh validates with a coarser plane (the estimate uses the plane's mesh)."""
    from scissor_cli.config import ConfigError

    data = example_dict()
    data["layer_check"] = {"height_mm": 60.0, "layer_z_mm": 30.0, "max_layer_mm": 0.6}
    with pytest.raises(ConfigError, match="tetrahedra"):
        parse_config(yaml.safe_dump(data), "a.yaml")
    data["layer_check"]["in_plane_scale"] = 4.0
    assert parse_config(yaml.safe_dump(data), "a.yaml").layer_check.in_plane_scale == 4.0
