"""`scissor simulate` end to end: the HDF5 layout of CONTRACT.md, figures, failures."""

import subprocess
import sys

import h5py
import numpy as np
import pytest

from helpers import example_dict, write_scene, deep_update


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "scissor_cli.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd)


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
        assert np.allclose(f["cups/cup"].attrs["axis"], [0, -1]) and np.allclose(f["cups/cup"].attrs["contact"], [50, 60])
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
    assert (out / "forward_push10.png").stat().st_size > 10_000


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
