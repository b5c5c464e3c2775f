"""A 3-D scene's config (docs/contract.md, "3-D scenes"): the normative dome validates, and every bad input is one
clear message naming the field — exit 2 through the CLI, never a traceback."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml

from scissor_cli.config import ConfigError, parse_config, resolved_yaml
from scissor_cli.config.body_checks import DomeSurface
from scissor_cli.config.body_sections import BodyConfig

from helpers import ROOT, cli_here, example_dict, write_scene
from test_cli import run_cli

DOME = ROOT / "configs" / "example_dome.yaml"


def dome() -> dict:
    return yaml.safe_load(DOME.read_text())


def refused(data: dict, *words: str) -> str:
    with pytest.raises(ConfigError) as info:
        parse_config(yaml.safe_dump(data, sort_keys=False), "scene.yaml")
    message = str(info.value)
    assert message.startswith("scene.yaml"), message
    for w in words:
        assert w in message, (w, message)
    return message


def test_the_normative_dome_validates_and_round_trips():
    cfg = parse_config(DOME.read_text(), "example_dome.yaml")
    assert isinstance(cfg, BodyConfig) and cfg.tissue.shape == "dome"
    assert cfg.targets[0].position_mm == [10.0, 20.0, 15.0] and cfg.obstacles[0].tube.radius_mm == 1.5
    assert parse_config(resolved_yaml(cfg), "resolved") == cfg


def _with(path: str, value) -> dict:
    data = dome()
    node = data
    keys = path.split(".")
    for k in keys[:-1]:
        node = node[int(k)] if isinstance(node, list) else node[k]
    last = keys[-1]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return data


@pytest.mark.parametrize("path, value, words", [
    ("targets.0.position_mm", [0.0, 0.0, 50.0], ["targets[0].position_mm", "outside the body"]),
    ("targets.0.position_mm", [0.0, 0.0, 34.0], ["targets[0].radius_mm", "out of the body"]),
    ("targets.0.position_mm", [0.0, 0.0, 1.0], ["targets[0].radius_mm", "out of the body"]),
    ("obstacles.1.sphere.center_mm", [100.0, 0.0, 10.0], ["obstacles[1].sphere", "outside the body"]),
    ("obstacles.1.sphere.center_mm", [10.0, 22.0, 15.0], ["obstacles[1].sphere", "overlaps lesion 'T1'"]),
    ("obstacles.0.tube.points_mm", [[26.0, 23.0, 15.0]], ["obstacles[0].tube.points_mm", "2"]),
    ("cups.0.contact_mm", [0.0, 0.0, 100.0], ["cups[0].contact_mm", "from the skin"]),
    ("cups.0.contact_mm", [0.0, 60.0, 2.0], ["cups[0].contact_mm", "held base"]),
    ("cups.0.axis", [0.0, -2.0, 0.0], ["cups[0].axis", "unit vector"]),
    ("targets.0.name", "skin", ["targets[0].name", "region"]),
    ("tissue.radius_mm", None, ["tissue.radius_mm", "a dome needs radius_mm"]),
    ("tissue.fixed", [{"plane": {"point_mm": [0, 0, 0], "normal": [0, 0, 1]}}], ["tissue.fixed", "base"]),
    ("tissue.skin", {"thickness_mm": 30.0}, ["tissue.skin.thickness_mm", "half"]),
    ("trials", {"count": 0, "truth": "slab"}, ["trials.truth", "body itself"]),
    ("targets.0.position_mm", [0.0, float("nan"), 10.0], ["targets[0].position_mm"]),
    ("needle.cone_deg", 90.0, ["needle.cone_deg", "89"]),
    ("solver.kind", "admm", ["solver.kind", "newton"]),
])
def test_bad_3d_input_is_one_message_naming_the_field(path, value, words):
    refused(_with(path, value), *words)


def test_overlapping_patches_and_obstacles_are_refused():
    data = dome()
    data["cups"].append(dict(copy.deepcopy(data["cups"][0]), name="cup2", contact_mm=[3.0, 57.4, 10.0]))
    refused(data, "cups[1].contact_mm", "overlap")
    data = dome()
    data["obstacles"][1]["sphere"]["center_mm"] = [35.0, 23.0, 15.0]  # on the vessel
    refused(data, "obstacles[1].sphere", "overlap")


def test_a_2d_field_in_a_3d_scene_and_the_reverse_say_which_shape_takes_it():
    data = dome()
    data["tissue"]["size_mm"] = [100.0, 60.0]
    refused(data, "tissue.size_mm", "2-D layer", "rectangle")
    data = dome()
    data["cups"][0]["contact_mm"] = [0.0, 57.5]
    refused(data, "cups[0].contact_mm", "3")
    layer = example_dict()
    layer["tissue"]["radius_mm"] = 60.0
    refused(layer, "tissue.radius_mm", "3-D scene", "dome")
    layer = example_dict()
    layer["targets"][0]["radius_mm"] = 2.0
    refused(layer, "targets[0].radius_mm", "3-D scene")


def test_cups_move_onto_the_skin():
    from scissor_cli.scene.body_scene import build_body_scene

    data = dome()
    data["cups"][0]["contact_mm"] = [0.0, 60.0, 10.0]  # 2 mm outside the skin, within the cup's radius
    data["cups"][0].pop("axis")
    cfg = parse_config(yaml.safe_dump(data), "scene.yaml")
    cup = build_body_scene(cfg).cups[0]
    surface = DomeSurface(60.0, 35.0)
    assert abs(surface.depth(cup.contact[None])[0]) < 1e-9  # on the skin
    assert np.linalg.norm(cup.contact - [0.0, 60.0, 10.0]) < 5.0
    n = cup.contact / np.array([60.0, 60.0, 35.0]) ** 2
    np.testing.assert_allclose(cup.axis, -n / np.linalg.norm(n), atol=1e-12)  # the inward normal


def test_bad_3d_input_exits_2_through_the_cli(tmp_path):
    data = _with("targets.0.position_mm", [0.0, 0.0, 50.0])
    for command in (["validate"], ["simulate", "--trials", "0", "--out", str(tmp_path / "run")]):
        r = run_cli(*command[:1], write_scene(tmp_path, data), *command[1:])
        assert r.returncode == 2, r.stderr
        assert "Traceback" not in r.stderr and "targets[0].position_mm" in r.stderr


def test_options_and_models_that_a_body_does_not_take_exit_2(tmp_path):
    scene = write_scene(tmp_path, dome())
    for option in (["--study"], ["--truth", "slab"], ["--solver", "admm"]):
        r = _refused_here("simulate", scene, "--trials", "0", *option, "--out", str(tmp_path / "run"))
        assert "3-D" in r.stderr
    data = dome()
    data["controller"]["mesh_scale"] = 0.5  # the model's body is never finer than the truth's
    r = _refused_here("validate", write_scene(tmp_path, data))
    assert "controller.mesh_scale" in r.stderr


def _refused_here(*args):
    """`scissor ARGS` in this process (`cli_here`), checked to exit 2 with a message and no traceback (the exit as a
    process: test_bad_3d_input_exits_2_through_the_cli)."""
    r = cli_here(*args)
    assert r.exit_code == 2 and isinstance(r.exception, SystemExit), (r.exit_code, r.output)
    assert "Traceback" not in r.output and r.stderr.startswith("error: "), r.output
    return r


def test_a_mesh_over_the_budget_is_refused_before_meshing(tmp_path):
    data = dome()
    data["tissue"]["mesh"] = {"min_edge_mm": 0.3, "max_edge_mm": 0.6}
    r = _refused_here("validate", write_scene(tmp_path, data))
    assert "tissue.mesh" in r.stderr and "budget" in r.stderr


@pytest.mark.parametrize("content, words", [
    (None, "surface_file"),  # missing
    (b"\x00\xff garbage", "surface_file"),
    (b"solid open\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\n"
     b"endsolid open\n", "surface_file"),
])
def test_a_bad_surface_file_exits_2_naming_the_field(tmp_path, content, words):
    if content is not None:
        (tmp_path / "body.stl").write_bytes(content)
    data = {"tissue": {"shape": "surface", "surface_file": "body.stl",
                       "fixed": [{"plane": {"point_mm": [0, 0, 0], "normal": [0, 0, 1]}}]}, "trials": {"count": 0}}
    r = _refused_here("validate", write_scene(tmp_path, data))
    assert words in r.stderr and "body.stl" in r.stderr
