"""The `controller.error` and `manipulation_points` fields (docs/contract.md#config): defaults, the
full example's sections, and bad input refused with exit 2 and one message (file, field, line)."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from scissor_cli.config import ConfigError, parse_config

from helpers import ROOT, example_dict

#: the example scene with every optional section
FULL = ROOT / "configs" / "example_full.yaml"


def _text(data: dict) -> str:
    return yaml.safe_dump(data, sort_keys=False)


def with_points(**mp) -> dict:
    data = example_dict()
    data["manipulation_points"] = {"sides": ["top"], "spacing_mm": 2.0, "cups": 1} | mp
    return data


def test_defaults_are_miss_and_no_placement():
    cfg = parse_config(_text(example_dict()), "scene.yaml")
    assert cfg.controller.error == "miss" and cfg.manipulation_points is None


def test_full_example_controller_and_manipulation_points_validate():
    data = yaml.safe_load(FULL.read_text())
    data.pop("insertion", None), data.pop("layer_check", None)  # other features' sections
    cfg = parse_config(_text(data), "example-full.yaml")
    assert cfg.controller.error == "miss"
    mp = cfg.manipulation_points
    assert mp.sides == ["top"] and mp.spacing_mm == 2.0 and mp.cups == 1


@pytest.mark.parametrize("mp, words", [
    (dict(sides=["bottom"]), ["manipulation_points.sides[0]", "'bottom' is fixed", "line"]),
    (dict(cups=0), ["manipulation_points.cups", "0 cups to place", "line"]),
    (dict(cups=2), ["manipulation_points.cups", "2 cups to place but the scene lists 1", "line"]),
    (dict(spacing_mm=0.0), ["manipulation_points.spacing_mm", "line"]),
    (dict(sides=["front"]), ["manipulation_points.sides[0]", "line"]),
])
def test_bad_manipulation_points_are_refused(mp, words):
    with pytest.raises(ConfigError) as info:
        parse_config(_text(with_points(**mp)), "scene.yaml")
    message = str(info.value)
    assert message.startswith("scene.yaml")
    for w in words:
        assert w in message, (w, message)


def test_bad_error_mode_is_refused():
    data = example_dict()
    data["controller"]["error"] = "across"
    with pytest.raises(ConfigError) as info:
        parse_config(_text(data), "scene.yaml")
    assert "controller.error" in str(info.value) and "miss" in str(info.value)


def test_cli_exits_2_with_one_message(tmp_path: Path):
    path = tmp_path / "scene.yaml"
    path.write_text(_text(with_points(sides=["top", "bottom"])))
    proc = subprocess.run([sys.executable, "-m", "scissor_cli", "validate", str(path)], capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert str(path) in proc.stderr and "manipulation_points.sides[1]" in proc.stderr and "line" in proc.stderr
