"""A body's error budget (docs/model.md §20, "Budget"): the trials again with one source at a time, the body's own
sources among them (its registration in the robot's frame, the lesion's stiffness)."""

from __future__ import annotations

import h5py
import numpy as np
import yaml

from scissor_cli.config.loading import parse_config
from scissor_cli.experiments.error_budget import budget_plan
from scissor_cli.experiments.profiles import draw_body, error_model

from helpers import cli_here, example_dict, simulate_here, write_scene
from test_body_loop import SCENE
from test_cli import run_cli

#: only the body's own sources on: every other row would be the `none` row
TRIALS = {"count": 1, "profile": "ideal", "budget": True, "registration_mm": 0.5, "registration_deg": 0.5,
          "lesion_stiffness_log_sd": 0.5}


def test_the_registration_moves_the_needles_line_by_a_rigid_motion():
    cfg = parse_config(yaml.safe_dump(dict(SCENE, trials=TRIALS)), "<test>")
    draw = draw_body(error_model(cfg.trials), cfg.seed, 0, 1)
    R = draw.rotation
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0
    p = np.array([[5.0, 10.0, 10.0], [-8.0, -6.0, 8.0]])
    moved = draw.moved(p)
    assert abs(np.linalg.norm(moved[0] - moved[1]) - np.linalg.norm(p[0] - p[1])) < 1e-9  # rigid
    again = draw_body(error_model(cfg.trials), cfg.seed, 0, 1)  # the same trial: the same draw
    assert np.array_equal(again.offset_mm, draw.offset_mm) and again.lesion_stiffness == draw.lesion_stiffness
    off = parse_config(yaml.safe_dump(dict(SCENE, trials=dict(TRIALS, registration_mm=0.0, registration_deg=0.0))),
                       "<test>")
    assert draw_body(error_model(off.trials), off.seed, 0, 1).registered_exactly
    rows = budget_plan(cfg).rows
    assert list(rows) == ["registration", "lesion_stiffness", "none"]  # a body has no slab or release-slip row


def test_a_bodys_budget_has_its_own_sources(tmp_path):
    one = dict(SCENE, targets=SCENE["targets"][:1], trials=TRIALS)  # (one lesion keeps the test short)
    with h5py.File(simulate_here(tmp_path, one) / "results.h5", "r") as f:
        assert list(f["budget"].attrs["sources"]) == ["all", "registration", "lesion_stiffness", "none"]
        for t in ("T1",):
            none = f[f"budget/none/{t}/miss_mm"][()]
            registration = f[f"budget/registration/{t}/miss_mm"][()]
            assert f[f"budget/registration/{t}/final_error"].shape == (1, 3)
            assert np.max(registration) > np.max(none) + 0.05  # the needle's line moved off the lesion
            # the loop does not see the registration: it ends where the row without it ends
            np.testing.assert_allclose(f[f"budget/registration/{t}/final_error"][()],
                                       f[f"budget/none/{t}/final_error"][()], atol=1e-9)
            stiff = f[f"budget/lesion_stiffness/{t}/final_error"][()]
            assert np.all(np.isfinite(stiff)) and not np.array_equal(stiff, f[f"budget/none/{t}/final_error"][()])
        assert f["trials"].attrs["registration_mm"] == 0.5
    assert (tmp_path / "run" / "budget.png").is_file()
    r = cli_here("report", tmp_path / "run", "--out", tmp_path / "report")
    assert r.exit_code == 0, r.output
    assert "z_max_mm" in (tmp_path / "report" / "budget.md").read_text()  # a body's vertical error too


def test_a_layer_refuses_the_bodys_sources(tmp_path):
    data = example_dict()
    data["trials"] = dict(data.get("trials", {}), registration_mm=0.5)
    r = run_cli("validate", write_scene(tmp_path, data))
    assert r.returncode == 2 and "trials.registration_mm" in r.stderr and "Traceback" not in r.stderr, r.stderr
