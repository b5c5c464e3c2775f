"""`scissor simulate` end to end: the HDF5 layout of docs/contract.md, figures, failures."""

import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest

from figure_checks import assert_png_drawn
from helpers import ROOT, deep_update, example_dict, write_scene


def run_cli(*args, cwd=None):
    """`python -m scissor_cli ARGS` importing this checkout's package, whatever is installed."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "scissor_cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env)


def small_scene(tmp_path, **changes):
    data = example_dict()
    deep_update(data, "tissue.mesh.max_edge_mm", 8.0)
    deep_update(data, "tissue.mesh.min_edge_mm", 2.0)
    deep_update(data, "solver.kind", "newton")
    for k, v in changes.items():
        deep_update(data, k, v)
    return write_scene(tmp_path, data)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("run")
    scene = small_scene(tmp)
    proc = run_cli("simulate", scene, "--trials", "0", "--out", tmp / "out", "--quiet")
    return proc, tmp / "out"


def test_simulate_writes_contract_layout(run):
    proc, out = run
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(out)
    with h5py.File(out / "results.h5") as f:
        a = f.attrs
        assert a["status"] == "complete" and a["seed"] == 7 and "tissue:" in a["config_yaml"]
        assert "scissor_version" in a and "created" in a
        N = f["mesh/nodes"].shape[0]
        M = f["mesh/triangles"].shape[0]
        assert f["mesh/nodes"].shape == (N, 2) and f["mesh/nodes"].attrs["units"] == "mm"
        assert f["mesh/triangles"].dtype == np.int64
        assert f["mesh/fiber"].shape == (M, 2) and f["mesh/element_E_kPa"].shape == (M,)
        assert f["mesh/fixed_nodes"].dtype == np.int64
        for key in ("model", "E_kPa", "nu", "eta_kPa", "thickness_mm", "density_kg_per_mm3", "fiber_tension_only"):
            assert key in f["material"].attrs
        assert f["cups/cup/nodes"].dtype == np.int64
        assert np.allclose(f["cups/cup"].attrs["axis"], [0, -1])
        assert np.allclose(f["cups/cup"].attrs["contact"], [50, 60])
        for case, stroke in (("push10", 10.0), ("pull8", -8.0)):
            g = f[f"forward/{case}"]
            assert g["strokes"].attrs["cup"] == stroke
            assert g["displacement"].shape == (N, 2) and g["displacement"].attrs["units"] == "mm"
            assert g.attrs["solver"] == "newton" and g.attrs["residual"] <= 1e-8 and g.attrs["iterations"] > 0
            assert g.attrs["time_s"] > 0
            for t in ("T1", "T2"):
                assert g[f"targets/{t}"].shape == (2,)
        # the cup nodes moved by exactly the stroke along the axis
        cup = f["cups/cup/nodes"][:]
        assert np.allclose(f["forward/push10/displacement"][:][cup], [0.0, -10.0])
        assert np.allclose(f["targets/T2"].attrs["desired"], [58.0, 20.5])
        for t in ("T1", "T2"):
            assert f[f"jacobian/{t}"].shape == (2, 1) and f[f"jacobian/{t}"].attrs["units"] == "mm/mm"
            plan = f[f"plan/{t}"].attrs
            for key in ("entry", "direction", "depth_mm", "clearance_mm", "joints", "feasible"):
                assert key in plan
            assert plan["joints"].shape == (5,) and plan["entry"].shape == (2,)
            assert plan["feasible"] and plan["clearance_mm"] > 0
        # a push moves the targets down: J's y entry is negative
        assert f["jacobian/T1"][1, 0] < 0
    assert_png_drawn(out / "forward_push10.png", min_ink=0.1, min_colour=0.05)  # the tissue, filled


def test_existing_output_is_not_overwritten(run, tmp_path):
    proc, out = run
    scene = small_scene(tmp_path)
    again = run_cli("simulate", scene, "--trials", "0", "--out", out)
    assert again.returncode == 2 and "--force" in again.stderr


def test_solver_failure_exits_1_and_keeps_a_failed_file(tmp_path):
    scene = small_scene(tmp_path, **{"solver.newton_max_iterations": 1})
    proc = run_cli("simulate", scene, "--trials", "0", "--out", tmp_path / "o")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert "push10" in proc.stderr and "not converged" in proc.stderr
    with h5py.File(tmp_path / "o" / "results.h5") as f:
        assert f.attrs["status"] == "failed" and "push10" in f.attrs["failure"]
        assert "mesh/nodes" in f  # what it finished is kept


def test_same_config_same_numbers(run, tmp_path):
    _, out = run
    proc = run_cli("simulate", small_scene(tmp_path), "--trials", "0", "--out", tmp_path / "again", "--quiet")
    assert proc.returncode == 0
    with h5py.File(out / "results.h5") as a, h5py.File(tmp_path / "again" / "results.h5") as b:
        assert np.array_equal(a["forward/push10/displacement"][:], b["forward/push10/displacement"][:])


def test_version_and_bad_solver_option():
    proc = run_cli("--version")
    assert proc.returncode == 0 and proc.stdout.startswith("scissor ")
    proc = run_cli("simulate", "--solver", "jacobi", "--trials", "0")
    assert proc.returncode == 2 and "admm" in proc.stderr and "Traceback" not in proc.stderr


def test_non_finite_value_exits_1_naming_where(tmp_path, monkeypatch):
    """A NaN in a trial's result stops the run: exit 1, the dataset and trial named, nothing non-finite stored."""
    import signal

    from typer.testing import CliRunner

    from scissor_cli import cli, control
    from scissor_cli.sensing.sensor import EXACT

    real = control.run_target

    def poisoned(*args, **kw):
        r = real(*args, **kw)
        run = args[4] if len(args) > 4 else kw.get("run", control.TargetRun())
        if run.sensor is not EXACT:  # a trial, not the nominal manipulation
            r.final_error = np.array([np.nan, 0.0])
        return r

    monkeypatch.setattr(control, "run_target", poisoned)
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:  # in this process, so the patch reaches the trials (--jobs 1)
        result = CliRunner().invoke(cli.app, ["simulate", str(small_scene(tmp_path)), "--trials", "2", "--jobs", "1",
                                              "--out", str(tmp_path / "o")])
    finally:
        for s, handler in saved.items():
            signal.signal(s, handler)
    stderr = " ".join(result.stderr.split())
    assert result.exit_code == 1, stderr
    assert "non-finite value to /trials/T1/final_error (trial 0): nan" in stderr and "Traceback" not in stderr
    assert "status = failed" in stderr
    with h5py.File(tmp_path / "o" / "results.h5") as f:
        assert f.attrs["status"] == "failed" and "non-finite" in f.attrs["failure"]
        assert np.all(np.isfinite(f["trials/T1/final_error"][:])) and not f["trials/T1/done"][:].any()


def test_resume_refuses_what_it_cannot_resume(run, tmp_path):
    _, out = run
    proc = run_cli("simulate", "--resume", tmp_path)
    assert proc.returncode == 2 and "no results.h5" in proc.stderr and "Traceback" not in proc.stderr
    proc = run_cli("simulate", "--resume", tmp_path / "nowhere")
    assert proc.returncode == 2 and "no results.h5" in proc.stderr and "Traceback" not in proc.stderr


def test_resume_of_a_complete_run_without_trials_computes_nothing(run, tmp_path):
    _, out = run
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    with h5py.File(copy / "results.h5") as f:
        times = {k: f[f"forward/{k}"].attrs["time_s"] for k in f["forward"]}
    proc = run_cli("simulate", "--resume", copy)  # a --trials 0 run
    assert proc.returncode == 0, proc.stderr
    assert "resumed: 0 trial(s) run" in proc.stdout + proc.stderr
    with h5py.File(copy / "results.h5") as f:
        assert f.attrs["status"] == "complete"
        assert {k: f[f"forward/{k}"].attrs["time_s"] for k in f["forward"]} == times
    assert not (copy / "results.h5.tmp").exists()
