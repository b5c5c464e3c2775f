"""Workspace sampling, box coverage, workspace.h5 and the Fig. 8 figure."""

import subprocess
import sys

import h5py
import numpy as np

from scissor_cli.robot import RobotModel
from scissor_cli.workspace import coverage, run_workspace

PAPER = RobotModel.paper()


def test_coverage_of_hand_checkable_boxes():
    # tips filling x in [0, 10] of a 20 x 10 x 10 box: exactly half its voxels
    g = np.stack(np.meshgrid(np.arange(0.5, 10, 1.0), np.arange(0.5, 10, 1.0), np.arange(0.5, 10, 1.0)), -1).reshape(-1, 3)
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
    assert (tmp_path / "ws" / "workspace.png").stat().st_size > 20_000


def test_same_seed_same_samples():
    a = run_workspace(PAPER, samples=1000, seed=5)
    b = run_workspace(PAPER, samples=1000, seed=5)
    assert np.array_equal(a.joints, b.joints) and a.coverage.coverage == b.coverage.coverage
