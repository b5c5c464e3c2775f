"""Config validation: the example scene passes, each class of bad input fails with one clear message.

The contract (docs/contract.md, "Config"): exit 2 with one message naming
the file, the dotted field, the YAML line and what is allowed — for bad
bytes, bad YAML, bad values of any field, and meshes over the element budget.
"""

import os
import subprocess
import sys
import time
import typing

import numpy as np
import pytest
import yaml
from pydantic import BaseModel

from scissor_cli.config import (
    ELEMENT_BUDGET,
    MAX_CONFIG_BYTES,
    Config,
    ConfigError,
    checks,
    estimate_elements,
    load_config,
    loading,
    parse_config,
    resolved_yaml,
)
from scissor_cli.config import element_budget as budget
from scissor_cli.config.messages import _unwrap, field_type

from helpers import EXAMPLE, ROOT, cli_here, deep_update, example_dict, write_scene


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "scissor_cli.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd)


def parse(data: dict) -> Config:
    return parse_config(yaml.safe_dump(data, sort_keys=False), "scene.yaml")


def refused(text_or_data, *words) -> str:
    """The ConfigError message for a scene (YAML text or data), checked to contain every word."""
    text = text_or_data if isinstance(text_or_data, str) else yaml.safe_dump(text_or_data, sort_keys=False)
    with pytest.raises(ConfigError) as info:
        parse_config(text, "scene.yaml")
    message = str(info.value)
    assert message.startswith("scene.yaml"), message
    for w in words:
        assert w in message, (w, message)
    return message


def test_example_scene_validates_unchanged():
    cfg = load_config(EXAMPLE)
    assert cfg.name == "paper-push" and cfg.seed == 7
    assert [c.name for c in cfg.forward] == ["push10", "pull8"]
    assert cfg.targets[1].desired_mm == [58.0, 20.5]


def test_resolved_yaml_round_trips():
    cfg = load_config(EXAMPLE)
    again = parse_config(resolved_yaml(cfg), "resolved")
    assert again == cfg


def test_validate_command_prints_resolved_config():
    proc = run_cli("validate", EXAMPLE)
    assert proc.returncode == 0, proc.stderr
    assert "min_angle_deg: 28.0" in proc.stdout and "grading:" in proc.stdout  # defaults filled in


BAD = [
    # (dotted field, value, words the message must contain)
    ("material.E_kPa", 0.0, ["material.E_kPa", "a finite number in [0.001, 1e+06]", "got 0.0"]),
    ("material.E_kPa", "10", ["material.E_kPa", "a finite number", "YAML read 10 as text", "got '10'"]),
    ("material.E_kPa", float("nan"), ["material.E_kPa", "a finite number in [0.001, 1e+06]", "got nan"]),
    ("material.E_kPa", float("-inf"), ["material.E_kPa", "finite", "got -inf"]),
    ("material.E_kPa", True, ["material.E_kPa", "a finite number", "got True"]),
    ("material.nu", 0.5, ["material.nu", "(-1, 0.5)"]),
    ("material.nu", -1.0, ["material.nu", "(-1, 0.5)"]),
    ("material.eta_kPa", -1.0, ["material.eta_kPa", "[0, 1e+06]"]),
    ("material.model", "mooney", ["material.model", "'linear'", "'neo_hookean_fiber'"]),
    ("seed", 10**30, ["seed", "an integer in [0, 9223372036854775807]"]),
    ("seed", 7.5, ["seed", "an integer"]),
    ("controller.max_iterations", 10**9, ["controller.max_iterations", "an integer in [1, 10000]"]),
    ("solver.max_iterations", 10**6, ["solver.max_iterations", "[1, 50000]"]),
    ("solver.tolerance", 1e-300, ["solver.tolerance", "[1e-12, 1)"]),
    ("camera.position_mm", [1.0, 2.0], ["camera.position_mm", "must be a list of 3 items"]),
    ("camera.position_mm", [1e308, 2.0, 3.0], ["camera.position_mm[0]", "[-10000, 10000]"]),
    ("cups.0.name", "a/b", ["cups[0].name", "letters, digits"]),
    ("targets.0.position_mm", [150.0, 30.0], ["targets[0].position_mm", "inside the tissue"]),
    ("obstacles.0.circle.center_mm", [-5.0, 30.0], ["obstacles[0].circle", "inside the tissue"]),
    ("obstacles.0.circle.center_mm", [70.0, 31.0], ["obstacles[1]", "overlaps"]),
    ("obstacles.1.polygon_mm", [[64.0, 29.0], [84.0, 29.0], [74.0, 29.0]], ["obstacles[1].polygon_mm", "0.01 mm²"]),
    ("cups.0.contact_mm", [50.0, 30.0], ["cups[0].contact_mm", "boundary"]),
    ("cups.0.radius_mm", 70.0, ["cups[0].radius_mm", "fixed side"]),
    ("cups.0.stroke_mm", [15.0, -15.0], ["cups[0].stroke_mm", "min < max"]),
    ("tissue.mesh.min_edge_mm", 5.0, ["tissue.mesh.min_edge_mm", "max_edge_mm"]),
    ("tissue.size_mm", None, ["tissue.size_mm", "required when shape is 'rectangle'"]),
    ("tissue.fixed", [], ["tissue.fixed", "a list of 1 to 4 items"]),
    ("tissue.fixed", ["front"], ["tissue.fixed[0]", "'bottom'"]),
    ("tissue.colour", "pink", ["tissue.colour", "unknown key", "thickness_mm"]),
    ("forward.0.strokes", {"cup": 40.0}, ["forward[0].strokes.cup", "outside"]),
    ("forward.0.strokes", {"sucker": 4.0}, ["forward[0].strokes.sucker", "unknown cup"]),
    ("robot.breast_box_mm.max", [0.0, 0.0, 0.0], ["robot.breast_box_mm", "max must exceed min"]),
    ("robot.voxel_mm", 0.1, ["robot.voxel_mm", "voxels", "at most 2000000"]),
    ("tissue.mesh.min_edge_mm", 0.01, ["tissue.mesh.min_edge_mm", "[0.05, 100]"]),
    ("tissue.mesh.scale", 0.02, ["tissue.mesh.scale", "min_edge_mm × scale = 0.02 mm", "0.05 mm"]),
    ("tissue.mesh.scale", 0.06, ["tissue.mesh (line", "about", f"the budget is {ELEMENT_BUDGET}"]),
]


@pytest.mark.parametrize("field,value,words", BAD, ids=[f"{b[0]}={b[1]}" for b in BAD])
def test_bad_config_exits_2_naming_the_field(tmp_path, field, value, words):
    path = write_scene(tmp_path, deep_update(example_dict(), field, value))
    result = cli_here("validate", path)  # in this process: the exit as a process is test_line_number_points_...'s
    assert result.exit_code == 2 and isinstance(result.exception, SystemExit)
    assert "Traceback" not in result.output
    message = result.stderr
    assert message.startswith(f"error: {path}: ") and message.count("error:") == 1
    assert "(line " in message or "(in the block at line" in message
    for w in words:
        assert w in message, (w, message)


def test_line_number_points_into_the_file(tmp_path):
    text = EXAMPLE.read_text().replace("nu: 0.45", "nu: 0.7")
    line = next(i + 1 for i, row in enumerate(text.splitlines()) if row.strip().startswith("nu: 0.7"))
    path = tmp_path / "s.yaml"
    path.write_text(text)
    proc = run_cli("simulate", path, "--trials", "0", "--out", tmp_path / "o")
    assert proc.returncode == 2 and f"(line {line})" in proc.stderr and "Traceback" not in proc.stderr


# --------------------------------------------------------------------------
# Every number has a documented finite range


def _numeric_leaves(tp=Config, loc=()):
    """(loc, type, constraints) of every int/float leaf the config can hold (list items at index 0)."""
    bare, _ = _unwrap(tp)
    if isinstance(bare, type) and issubclass(bare, BaseModel):
        for name in bare.model_fields:
            yield from _numeric_leaves(bare.model_fields[name].annotation, loc + (name,))
        return
    origin = typing.get_origin(bare)
    if origin is list:
        yield from _numeric_leaves(typing.get_args(bare)[0], loc + (0,))
    elif origin is dict:
        yield from _numeric_leaves(typing.get_args(bare)[1], loc + ("cup",))
    elif bare in (int, float):
        yield (loc, *field_type(loc))


LEAVES = list(_numeric_leaves())


def test_every_number_has_a_finite_range():
    assert len(LEAVES) > 75  # every section is walked (the DH table and the study included)
    unbounded = []
    for loc, _, meta in LEAVES:
        lower = [getattr(m, k) for m in meta for k in ("ge", "gt") if getattr(m, k, None) is not None]
        upper = [getattr(m, k) for m in meta for k in ("le", "lt") if getattr(m, k, None) is not None]
        if not (lower and upper and all(np.isfinite(lower + upper))):
            unbounded.append(loc)
    assert not unbounded, unbounded


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -1e308, 10**400, True, "1.0", None, [1.0], {"a": 1}],
                         ids=["nan", "inf", "-1e308", "10**400", "true", "string", "null", "list", "mapping"])
def test_nonsense_numbers_are_refused_everywhere(value):
    """Every numeric field of the example refuses each kind of nonsense with its range in the message."""
    data = example_dict()
    leaves = []

    def walk(node, path):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, path + (k,))
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, path + (i,))
        elif isinstance(node, (int, float)) and not isinstance(node, bool):
            leaves.append(path)

    walk(data, ())
    assert len(leaves) > 40
    for path in leaves:
        mutated = example_dict()
        deep_update(mutated, ".".join(map(str, path)), value)
        message = refused(mutated)
        dotted = path[0] + "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in path[1:])
        named = (f"scene.yaml: {dotted}", f"scene.yaml: {dotted.rsplit('[', 1)[0]}")
        assert message.split(" (line")[0] in named, message
        assert "must be" in message or "must" in message, message


# --------------------------------------------------------------------------
# Bytes, text and YAML


@pytest.mark.parametrize("content,words", [
    (b"", ["no YAML document", "empty"]),
    (b"# only a comment\n\n", ["no YAML document"]),
    (b"tissue:\n  shape: rect\xe9ngle\n", ["(line 2)", "not UTF-8", "0xe9"]),
    (b"\xff\xfet\x00i\x00", ["(line 1)", "not UTF-8"]),
    (b"seed: 1\nname: a\x00b\n", ["(line 2)", "0x0000", "not allowed"]),
    (b"\x1b[2Jseed: 1\n", ["(line 1)", "0x001b"]),
    (b"material: {E_kPa: 10\n", ["not valid YAML"]),
    (b"seed: 1\n---\nseed: 2\n", ["(line 2)", "not valid YAML", "single document"]),
    (b"- tissue\n- material\n", ["(line 1)", "top level must be a mapping", "got list"]),
    (b"just text\n", ["top level must be a mapping", "got str"]),
    (b"seed: !!python/object:os.system {}\n", ["not valid YAML", "constructor"]),
    (b"seed: " + b"9" * 5000 + b"\n", ["(line 1)", "cannot read the value"]),
    (b"name: 2001-02-30\n", ["(line 1)", "cannot read the value"]),
    (b'name: "\\UFFFFFFFF"\n', ["(line 1)", "not valid YAML"]),
    (b"a: &a [*a]\n", ["(line 1)", "recursive"]),
    (b"seed: " + b"[" * 2000 + b"]" * 2000 + b"\n", ["(line 1)", "nested more than 32 levels"]),
    (b"a:\n" + b"".join(b" " * k + b"- \n" for k in range(1, 200)), ["nested more than 32 levels"]),
    (b"seed: " + b"[" * 40 + b"]" * 40 + b"\n", ["nested more than 32 levels"]),
    (b"? [a, b]\n: 1\n", ["not valid YAML"]),
], ids=["empty", "comment", "latin1", "utf16", "nul", "escape", "unclosed", "two-docs", "list", "scalar", "python-tag",
        "huge-int", "bad-date", "bad-escape", "recursive", "deep", "deep-block", "deep-32", "complex-key"])
def test_bad_bytes_and_yaml(tmp_path, content, words):
    path = tmp_path / "scene.yaml"
    path.write_bytes(content)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(str(path)), message
    for w in words:
        assert w in message, (w, message)


def test_alias_bomb_is_refused_quickly():
    levels = ["a: &a [1, 2, 3, 4, 5, 6, 7, 8, 9]"]
    for k in range(1, 10):  # 9^10 values once expanded
        prev, name = chr(ord("a") + k - 1), chr(ord("a") + k)
        levels.append(f"{name}: &{name} [{', '.join([f'*{prev}'] * 9)}]")
    t0 = time.perf_counter()
    message = refused("\n".join(levels) + "\n", f"more than {loading.MAX_NODES} values", "alias")
    assert time.perf_counter() - t0 < 2.0
    assert "(line " in message


def test_aliases_within_reason_still_work():
    text = EXAMPLE.read_text().replace("stroke_mm: [-15.0, 15.0]", "stroke_mm: &s [-15.0, 15.0]")
    text = text.replace("direction_range_deg: [0.0, 0.0]", "direction_range_deg: &z [0.0, 0.0]")
    assert parse_config(text).cups[0].stroke_mm == [-15.0, 15.0]


def test_file_size_cap(tmp_path):
    path = tmp_path / "big.yaml"
    path.write_bytes(EXAMPLE.read_bytes() + b"#" * MAX_CONFIG_BYTES)
    with pytest.raises(ConfigError, match="larger than 256 KiB"):
        load_config(path)
    refused(EXAMPLE.read_text() + "#" * MAX_CONFIG_BYTES, "larger than 256 KiB")


def test_missing_file_and_directory(tmp_path):
    proc = run_cli("validate", tmp_path / "nope.yaml")
    assert proc.returncode == 2 and "cannot read" in proc.stderr and "Traceback" not in proc.stderr
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path)


def test_duplicate_key_is_an_error():
    with pytest.raises(ConfigError, match="given twice"):
        parse_config("seed: 1\nseed: 2\n")


def test_odd_keys_and_file_names_are_shown_escaped(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text('seed: 1\n"\\x1b[2J\\u00e9": 1\n')
    proc = run_cli("validate", path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "unknown key '\\x1b[2Jé'" in proc.stderr and "\x1b" not in proc.stderr
    odd = tmp_path / os.fsdecode(b"sc\xffene.yaml")  # a name that is not UTF-8
    odd.write_text("seed: -1\n")
    proc = run_cli("validate", odd)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and "sc\\udcffene.yaml" in proc.stderr


def test_polygon_and_ellipse_layers_validate():
    cups = "cups: [{name: c, contact_mm: [40, 50], axis: [0, -1]}]\n"
    cfg = parse_config("tissue: {shape: ellipse, size_mm: [80, 50]}\n" + cups)
    assert cfg.tissue.shape == "ellipse"
    poly = "tissue: {shape: polygon, polygon_mm: [[0, 0], [90, 0], [80, 50], [10, 50]]}\n" + cups
    assert parse_config(poly).tissue.polygon_mm[2] == [80.0, 50.0]


def test_ellipse_targets_keep_clear_of_the_coarsest_outline():
    """A target between the ellipse and its 32-gon would lie outside the mesh: refused, not a crash later."""
    from scissor_cli.experiments.build import scene_of

    data = example_dict()
    deep_update(data, "tissue.shape", "ellipse")
    data["obstacles"] = []
    angle = np.pi + np.pi / checks.ELLIPSE_MIN_POINTS  # mid-edge of the 32-gon, 0.1 mm inside the ellipse
    data["targets"][0]["position_mm"] = [float(50 + 49.9 * np.cos(angle)), float(30 + 29.94 * np.sin(angle))]
    refused(data, "targets[0].position_mm", "32 or more straight edges")
    # the constant is the scene's: its coarsest ellipse has that many points
    coarse = parse(deep_update(example_dict(), "tissue.shape", "ellipse"))
    coarse = coarse.model_copy(update={"tissue": coarse.tissue.model_copy(
        update={"mesh": coarse.tissue.mesh.model_copy(update={"scale": 100.0})})})
    assert len(scene_of(coarse).outline) == checks.ELLIPSE_MIN_POINTS


def test_work_bounds_of_time_steps_and_robot():
    data = deep_update(example_dict(), "solver.dt_s", 1e-4)
    refused(data, "solver.dt_s", "implicit-Euler steps", f"at most {checks.MAX_TIME_STEPS}")
    data["robot"]["dh"] = [{"alpha_deg": 0.0, "a_mm": 0.0, "theta_deg": 0.0, "d_mm": 0.0, "joint": "fixed"}]
    data["solver"].pop("dt_s")
    refused(data, "robot.dh", "at least one revolute or prismatic joint")
    data["robot"]["dh"] = [{"alpha_deg": 0.0, "a_mm": 0.0, "theta_deg": 0.0, "d_mm": 0.0, "joint": "prismatic",
                            "limits": [5.0, 1.0]}]
    refused(data, "robot.dh[0].limits", "lo <= hi")


def test_study_and_accuracy_need_targets():
    data = example_dict()
    data["targets"] = []
    data["study"] = {}
    refused(data, "study", "at least one target")
    data.pop("study")
    data["solver"]["accuracy_mm"] = 0.1
    refused(data, "solver.accuracy_mm", "at least one")


def test_largest_scene_file_validates_in_seconds():
    """A 1000-vertex outline and 33 obstacles of 150 vertices (about 130 KiB): bounded work."""
    t = np.linspace(0, 2 * np.pi, 1000, endpoint=False)
    outline = np.column_stack([500 + 499 * np.cos(t), 500 + 499 * np.sin(t)]).round(3).tolist()
    s = np.linspace(0, 2 * np.pi, 150, endpoint=False)
    obstacles = [{"name": f"o{k}", "polygon_mm": np.column_stack([
        250 + 70 * (k % 6) + 20 * np.cos(s), 250 + 70 * (k // 6) + 20 * np.sin(s)]).round(3).tolist()}
        for k in range(33)]
    data = {"tissue": {"shape": "polygon", "size_mm": None, "polygon_mm": outline,
                       "mesh": {"min_edge_mm": 20.0, "max_edge_mm": 60.0}},
            "cups": [{"name": "c", "contact_mm": outline[250], "axis": [0.0, -1.0], "radius_mm": 5.0}],
            "obstacles": obstacles}
    text = yaml.safe_dump(data, default_flow_style=None, width=10**6)
    assert 100 * 1024 < len(text) <= MAX_CONFIG_BYTES
    t0 = time.process_time()  # this process's CPU seconds: the work validation does, not the machine's load
    cfg = parse_config(text)
    assert len(cfg.obstacles) == 33 and time.process_time() - t0 < 10.0
    data["obstacles"].append({"name": "more", "circle": {"center_mm": [500.0, 800.0], "radius_mm": 5.0}})
    refused(data, "obstacles (line", f"at most {checks.MAX_OBSTACLE_VERTICES}")


def test_interleaved_obstacles_validate_in_seconds():
    """25 thin diagonal strips of 200 vertices: every pair's bounding boxes meet, none overlaps."""
    u = np.linspace(0, 1, 100)
    strips = []
    for k in range(25):
        x, y = 100 + 600 * u, 100 + 600 * u + 6 * k
        poly = np.vstack([np.column_stack([x, y]), np.column_stack([x[::-1] + 0.5, y[::-1] + 2.0])])
        strips.append({"name": f"s{k}", "polygon_mm": poly.round(4).tolist()})
    data = {"tissue": {"size_mm": [1000.0, 1000.0], "mesh": {"min_edge_mm": 20.0, "max_edge_mm": 60.0}},
            "cups": [{"name": "c", "contact_mm": [500.0, 1000.0], "axis": [0.0, -1.0]}], "obstacles": strips}
    t0 = time.process_time()  # CPU seconds: the pairwise checks' work, which a shared machine does not inflate
    assert len(parse(data).obstacles) == 25 and time.process_time() - t0 < 10.0


# --------------------------------------------------------------------------
# The element budget


def _mesh_count(cfg: Config, scale=None) -> int:
    from scissor_cli.experiments.build import scene_of
    from scissor_cli.mesh.mesh import mesh_for_config

    s = cfg.tissue.mesh.scale if scale is None else scale
    mesh = cfg.tissue.mesh.model_copy(update={"scale": s})
    at = cfg.model_copy(update={"tissue": cfg.tissue.model_copy(update={"mesh": mesh})})
    return mesh_for_config(scene_of(at), at.tissue.mesh).n_elements


def _variant(**changes) -> Config:
    data = example_dict()
    for key, value in changes.items():
        deep_update(data, key.replace("__", "."), value)
    return parse(data)


ESTIMATED = {
    "example": (_variant, {}),
    "uniform": (_variant, {"tissue__mesh__graded": False, "tissue__mesh__min_edge_mm": 2.0}),
    "steep-grading": (_variant, {"tissue__mesh__grading": 1.0}),
    "angle-33": (_variant, {"tissue__mesh__min_angle_deg": 33.0}),
    "ellipse": (lambda **k: parse_config(
        "tissue: {shape: ellipse, size_mm: [120, 80]}\ncups: [{name: c, contact_mm: [60, 80], axis: [0, -1]}]\n"
        "obstacles: [{name: v, circle: {center_mm: [40, 40], radius_mm: 5}}]\n"
        "targets: [{name: t, position_mm: [70, 30]}]\n"), {}),
    "polygon": (lambda **k: parse_config(
        "tissue: {shape: polygon, polygon_mm: [[0, 0], [150, 0], [130, 70], [20, 90]], fixed: [bottom]}\n"
        "cups: [{name: c, contact_mm: [75, 80], axis: [0, -1]}]\ntargets: [{name: a, position_mm: [60, 40]}]\n"), {}),
}


@pytest.mark.parametrize("name", list(ESTIMATED))
def test_estimate_is_within_a_factor_1_5_of_the_mesh(name):
    make, changes = ESTIMATED[name]
    cfg = make(**changes)
    scales = (1.0, 0.5) if name in ("example", "ellipse") else (1.0,)
    for scale in scales:
        estimate, real = estimate_elements(cfg, scale=scale), _mesh_count(cfg, scale)
        assert real / 1.5 <= estimate <= 1.5 * real, (name, scale, estimate, real)


def test_over_budget_is_refused_before_meshing(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from scissor_cli import cli
    from scissor_cli.mesh import mesh

    def no_meshing(*args, **kwargs):
        raise AssertionError("meshed a scene over the budget")

    monkeypatch.setattr(mesh, "build_mesh", no_meshing)
    data = deep_update(example_dict(), "tissue.mesh.graded", False)  # 1 mm everywhere: ~22 000
    deep_update(data, "tissue.mesh.min_edge_mm", 0.2)  # 0.2 mm everywhere: 25 times that
    path = write_scene(tmp_path, data)
    t0 = time.perf_counter()
    result = CliRunner().invoke(cli.app, ["simulate", str(path), "--trials", "0", "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and time.perf_counter() - t0 < 5.0
    estimate = int(result.stderr.split("about ")[1].split(" triangles")[0])
    assert estimate > ELEMENT_BUDGET and f"the budget is {ELEMENT_BUDGET}" in result.stderr
    assert "tissue.mesh (line " in result.stderr and not (tmp_path / "o").exists()


def test_estimate_of_an_absurd_mesh_is_quick():
    """A 1 m² layer: at 0.05 mm everywhere (10^9 triangles), and graded from 0.05 to 4 mm around 64 targets."""
    data = example_dict()
    deep_update(data, "tissue.size_mm", [1000.0, 1000.0])
    deep_update(data, "cups.0.contact_mm", [50.0, 1000.0])
    deep_update(data, "tissue.mesh.min_edge_mm", 0.05)
    data["targets"] = [{"name": f"t{k}", "position_mm": [50.0 + 120 * (k % 8), 50.0 + 120 * (k // 8)]}
                       for k in range(64)]
    cfg = Config.model_validate(data)
    t0 = time.perf_counter()
    assert estimate_elements(cfg, graded=False) > 1000 * ELEMENT_BUDGET
    assert estimate_elements(cfg) > ELEMENT_BUDGET
    assert time.perf_counter() - t0 < 3.0


def test_accuracy_selection_stays_within_the_budget():
    from scissor_cli.experiments.selection import CANDIDATE_LEVELS

    assert budget.SELECTION_FINEST_LEVEL == min(CANDIDATE_LEVELS)
    assert budget.SELECTION_COARSEST_LEVEL == max(CANDIDATE_LEVELS)
    # every level the selection may pick gives a config that validates again (trials and --resume re-read it)
    refused(deep_update(deep_update(example_dict(), "solver.accuracy_mm", 0.1), "tissue.mesh.min_edge_mm", 0.1),
            "solver.accuracy_mm", "below the finest edge 0.05 mm")
    refused(deep_update(deep_update(example_dict(), "solver.accuracy_mm", 0.1), "tissue.mesh.scale", 50.0),
            "solver.accuracy_mm", "above the largest scale 100")
    data = deep_update(example_dict(), "solver.accuracy_mm", 0.1)
    assert parse(data).solver.accuracy_mm == 0.1  # the example: ~26 000 triangles at a quarter of its size field
    deep_update(data, "tissue.mesh.min_edge_mm", 0.3)
    deep_update(data, "tissue.mesh.max_edge_mm", 1.0)
    assert estimate_elements(parse(deep_update(dict(data), "solver.accuracy_mm", None))) < ELEMENT_BUDGET
    deep_update(data, "solver.accuracy_mm", 0.1)
    refused(data, "solver.accuracy_mm", "0.25 x the size field", f"budget of {ELEMENT_BUDGET}")


def test_study_skips_levels_over_its_max_before_meshing(monkeypatch):
    from scissor_cli.experiments import study
    from scissor_cli.experiments.build import scene_of

    cfg = load_config(EXAMPLE)
    meshed = []
    real = study.mesh_for_config
    monkeypatch.setattr(study, "mesh_for_config", lambda scene, m, scale: meshed.append(scale) or real(scene, m, scale))
    settings = study.StudyConfig(levels=[1.0, 0.25, 0.05], uniform=False, max_elements=30000)
    notes = []
    variants = study.mesh_variants(cfg, scene_of(cfg), settings, notes)
    assert [level for level, _, _ in variants] == [1.0, 0.25] and meshed == [1.0, 0.25]
    assert "graded level 0.05: about" in notes[0]
    # its max_elements is at most half the budget: a mesh it builds stays within it
    assert field_type(("study", "max_elements"))[1][-1].le * 2 <= ELEMENT_BUDGET


SHIPPED = sorted((ROOT / "configs").rglob("*.yaml")) + sorted((ROOT / "scissor_cli" / "scenes").glob("*.yaml"))


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_shipped_scene_validates(path):
    """What the README and docs tell a user to run must load (configs/, the package's default)."""
    cfg = load_config(path)
    assert cfg.name


def test_the_packaged_example_is_configs_example():
    """`scissor simulate` with no config runs the packaged scene; the docs point at configs/example.yaml;
    the tests read either: one file, twice."""
    packaged = ROOT / "scissor_cli" / "scenes" / "example.yaml"
    assert packaged.read_text() == (ROOT / "configs" / "example.yaml").read_text()
