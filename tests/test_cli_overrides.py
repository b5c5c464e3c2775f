"""The command line's options combined with a scene: every combination runs or exits 2, never a traceback."""

from __future__ import annotations

import h5py

from scissor_cli.config import parse_config

from helpers import example_dict, write_scene
from test_cli import run_cli


def _scene_with_budget(tmp_path):
    data = example_dict()
    data["tissue"]["mesh"]["scale"] = 2.0
    data["targets"] = data["targets"][:1]
    data["trials"] = {"count": 2, "profile": "prosthesis", "budget": True}
    return write_scene(tmp_path, data)


def test_trials_0_on_a_scene_with_a_budget_runs_the_forward_cases_only(tmp_path):
    """The budget reruns the trials: with --trials 0 there are none, so there is no budget (a worker used to
    re-read the overridden config and fail with a traceback)."""
    r = run_cli("simulate", str(_scene_with_budget(tmp_path)), "--trials", "0", "--out", str(tmp_path / "run"),
                "--quiet")
    assert r.returncode == 0, r.stderr
    with h5py.File(tmp_path / "run" / "results.h5", "r") as f:
        assert f.attrs["status"] == "complete"
        assert "forward" in f and "budget" not in f and "trials" not in f
        recorded = f.attrs["config_yaml"]
    # the config the run records (what a resume or a worker reads back) is one the scene file format allows
    cfg = parse_config(recorded, "results.h5")
    assert cfg.trials.count == 0 and not cfg.trials.budget


def test_budget_with_trials_0_exits_2_without_a_traceback(tmp_path):
    r = run_cli("simulate", str(_scene_with_budget(tmp_path)), "--trials", "0", "--budget", "--out",
                str(tmp_path / "run"))
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and "--budget" in r.stderr
