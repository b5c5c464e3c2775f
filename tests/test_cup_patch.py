"""A cup's patch on the body (docs/model.md §21): its area is the cup's on any mesh, not the mesh's."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import yaml

from scissor_cli.config import parse_config
from scissor_cli.experiments.build import body_model
from scissor_cli.mechanics.body_tissue import build_body, cup_patch, held_nodes, skin_areas, skin_nodes
from scissor_cli.mechanics.tissue import BoundaryError

SCENE = {
    "name": "patch-dome",
    "tissue": {"shape": "dome", "radius_mm": 40.0, "height_mm": 25.0, "fixed": ["base"],
               "mesh": {"max_edge_mm": 8.0, "min_edge_mm": 2.5}},
    "material": {"model": "neo_hookean", "E_kPa": 10.0, "nu": 0.45},
    "cups": [{"name": "side", "contact_mm": [0.0, 38.5, 8.0], "radius_mm": 5.0, "stroke_mm": [-10.0, 10.0]}],
    "targets": [{"name": "T1", "position_mm": [5.0, 10.0, 10.0], "radius_mm": 3.0}],
    "needle": {"direction": [-1.0, 0.0, 0.0]},
    "solver": {"kind": "newton"},
    "trials": {"count": 0},
}


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    cfg = parse_config(yaml.safe_dump(SCENE), "patch.yaml", tmp_path_factory.mktemp("patch"))
    return [body_model(cfg, scale=scale)[:2] for scale in (1.4, 1.0, 0.7)]


@pytest.mark.parametrize("level", [0, 1, 2])
def test_the_gripped_skin_shares_add_up_to_the_cups_area_within_one_nodes_share(meshes, level):
    scene, mesh = meshes[level]
    cup = scene.cups[0]
    skin = skin_nodes(scene, mesh, held_nodes(scene, mesh))
    share = dict(zip(skin.tolist(), skin_areas(mesh, skin)))
    patch = cup_patch(mesh, skin, cup.contact, cup.radius_mm)
    gripped = sum(share[n] for n in patch.tolist())
    # the next node out, by distance from the contact: the one the area rule weighed against the last one in
    outside = np.setdiff1d(skin, patch)
    nearest_out = outside[np.argmin(np.linalg.norm(mesh.nodes[outside] - cup.contact, axis=1))]
    last_in = patch[np.argmax(np.linalg.norm(mesh.nodes[patch] - cup.contact, axis=1))]
    bound = 0.5 * max(share[int(last_in)], share[int(nearest_out)])
    assert abs(gripped - np.pi * cup.radius_mm**2) <= bound
    # the patch is the nodes nearest the contact: none outside is nearer than one inside
    assert (np.linalg.norm(mesh.nodes[patch] - cup.contact, axis=1).max()
            <= np.linalg.norm(mesh.nodes[outside] - cup.contact, axis=1).min())


def test_the_skin_shares_add_up_to_the_skins_area(meshes):
    scene, mesh = meshes[0]
    faces = mesh.boundary_triangles[~mesh.boundary_base]
    p = mesh.nodes[faces]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    skin = np.unique(faces)
    assert skin_areas(mesh, skin).sum() == pytest.approx(area, rel=1e-12)


def test_a_cup_smaller_than_the_mesh_at_it_is_refused_with_the_reason(meshes):
    scene, mesh = meshes[0]
    tiny = replace(scene, cups=(replace(scene.cups[0], radius_mm=0.2),))
    with pytest.raises(BoundaryError, match="smaller than the mesh"):
        build_body(tiny, mesh, element="p1")
