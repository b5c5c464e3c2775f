"""Config validation: the example scene passes, each class of bad input fails cleanly."""

import subprocess
import sys

import pytest

from scissor_cli.config import parse_config, resolved_yaml, load_config
from helpers import EXAMPLE, example_dict, write_scene, deep_update


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "scissor_cli.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd)


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
    ("material.E_kPa", 0.0, ["material.E_kPa", "greater than 0"]),
    ("material.E_kPa", "10", ["material.E_kPa", "valid number"]),
    ("material.nu", 0.5, ["material.nu", "less than 0.5"]),
    ("material.nu", -1.0, ["material.nu", "greater than -1"]),
    ("material.eta_kPa", -1.0, ["material.eta_kPa", "greater than or equal to 0"]),
    ("material.model", "mooney", ["material.model", "'linear'", "'neo_hookean_fiber'"]),
    ("targets.0.position_mm", [150.0, 30.0], ["targets[0].position_mm", "inside the tissue"]),
    ("obstacles.0.circle.center_mm", [-5.0, 30.0], ["obstacles[0].circle", "inside the tissue"]),
    ("obstacles.0.circle.center_mm", [70.0, 31.0], ["obstacles[1]", "overlaps"]),
    ("cups.0.contact_mm", [50.0, 30.0], ["cups[0].contact_mm", "boundary"]),
    ("cups.0.stroke_mm", [15.0, -15.0], ["cups[0].stroke_mm", "min < max"]),
    ("tissue.mesh.min_edge_mm", 5.0, ["tissue.mesh.min_edge_mm", "max_edge_mm"]),
    ("tissue.fixed", [], ["tissue.fixed", "at least 1"]),
    ("tissue.fixed", ["front"], ["tissue.fixed[0]", "'bottom'"]),
    ("tissue.colour", "pink", ["tissue.colour", "unknown key", "thickness_mm"]),
    ("forward.0.strokes", {"cup": 40.0}, ["forward[0].strokes.cup", "outside"]),
    ("forward.0.strokes", {"sucker": 4.0}, ["forward[0].strokes.sucker", "unknown cup"]),
]


@pytest.mark.parametrize("field,value,words", BAD, ids=[f"{b[0]}={b[1]}" for b in BAD])
def test_bad_config_exits_2_naming_the_field(tmp_path, field, value, words):
    path = write_scene(tmp_path, deep_update(example_dict(), field, value))
    proc = run_cli("validate", path)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    message = proc.stderr
    assert str(path) in message
    assert "(line " in message or "(in the block at line" in message
    for w in words:
        assert w in message, (w, message)


def test_line_number_points_into_the_file(tmp_path):
    text = EXAMPLE.read_text().replace("nu: 0.45", "nu: 0.7")
    line = next(i + 1 for i, l in enumerate(text.splitlines()) if l.strip().startswith("nu: 0.7"))
    path = tmp_path / "s.yaml"
    path.write_text(text)
    proc = run_cli("simulate", path, "--trials", "0", "--out", tmp_path / "o")
    assert proc.returncode == 2 and f"(line {line})" in proc.stderr and "Traceback" not in proc.stderr


def test_yaml_syntax_error_and_missing_file(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("material: {E_kPa: 10\n")
    proc = run_cli("validate", path)
    assert proc.returncode == 2 and "not valid YAML" in proc.stderr and "Traceback" not in proc.stderr
    proc = run_cli("validate", tmp_path / "nope.yaml")
    assert proc.returncode == 2 and "cannot read" in proc.stderr


def test_duplicate_key_is_an_error():
    with pytest.raises(Exception, match="given twice"):
        parse_config("seed: 1\nseed: 2\n")


def test_polygon_and_ellipse_layers_validate():
    cfg = parse_config("tissue: {shape: ellipse, size_mm: [80, 50]}\ncups: [{name: c, contact_mm: [40, 50], axis: [0, -1]}]\n")
    assert cfg.tissue.shape == "ellipse"
    poly = "tissue: {shape: polygon, polygon_mm: [[0, 0], [90, 0], [80, 50], [10, 50]]}\ncups: [{name: c, contact_mm: [40, 50], axis: [0, -1]}]\n"
    assert parse_config(poly).tissue.polygon_mm[2] == [80.0, 50.0]
