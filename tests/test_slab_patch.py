"""A cup's patch on the slab (docs/model.md §21, "The cup's patch"): its area is the cup's disc on any mesh."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from scissor_cli.config import parse_config
from scissor_cli.experiments.build import build_model
from scissor_cli.layer3d.slab import SlabSpec, build_slab, side_patch, side_shares
from scissor_cli.mechanics.patch import PATCH_AREA_LIMIT, disc_area_in_strip, nearest_patch
from scissor_cli.mechanics.tissue import BoundaryError
from tests.helpers import example_dict

HEIGHT_MM, LAYER_Z_MM = 30.0, 12.0


@pytest.fixture(scope="module", params=[4.0, 2.5, 1.6])
def slab(request):
    cfg = parse_config(yaml.safe_dump(example_dict()), "scene.yaml")
    scene, mesh, _ = build_model(cfg, mesh_scale=request.param)
    return scene, mesh, build_slab(scene, mesh, SlabSpec(HEIGHT_MM, LAYER_Z_MM, max_layer_mm=4.0))


def test_the_side_shares_add_up_to_the_side_surface(slab):
    _, mesh, tissue = slab
    edges = mesh.boundary_edges
    perimeter = np.linalg.norm(mesh.nodes[edges[:, 0]] - mesh.nodes[edges[:, 1]], axis=1).sum()
    surface, shares = side_shares(tissue.mesh)
    assert np.unique(surface).size == surface.size
    assert shares.sum() == pytest.approx(perimeter * HEIGHT_MM, rel=1e-12)


def test_the_gripped_side_shares_add_up_to_the_cups_disc_within_one_nodes_share(slab):
    scene, _, tissue = slab
    sm = tissue.mesh
    surface, shares = side_shares(sm)
    share = dict(zip(surface.tolist(), shares))
    cup = scene.cups[0]
    patch = tissue.cup_nodes[0]
    centre = np.array([*cup.contact, LAYER_Z_MM])
    distance = dict(zip(surface.tolist(), np.linalg.norm(sm.nodes[surface] - centre, axis=1)))
    free = np.setdiff1d(surface, tissue.fixed_nodes)
    outside = np.setdiff1d(free, patch)
    last_in = max(patch.tolist(), key=distance.get)
    first_out = min(outside.tolist(), key=distance.get)
    gripped = sum(share[n] for n in patch.tolist())
    # the example's cup (radius 5 mm at 12 mm over the chest wall) lies wholly on the face: its disc is π r²
    assert abs(gripped - np.pi * cup.radius_mm**2) <= 0.5 * max(share[last_in], share[first_out])
    assert distance[last_in] <= distance[first_out]  # the nearest nodes, none outside nearer than one inside
    assert np.array_equal(patch, side_patch(sm, tissue.fixed_nodes, cup.contact, cup.radius_mm))


@pytest.mark.parametrize("below, above", [(np.inf, np.inf), (0.0, np.inf), (2.0, 7.0), (1.0, 1.5), (4.9, 0.3)])
def test_a_disc_cut_by_the_faces_ends_has_the_area_of_its_part_between_them(below, above):
    radius = 5.0
    # the part of the disc between the lines, by the midpoint rule over a fine grid
    h = 0.005
    grid = np.arange(-radius + h / 2, radius, h)
    x, y = np.meshgrid(grid, grid)
    inside = (x**2 + y**2 <= radius**2) & (y >= -below) & (y <= above)
    assert disc_area_in_strip(radius, below, above) == pytest.approx(inside.sum() * h * h, rel=2e-3)


def test_a_cup_smaller_than_the_slabs_mesh_at_it_is_refused_with_the_reason(slab):
    scene, mesh, _ = slab
    tiny = replace(scene, cups=(replace(scene.cups[0], radius_mm=0.05),))
    with pytest.raises(BoundaryError, match="grips no free side-surface node"):
        build_slab(tiny, mesh, SlabSpec(HEIGHT_MM, LAYER_Z_MM, max_layer_mm=4.0))


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 60), st.floats(0.1, 200.0), st.integers(0, 2**32 - 1))
def test_a_patch_is_the_nearest_nodes_and_its_area_the_closest_to_the_cups(count, area, seed):
    rng = np.random.default_rng(seed)
    nodes = rng.permutation(1000)[:count]
    points = rng.normal(0.0, 5.0, (count, 3))
    shares = rng.uniform(0.05, 20.0, count)
    contact = rng.normal(0.0, 1.0, 3)
    patch = nearest_patch(nodes, points, shares, contact, area)
    distance = np.linalg.norm(points - contact, axis=1)
    order = np.lexsort((nodes, distance))
    if shares[order[0]] > PATCH_AREA_LIMIT * area:
        assert patch.size == 0
        return
    taken = np.isin(nodes, patch)
    k = int(taken.sum())
    assert k >= 1 and np.array_equal(np.sort(nodes[order[:k]]), patch)  # the k nearest, sorted
    covered = np.cumsum(shares[order])
    assert abs(covered[k - 1] - area) <= np.abs(covered - area).min() + 1e-9 * area  # no count comes closer


def test_two_cups_gripping_the_same_side_nodes_are_refused_with_their_names(slab):
    scene, mesh, _ = slab
    cup = scene.cups[0]
    near = replace(cup, name="second", contact=cup.contact + np.array([1.0, 0.0]))
    with pytest.raises(BoundaryError, match="'second' grip the same side-surface nodes"):
        build_slab(replace(scene, cups=(cup, near)), mesh, SlabSpec(HEIGHT_MM, LAYER_Z_MM, max_layer_mm=4.0))
