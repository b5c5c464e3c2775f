"""The tip force's zone (docs/model.md §12, "Tip force"): the kernel over the tissue just ahead of the tip as
consistent nodal loads, in 2-D and 3-D; continuous as the tip moves, whatever the mesh."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from scissor_cli.config import parse_config
from scissor_cli.experiments.build import build_model
from scissor_cli.insertion.capture import free_nodes
from scissor_cli.insertion.needle import transverse_basis
from scissor_cli.insertion.tip_zone import tip_weights, unit_stencil, zone_mesh
from scissor_cli.layer3d.slab import SlabSpec, build_slab

from helpers import example_dict

#: the kernel's centroid ahead of the tip, in units of R: ∫ρ^d (1−ρ²)² dρ · E[cos θ] / ∫ρ^(d−1) (1−ρ²)² dρ over
#: the half-disc (E[cos θ] = 2/π) and the half-ball (1/2)
CENTROID = {2: (8 / 105) * (2 / np.pi) / (1 / 6), 3: (1 / 24) * 0.5 / (8 / 105)}


@pytest.fixture(scope="module")
def tissues():
    data = example_dict()
    data["tissue"]["mesh"]["scale"] = 2.0
    scene, mesh, tissue = build_model(parse_config(yaml.safe_dump(data), "scene.yaml"))
    slab = build_slab(scene, mesh, SlabSpec(8.0, 4.0, levels_mm=(0.0, 3.0, 4.0, 5.0, 8.0)))
    return {2: tissue, 3: slab}


def _frame(n):
    n = np.asarray(n, float) / np.linalg.norm(n)
    return np.vstack([n, transverse_basis(n)])


@pytest.mark.parametrize("d", [2, 3])
def test_the_stencil_integrates_the_kernel_over_the_half_zone(d):
    points, w = unit_stencil(d)
    assert w.sum() == pytest.approx(1.0) and np.all(w > 0)
    assert np.all(points[:, 0] > 0) and np.all(np.linalg.norm(points, axis=1) < 1)  # ahead, inside
    centroid = w @ points
    assert centroid[0] == pytest.approx(CENTROID[d], rel=0.01)
    np.testing.assert_allclose(centroid[1:], 0.0, atol=1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_the_loads_sum_to_one_on_free_nodes_and_reproduce_the_kernels_centroid(tissues, d):
    tissue = tissues[d]
    n = np.array([1.0, 0.3] if d == 2 else [1.0, 0.3, 0.0])
    frame = _frame(n)
    tip = np.array([30.0, 30.0] if d == 2 else [30.0, 30.0, 4.0])
    R = 2.0 if d == 2 else 0.9  # (a 3-D zone within the slab's levels 3-5 mm: clear of the held face z = 0)
    nodes, w = tip_weights(tissue, tissue.rest, tip, frame, R, free_nodes(tissue), zone_mesh(tissue))
    assert w.sum() == pytest.approx(1.0) and np.all(w > 0)
    assert np.isin(nodes, free_nodes(tissue)).all()
    # linear shape functions reproduce positions: the loads' centroid is the kernel's, R·c along n ahead
    np.testing.assert_allclose(w @ tissue.rest[nodes], tip + R * CENTROID[d] * frame[0], atol=0.01 * R)


def test_the_loads_move_continuously_with_the_tip_on_a_coarse_mesh(tissues):
    """The kernel at the nodes jumped by the whole force when the tip passed its one or two nodes; the
    consistent loads of a zone finer than the mesh change by little for a small move of the tip."""
    tissue = tissues[2]
    frame = _frame([1.0, 0.0])
    zone, free = zone_mesh(tissue), free_nodes(tissue)
    dense = []
    for s in np.arange(5.0, 40.0, 0.02):
        nodes, w = tip_weights(tissue, tissue.rest, np.array([s, 32.0]), frame, 2.0, free, zone)
        v = np.zeros(tissue.mesh.n_nodes)
        v[nodes] = w
        dense.append(v)
    jumps = np.abs(np.diff(np.array(dense), axis=0)).sum(axis=1)
    assert jumps.max() <= 0.05


def test_a_zone_outside_the_tissue_falls_on_the_nearest_free_node(tissues):
    tissue = tissues[2]
    free = free_nodes(tissue)
    far = np.array([-50.0, 30.0])
    nodes, w = tip_weights(tissue, tissue.rest, far, _frame([-1.0, 0.0]), 2.0, free, zone_mesh(tissue))
    assert nodes.size == 1 and w[0] == 1.0
    assert nodes[0] == free[np.argmin(np.linalg.norm(tissue.rest[free] - far, axis=1))]
