"""Workspace sampling, box coverage, workspace.h5 and the Fig. 8 figure."""

import subprocess
import sys

import h5py
import numpy as np

from scissor_cli.output.workspace_file import plot_workspace, write_workspace_h5
from scissor_cli.robot.chain import RobotModel
from scissor_cli.robot.workspace import DEFAULT_BOX_MAX, DEFAULT_BOX_MIN, coverage, reachable_coverage, run_workspace

from figure_checks import assert_png_drawn

PAPER = RobotModel.paper()


def test_coverage_of_hand_checkable_boxes():
    # tips filling x in [0, 10] of a 20 x 10 x 10 box: exactly half its voxels
    centres = np.arange(0.5, 10, 1.0)
    g = np.stack(np.meshgrid(centres, centres, centres), -1).reshape(-1, 3)
    axes = np.tile([1.0, 0.0, 0.0], (len(g), 1))
    c = coverage(g, axes, [0, 0, 0], [20, 10, 10], voxel_mm=5.0)
    assert np.isclose(c.coverage, 0.5) and c.coverage_multi_direction == 0.0
    assert "x" in c.summary
    full = coverage(g, axes, [0, 0, 0], [10, 10, 10], voxel_mm=5.0)
    assert full.coverage == 1.0


def test_paper_robot_coverage_and_contract_file(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "scissor_cli.cli", "workspace", "--samples", "200000",
                           "--out", str(tmp_path / "ws"), "--seed", "3"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "coverage (reachable by IK): 91.7%" in proc.stderr and "missed" in proc.stderr
    with h5py.File(tmp_path / "ws" / "workspace.h5") as f:
        w = f["workspace"]
        assert w["joints"].shape == (200000, 5) and w["tip"].shape == (200000, 3) and w["axis"].shape == (200000, 3)
        assert np.allclose(w.attrs["box_min"], [60, 50, 200]) and np.allclose(w.attrs["box_max"], [210, 380, 300])
        assert 0 < w.attrs["coverage"] <= 1
        assert np.allclose(np.linalg.norm(w["axis"][:100], axis=1), 1)
    assert_png_drawn(tmp_path / "ws" / "workspace.png", min_colour=0.02)


def test_same_seed_same_samples():
    a = run_workspace(PAPER, samples=1000, seed=5)
    b = run_workspace(PAPER, samples=1000, seed=5)
    assert np.array_equal(a.joints, b.joints) and a.coverage.coverage == b.coverage.coverage


def test_multi_direction_needs_distinct_direction_bins():
    tips = np.full((4, 3), 2.5)
    ang = np.deg2rad([0.0, 1.0, 45.0, 90.0])  # 0° and 1° share a 10° bin
    axes = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(4)])
    box = ([0, 0, 0], [5, 5, 5])
    assert coverage(tips, axes, *box, min_directions=3).coverage_multi_direction == 1.0
    assert coverage(tips[:3], axes[:3], *box, min_directions=3).coverage_multi_direction == 0.0


def test_reachable_coverage_inside_and_at_the_default_box():
    inside = reachable_coverage(PAPER, [0, 100, 200], [100, 250, 300])
    assert inside.coverage == 1.0 and inside.missed_bbox_min is None
    default = reachable_coverage(PAPER, DEFAULT_BOX_MIN, DEFAULT_BOX_MAX)
    missed = int((default.hits == 0).sum())
    print(f"\npaper robot, default box: reachable {default.coverage:.4f} "
          f"(>= 3 directions {default.coverage_multi_direction:.4f}); {default.summary}")
    assert missed == 3300 and np.allclose(default.missed_bbox_min, [155, 50, 200])
    assert np.allclose(default.missed_bbox_max, [210, 125, 300])
    # a reachable voxel centre really is reachable: IK on one of them
    from scissor_cli.robot.ik import ik
    assert ik([62.5, 377.5, 202.5], [0.0, 1.0, 0.0], PAPER).reachable


def test_h5_round_trip_and_figure(tmp_path):
    res = run_workspace(PAPER, samples=5000, seed=1)
    path = tmp_path / "workspace.h5"
    write_workspace_h5(path, res, {"scissor_version": "test", "config_yaml": None})
    assert not (tmp_path / "workspace.h5.tmp").exists()
    with h5py.File(path) as f:
        w = f["workspace"]
        assert np.array_equal(w["joints"][()], res.joints) and w["joints"].dtype == np.float64
        assert np.array_equal(w["tip"][()], res.tip) and np.array_equal(w["axis"][()], res.axis)
        assert w.attrs["coverage"] == res.coverage.coverage and w.attrs["samples"] == 5000
        assert "rad" in w["joints"].attrs["units"] and f.attrs["scissor_version"] == "test"
    plot_workspace(res, tmp_path / "ws.png")
    assert_png_drawn(tmp_path / "ws.png", min_colour=0.02)
