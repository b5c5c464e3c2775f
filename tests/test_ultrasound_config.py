"""The `imaging` section: what it accepts, what it refuses (exit 2 naming the field), and its tables against the core.

docs/contract.md ("imaging") is the contract; the checks are
scissor_cli/config/imaging_checks.py.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml

from scissor_cli.config import ConfigError, parse_config
from scissor_cli.config.imaging_checks import PROBE_ARRAYS, image_half_width_mm
from scissor_cli.config.sections import LINEAR_PROBE_NAMES

from helpers import deep_update, example_dict, write_scene

IMAGING = {"probe": "L11-5v", "position_mm": [0.0, 30.0], "axis": [1.0, 0.0], "depth_mm": 70.0,
           "assumed_sound_speed_m_per_s": 1540.0, "sound_speed_m_per_s": 1540.0, "lesion_radius_mm": 2.0,
           "lesion_echogenicity_db": -10.0, "snr_db": 30.0, "model": "fast"}


def scene(**imaging) -> dict:
    data = example_dict()
    data["imaging"] = {**IMAGING, **imaging}
    return data


def test_the_config_tables_are_the_cores():
    from scissor_cli.sensing.ultrasound import LINEAR_PROBES, image_grid, probe_params

    assert LINEAR_PROBE_NAMES == LINEAR_PROBES
    for name in LINEAR_PROBES:
        p = probe_params(name)
        assert PROBE_ARRAYS[name] == (p.n_elements, pytest.approx(p.pitch_mm))
        grid = image_grid(p, 70.0, 1540.0)
        assert image_half_width_mm(name) == pytest.approx(grid.lateral_mm[-1]) == pytest.approx(-grid.lateral_mm[0])


def test_a_good_section_and_its_defaults():
    cfg = parse_config(yaml.safe_dump(scene(axis=[1.005, 0.0], depth_mm=100.0)), "scene.yaml")
    assert cfg.imaging.axis == [1.0, 0.0]  # normalised
    # from the top, looking down: lateral is then -x (the axis turned +90 degrees)
    cfg = parse_config(yaml.safe_dump(scene(axis=[0.0, -1.0], position_mm=[50.0, 60.0])), "scene.yaml")
    assert cfg.imaging.position_mm == [50.0, 60.0]
    data = example_dict()
    data["imaging"] = {}
    cfg = parse_config(yaml.safe_dump(data), "scene.yaml")
    assert cfg.imaging.probe == "L11-5v" and cfg.imaging.position_mm == [0.0, 30.0] and cfg.imaging.snr_db == 30.0
    assert parse_config(yaml.safe_dump(example_dict()), "scene.yaml").imaging is None


@pytest.mark.parametrize("change,field,words", [
    ({"position_mm": [5.0, 30.0]}, "imaging.position_mm", ["on the skin", "5 mm"]),
    ({"axis": [-1.0, 0.0]}, "imaging.axis", ["into the tissue"]),
    ({"axis": [0.0, 1.0]}, "imaging.axis", ["into the tissue"]),
    ({"axis": [0.0, 0.0]}, "imaging.axis", ["unit vector"]),
    ({"depth_mm": 40.0}, "imaging.depth_mm", ["'T1'", "outside the image"]),
    ({"position_mm": [0.0, 55.0]}, "imaging.position_mm", ["'T1'", "lateral", "outside the L11-5v image"]),
    ({"sound_speed_m_per_s": 1000.0, "assumed_sound_speed_m_per_s": 1600.0, "depth_mm": 80.0}, "imaging.depth_mm",
     ["shows at", "outside the image"]),
    ({"probe": "C5-2v"}, "imaging.probe", ["L11-5v", "L12-3v", "P4-2v"]),
    ({"sound_speed_m_per_s": 340.0}, "imaging.sound_speed_m_per_s", ["[1000, 2000]"]),
    ({"assumed_sound_speed_m_per_s": 5000.0}, "imaging.assumed_sound_speed_m_per_s", ["[1000, 2000]"]),
    ({"lesion_radius_mm": 0.0}, "imaging.lesion_radius_mm", ["(0, 100]"]),
    ({"lesion_radius_mm": 20.0}, "imaging.lesion_radius_mm", ["smaller than the image"]),
    ({"lesion_echogenicity_db": 0.0}, "imaging.lesion_echogenicity_db", ["0 dB"]),
    ({"model": "kwave"}, "imaging.model", ["fast", "simus"]),
    ({"colour": "grey"}, "imaging.colour", ["unknown key"]),
    ({"obstacle_echogenicity_db": {"artery": -40.0}}, "imaging.obstacle_echogenicity_db.artery", ["unknown obstacle"]),
])
def test_bad_sections_are_refused_naming_the_field(change, field, words):
    with pytest.raises(ConfigError) as info:
        parse_config(yaml.safe_dump(scene(**change)), "scene.yaml")
    message = str(info.value)
    assert message.startswith(f"scene.yaml: {field} (line"), message
    for w in words:
        assert w in message, (w, message)


@pytest.mark.parametrize("change", [
    {"position_mm": [5.0, 30.0]},  # off the skin
    {"axis": [-1.0, 0.0]},  # facing out
    {"depth_mm": 40.0},  # a target beyond the image
    {"probe": "C5-2v"},  # not a linear probe
    {"sound_speed_m_per_s": 340.0},  # air
])
def test_validate_exits_2_without_a_traceback(tmp_path, change):
    path = write_scene(tmp_path, scene(**change))
    proc = subprocess.run([sys.executable, "-m", "scissor_cli", "validate", str(path)], capture_output=True, text=True)
    assert proc.returncode == 2 and "imaging." in proc.stderr and "Traceback" not in proc.stderr, proc.stderr


def test_the_trials_imaging_spreads_have_ranges():
    data = deep_update(scene(), "trials.sound_speed_sd_m_per_s", 500.0)
    with pytest.raises(ConfigError, match="trials.sound_speed_sd_m_per_s"):
        parse_config(yaml.safe_dump(data), "scene.yaml")
    data = deep_update(scene(), "trials.electronic_noise_scale", -1.0)
    with pytest.raises(ConfigError, match="trials.electronic_noise_scale"):
        parse_config(yaml.safe_dump(data), "scene.yaml")
