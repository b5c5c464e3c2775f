"""A body's lesion is carried as its region's mean (`Tissue.probe`, `LinearSimplex.mean_probe`; docs/model.md §21).

The needle's friction acts along a line through the lesion, where the displacement of a single point has no limit
under refinement; the mean over the lesion's region has one (benchmarks/bench_insertion_elements.py measures
both). The mean's weights are the region's integrals of the shape functions, nudged to read the configured centre
at rest: so the probe carries every affine map exactly, as a point's does.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from scissor_cli.config.loading import parse_config
from scissor_cli.experiments.build import body_model
from scissor_cli.mechanics.tissue import lesion_regions
from scissor_cli.mesh.probe import stacked_probes, target_positions

from test_body_insertion import COARSE
from test_element_interface import _layer


@pytest.fixture(scope="module")
def body():
    _, mesh, tissue = body_model(parse_config(yaml.safe_dump(COARSE), "<test>"))
    return mesh, tissue


def test_a_lesion_is_its_regions_mean_and_reads_its_centre_at_rest(body):
    mesh, tissue = body
    centres = np.array([t.rest for t in tissue.scene.targets])
    probe = tissue.probe(centres)
    assert probe.nodes.shape[1] > 4  # a region's nodes, not a tetrahedron's corners
    np.testing.assert_allclose(probe.bary.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(target_positions(probe, tissue.rest), centres, atol=1e-9)
    for k, target in enumerate(tissue.scene.targets):
        region = mesh.tetrahedra[mesh.region == mesh.region_names.index(target.name)]
        used = probe.nodes[k][probe.bary[k] > 0]
        assert np.all(probe.bary[k] >= 0) and set(used) == set(np.unique(region))
        # the element holding the centre, for reference, as a point's probe gives
        assert probe.tri_idx[k] == tissue.element.probe(tissue.rest, centres[k:k + 1]).tri_idx[0]


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-0.3, 0.3), min_size=12, max_size=12))
def test_the_mean_carries_any_affine_map_exactly(body, entries):
    _, tissue = body
    A = np.eye(3) + np.reshape(entries[:9], (3, 3))
    b = 10.0 * np.asarray(entries[9:])
    centres = np.array([t.rest for t in tissue.scene.targets])
    probe = tissue.probe(centres)
    np.testing.assert_allclose(target_positions(probe, tissue.rest @ A.T + b), centres @ A.T + b, atol=1e-9)


def test_the_weights_are_the_regions_integrals_of_the_shape_functions(body):
    """Two tetrahedra whose joint centroid is the centre: no nudge, each node's weight Σ V_e / (4 V)."""
    _, tissue = body
    rng = np.random.default_rng(0)
    cells = rng.choice(tissue.mesh.n_elements, 2, replace=False)
    corners = tissue.ops.triangles[cells]
    volume = tissue.ops.volume[cells]
    centroid = (volume[:, None] * tissue.rest[corners].mean(axis=1)).sum(axis=0) / volume.sum()
    probe = tissue.element.mean_probe(tissue.rest, cells, centroid)
    expected = {}
    for e in range(2):
        for a in corners[e]:
            expected[a] = expected.get(a, 0.0) + volume[e] / (4.0 * volume.sum())
    got = dict(zip(probe.nodes[0].tolist(), probe.bary[0]))
    assert got.keys() == expected.keys()
    np.testing.assert_allclose([got[a] for a in expected], list(expected.values()), rtol=1e-9)


def test_the_mean_is_refused_for_no_region_or_a_centre_it_cannot_read(body):
    _, tissue = body
    with pytest.raises(ValueError, match="at least one element"):
        tissue.element.mean_probe(tissue.rest, np.zeros(0, np.int64), np.zeros(3))
    cells = lesion_regions(tissue)[0][1]
    with pytest.raises(ValueError, match="too far"):
        tissue.element.mean_probe(tissue.rest, cells, lesion_regions(tissue)[0][0] + 50.0)


def test_other_points_keep_the_elements_probe_and_rows_stack_in_order(body):
    _, tissue = body
    centres = np.array([t.rest for t in tissue.scene.targets])
    other = centres[0] + np.array([0.0, 0.0, -5.0])
    points = np.vstack([centres[0], other, centres[1]])
    probe = tissue.probe(points)
    rng = np.random.default_rng(3)
    x = tissue.rest + 0.5 * rng.standard_normal(tissue.rest.shape)  # any nodal field
    one_by_one = [target_positions(tissue.probe(p[None]), x)[0] for p in points]
    np.testing.assert_allclose(target_positions(probe, x), one_by_one, atol=1e-12)
    np.testing.assert_allclose(target_positions(tissue.probe(other[None]), x),
                               target_positions(tissue.element.probe(tissue.rest, other[None]), x), atol=1e-12)
    assert probe.bary[1, 4:].max() == 0.0  # a point's row, padded
    padded = stacked_probes([tissue.element.probe(tissue.rest, other[None]), tissue.probe(centres[:1])])
    np.testing.assert_allclose(target_positions(padded, x), [one_by_one[1], one_by_one[0]], atol=1e-12)


def test_the_layer_has_no_lesion_regions_and_keeps_points():
    layer = _layer("nodal")
    assert lesion_regions(layer) == []
    points = np.array([t.rest for t in layer.scene.targets])
    probe, element_probe = layer.probe(points), layer.element.probe(layer.rest, points)
    np.testing.assert_array_equal(probe.nodes, element_probe.nodes)
    np.testing.assert_array_equal(probe.bary, element_probe.bary)
