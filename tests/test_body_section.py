"""The paper's reduction on a body (docs/model.md §19, "Control"; `config.body_section`): `controller.model: layer`
makes the controller's model the 2-D layer on the body's section through the lesion, in the plane of the cup's
axis and the needle, and drives the 3-D body with it.

The section of a dome is checked against a layer built independently from the dome's formula; a run with the
layer model puts the lesion on its needle as the camera above sees it; the sections a layer cannot be made of
exit 2.
"""

from __future__ import annotations

import copy

import h5py
import numpy as np
import pytest
import yaml
from scenes.body_surfaces import box, write_stl

from scissor_cli import geometry
from scissor_cli.config import Config, ConfigError, parse_config
from scissor_cli.config.body_section import section_config, section_plane
from scissor_cli.control.plant import Controller
from scissor_cli.experiments.build import build_model, section_model
from scissor_cli.mesh.probe import probe_targets, target_positions

from helpers import simulate_here, write_scene
from test_cli import run_cli

RADIUS_MM, HEIGHT_MM, LESION_Z_MM = 40.0, 25.0, 10.0
#: the dome's horizontal section at the lesion's height: x² + y² = r², r = R √(1 − z²/H²)
SECTION_RADIUS_MM = float(RADIUS_MM * np.sqrt(1.0 - (LESION_Z_MM / HEIGHT_MM) ** 2))

SCENE = {
    "name": "section-dome",
    "seed": 3,
    "tissue": {"shape": "dome", "radius_mm": RADIUS_MM, "height_mm": HEIGHT_MM, "fixed": ["base"],
               "mesh": {"max_edge_mm": 8.0, "min_edge_mm": 2.5}},
    "material": {"model": "neo_hookean_fiber", "E_kPa": 10.0, "nu": 0.45, "eta_kPa": 5.0, "fiber_angle_deg": 30.0},
    "cups": [{"name": "cup", "contact_mm": [0.0, SECTION_RADIUS_MM, LESION_Z_MM], "axis": [0.0, -1.0, 0.0],
              "radius_mm": 5.0, "stroke_mm": [-8.0, 8.0]}],
    "targets": [{"name": "T1", "position_mm": [5.0, 10.0, LESION_Z_MM], "radius_mm": 2.5,
                 "desired_mm": [5.0, 9.7, LESION_Z_MM]}],
    "needle": {"direction": [-1.0, 0.0, 0.0], "margin_mm": 1.0},
    "controller": {"model": "layer"},
    "solver": {"kind": "newton"},
    "forward": [{"name": "push", "strokes": {"cup": 4.0}}],
    "camera": {"position_mm": [0.0, 0.0, 400.0]},
    "robot": {"layer_origin_mm": [100.0, 215.0, 200.0]},
    "trials": {"count": 1, "profile": "ideal"},
}


def _cfg(data: dict = SCENE):
    return parse_config(yaml.safe_dump(data, sort_keys=False), "scene.yaml")


def _moved(tissue, probe, stroke_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The layer's target (2,) mm at a stroke and its J (2, 1) there."""
    c = Controller(tissue, probe, [-8.0], [8.0])
    c.update(np.array([stroke_mm]))
    return target_positions(probe, c.eq.x)[0], c.jacobian


def test_the_section_of_a_dome_is_the_layer_built_from_the_dome_s_formula():
    data = copy.deepcopy(SCENE)
    data["tissue"]["mesh"] = {"max_edge_mm": 2.5, "min_edge_mm": 1.25}  # (both layers meshed alike, and finely)
    cfg = _cfg(data)
    layer, plane = section_config(cfg, 0)
    # the cup's axis −y and the needle −x: the horizontal plane through the lesion; the layer's x is along the
    # needle (the body's −x), its y against the cup's push (the body's y)
    assert np.allclose(plane.basis, [[-1, 0], [0, 1], [0, 0]]) and np.allclose(plane.origin, [0, 0, LESION_Z_MM])
    outline = np.asarray(layer.tissue.polygon_mm)
    assert np.allclose(np.linalg.norm(outline, axis=1), SECTION_RADIUS_MM, rtol=2e-3)
    assert layer.material.fiber_angle_deg == pytest.approx(150.0)  # the body's 30° from x, seen with x reversed
    assert layer.tissue.fixed == ["bottom"]
    # the same layer, built by hand: a circle of the section's radius, the cup at its top pushing down
    by_hand = Config.model_validate({
        "name": "by-hand",
        "tissue": {"shape": "polygon", "fixed": ["bottom"], "thickness_mm": 10.0,
                   "polygon_mm": geometry.circle_polygon([0.0, 0.0], SECTION_RADIUS_MM, 128).tolist(),
                   "mesh": {"max_edge_mm": 2.5, "min_edge_mm": 1.25}},
        "material": dict(SCENE["material"], fiber_angle_deg=150.0),
        "cups": [{"name": "cup", "contact_mm": [0.0, SECTION_RADIUS_MM], "axis": [0.0, -1.0], "radius_mm": 5.0,
                  "stroke_mm": [-8.0, 8.0]}],
        "targets": [{"name": "T1", "position_mm": [-5.0, 10.0]}],
        "solver": {"kind": "newton"},
    })
    _, mesh, tissue = build_model(by_hand)
    section_tissue, section_probe, _ = section_model(cfg, 0)
    for stroke in (4.0, -4.0):
        ours, J_ours = _moved(section_tissue, section_probe, stroke)
        theirs, J_theirs = _moved(tissue, probe_targets(mesh, np.array([[-5.0, 10.0]])), stroke)
        moved = np.linalg.norm(theirs - [-5.0, 10.0])
        assert moved > 0.5  # (the push moves the lesion: the comparison is not of two zeros)
        assert np.linalg.norm(ours - theirs) <= 0.02 * moved
        assert np.linalg.norm(J_ours - J_theirs) <= 0.03 * np.linalg.norm(J_theirs)


def test_the_plane_s_frame_puts_the_cup_on_top_and_the_needle_along_x():
    plane = section_plane(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, -1.0]), np.array([-1.0, 0.0, 0.0]))
    assert np.allclose(plane.basis[:, 1], [0, 0, 1]) and np.allclose(plane.basis[:, 0], [-1, 0, 0])
    assert np.allclose(plane.to_body(plane.to_plane(np.array([[1.0, 2.0, 3.0]]))), [[1.0, 2.0, 3.0]])


def test_a_layer_controlled_dome_puts_the_lesion_on_its_needle_as_the_camera_sees_it(tmp_path):
    with h5py.File(simulate_here(tmp_path, SCENE) / "results.h5", "r") as f:
        plan = f["plan/T1"].attrs
        n = np.asarray(plan["direction"], float)
        error = f["trials/T1/final_error"][()]
        seen = error[:, :2] - np.outer(error[:, :2] @ n[:2], n[:2]) / (n[:2] @ n[:2])  # the camera's x, y
        assert np.linalg.norm(seen, axis=1).max() <= 0.1
        assert f["trials/T1/stop_reason"][0] == b"tolerance"
        assert f["trials/T1/manipulation_miss_mm"][0] <= 0.2  # (the vertical miss, which no camera above sees)
        assert f["/"].attrs["status"] == "complete"


@pytest.mark.parametrize("change, words", [
    ({"cups": [dict(SCENE["cups"][0], contact_mm=[0.0, 30.0, 16.5])]}, ["farther than its radius"]),
    ({"cups": [dict(SCENE["cups"][0], contact_mm=[SECTION_RADIUS_MM, 0.0, LESION_Z_MM], axis=[-1.0, 0.0, 0.0])]},
     ["span no plane"]),
    ({"controller": {"model": "layer", "section_fixed": ["top"]}}, ["fixed side"]),
    ({"controller": {"model": "body", "section_fixed": ["bottom"]}}, ["controller.section_fixed", "layer"]),
])
def test_a_section_the_layer_cannot_be_made_of_is_refused(change, words):
    data = copy.deepcopy(SCENE) | copy.deepcopy(change)
    with pytest.raises(ConfigError) as info:
        _cfg(data)
    for w in words:
        assert w in str(info.value), (w, str(info.value))


def test_a_refused_section_exits_2_through_the_cli(tmp_path):
    data = copy.deepcopy(SCENE)
    data["cups"][0]["contact_mm"] = [0.0, 30.0, 16.5]
    r = run_cli("validate", write_scene(tmp_path, data))
    assert r.returncode == 2 and "controller.model" in r.stderr and "Traceback" not in r.stderr


def test_the_section_of_a_box_is_the_paper_s_rectangle_held_opposite_the_cup(tmp_path):
    """A surface body: a 40 × 30 × 20 mm box held on its base, the cup on its face y = 0 (its inward normal +y).
    The section at the lesion's height is the rectangle, corners kept; the layer on it moves its target as the
    rectangle layer of §1–5 built by hand does (the paper's: the cup on one side, the opposite side held)."""
    write_stl(tmp_path / "box.stl", *box(hi=(40.0, 30.0, 20.0)))
    data = {"name": "box", "tissue": {"shape": "surface", "surface_file": str(tmp_path / "box.stl"),
                                      "fixed": [{"plane": {"point_mm": [0, 0, 0], "normal": [0, 0, 1]}}],
                                      "mesh": {"max_edge_mm": 2.5, "min_edge_mm": 1.25}},
            "material": dict(SCENE["material"], fiber_angle_deg=0.0),
            "cups": [{"name": "cup", "contact_mm": [20.0, 0.0, 10.0], "radius_mm": 5.0, "stroke_mm": [-8.0, 8.0]}],
            "targets": [{"name": "T", "position_mm": [20.0, 15.0, 10.0], "radius_mm": 3.0}],
            "needle": {"direction": [1.0, 0.0, 0.0]}, "controller": {"model": "layer"}}
    cfg = _cfg(data)
    layer, plane = section_config(cfg, 0)
    # the cup's axis +y, the needle +x: the layer's x is the body's x, its y the body's −y (the cup on top)
    assert np.allclose(plane.basis, [[1, 0], [0, -1], [0, 0]])
    outline = np.asarray(layer.tissue.polygon_mm)
    corners = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, -30.0], [0.0, -30.0]])
    assert np.max(np.min(np.linalg.norm(outline[:, None] - corners[None], axis=2), axis=0)) < 0.5
    assert np.allclose(layer.cups[0].contact_mm, [20.0, 0.0], atol=0.05) and np.allclose(layer.cups[0].axis, [0, -1])
    by_hand = Config.model_validate({
        "name": "rectangle", "tissue": {"shape": "rectangle", "size_mm": [40.0, 30.0], "fixed": ["bottom"],
                                        "mesh": {"max_edge_mm": 2.5, "min_edge_mm": 1.25}},
        "material": data["material"],
        "cups": [{"name": "cup", "contact_mm": [20.0, 30.0], "axis": [0.0, -1.0], "radius_mm": 5.0,
                  "stroke_mm": [-8.0, 8.0]}],
        "targets": [{"name": "T", "position_mm": [20.0, 15.0]}], "solver": {"kind": "newton"}})
    _, mesh, tissue = build_model(by_hand)
    section_tissue, section_probe, _ = section_model(cfg, 0)
    ours, J_ours = _moved(section_tissue, section_probe, 4.0)
    theirs, J_theirs = _moved(tissue, probe_targets(mesh, np.array([[20.0, 15.0]])), 4.0)
    theirs = theirs - [0.0, 30.0]  # (the rectangle spans [0, 30] in y, the section [−30, 0])
    moved = np.linalg.norm(theirs - [20.0, -15.0])
    assert moved > 0.5
    assert np.linalg.norm(ours - theirs) <= 0.02 * moved
    assert np.linalg.norm(J_ours - J_theirs) <= 0.03 * np.linalg.norm(J_theirs)
