"""A run stopped in any stage before its trials: `--resume` keeps what finished and completes the rest.

docs/contract.md#resume: every stage product (a forward case, a layer
check, the plans, a target's manipulation or insertions) is marked finished
in results.h5 once it and its figure are stored; `--resume` redoes only what
is not marked. Checked here for a stop in the layer check and one in the
middle of the insertion stage (Ctrl-C in-process), and for a real SIGKILL of
`scissor simulate` during its insertions:

* the finished products are kept as stored (their wall times unchanged:
  they were not computed again);
* the completed run equals an uninterrupted one (every number but wall
  times, insertion and layer check included).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from scissor_cli.config import load_config
from scissor_cli.experiments.simulate import Execution, resume_simulation, run_simulation
from scissor_cli.output import results_sink as sink_module
from scissor_cli.output.results_sink import RunDirectory, open_for_resume

from helpers import example_dict, write_scene

ROOT = Path(__file__).resolve().parents[1]


def scene(tmp_path: Path) -> Path:
    data = example_dict()
    data["tissue"]["mesh"].update(max_edge_mm=8.0, min_edge_mm=2.5)
    data["solver"]["kind"] = "newton"
    data["forward"] = data["forward"][:1]
    data["layer_check"] = {"height_mm": 8.0, "layer_z_mm": 4.0, "chest_wall_fixed": True, "cup_holds_z": True,
                           "max_layer_mm": 4.0, "accuracy_mm": None}
    data["insertion"] = {"step_mm": 4.0, "friction_static_mN_per_mm": 15.0, "friction_kinetic_mN_per_mm": 10.0,
                         "tip_force_mN": 100.0, "tip_zone_mm": 2.0, "strategies": ["none"]}
    data["trials"] = {"count": 1, "profile": "prosthesis"}
    return write_scene(tmp_path, data)


def numbers(results_h5: Path) -> dict[str, np.ndarray]:
    """Every numeric dataset and attribute of a run, wall times and creation stamps left out."""
    out: dict[str, np.ndarray] = {}
    with h5py.File(results_h5, "r") as h5:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and "time_s" not in name.split("/")[-1]:
                data = obj[()]
                if data.dtype.kind in "fiub":
                    out[name] = np.asarray(data, float)
            for key, value in obj.attrs.items():
                arr = np.asarray(value)
                if key != "time_s" and arr.dtype.kind in "fiub":
                    out[f"{name}@{key}"] = arr.astype(float)

        h5.visititems(visit)
    return out


def wall_times(results_h5: Path, groups: list[str]) -> dict[str, float]:
    with h5py.File(results_h5, "r") as h5:
        return {g: float(h5[g].attrs["time_s"]) for g in groups if g in h5}


def assert_same_run(a: Path, b: Path) -> None:
    x, y = numbers(a), numbers(b)
    assert sorted(x) == sorted(y)
    different = [k for k in x if not np.array_equal(x[k], y[k])]
    assert not different, different[:10]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> tuple[Path, Path]:
    """An uninterrupted run of the scene: (scene path, results.h5)."""
    base = tmp_path_factory.mktemp("uninterrupted")
    path = scene(base)
    run_simulation(load_config(path), RunDirectory(base / "run"), execution=Execution(jobs=1))
    return path, base / "run" / "results.h5"


@pytest.mark.parametrize("stage, target", [pytest.param("layer_check", "push10", marks=pytest.mark.slow),
                                           pytest.param("insertion", "T2", marks=pytest.mark.slow)])
# (one resume rule for every stage; by default test_sigkill_during_the_insertions_then_resume below resumes a run
# stopped inside a stage, the harder case)
def test_a_run_stopped_before_its_trials_resumes_without_redoing_what_finished(stage, target, reference, tmp_path,
                                                                               monkeypatch):
    path, ref = reference
    real = getattr(sink_module.ResultsSink, stage)

    def stopped(self, product, *args):
        name = getattr(product, "target", None) or getattr(product, "name", None)
        if name == target:
            raise KeyboardInterrupt("SIGINT")  # Ctrl-C while this product is being computed
        return real(self, product, *args)

    monkeypatch.setattr(sink_module.ResultsSink, stage, stopped)
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_simulation(load_config(path), RunDirectory(run), execution=Execution(jobs=1))
    monkeypatch.undo()
    with h5py.File(run / "results.h5", "r") as h5:
        assert h5.attrs["status"] == "failed" and "trials" not in h5
        finished = set(h5.attrs["finished"].astype(str))
    assert f"{stage}/{target}" not in finished and "trials" not in finished
    assert "forward/push10" in finished
    if stage == "insertion":
        assert {"layer_check/push10", "plan", "manipulation/T1", "manipulation/T2", "insertion/T1"} <= finished
    kept = ["forward/push10"] + (["layer_check/push10", "insertion/T1/none"]
                                 if stage == "insertion" else [])
    before = wall_times(run / "results.h5", kept)

    assert resume_simulation(open_for_resume(run), execution=Execution(jobs=1)) == 2  # 1 trial x 2 targets
    with h5py.File(run / "results.h5", "r") as h5:
        assert h5.attrs["status"] == "complete"
        assert {"trials", f"{stage}/{target}"} <= set(h5.attrs["finished"].astype(str))
    assert wall_times(run / "results.h5", kept) == before  # kept, not computed again
    assert_same_run(ref, run / "results.h5")
    assert (run / f"{'layer_check_push10.png' if stage == 'layer_check' else 'insertion_force_T2.png'}").exists()
    # the animation belongs to the first planned target, however the run was split
    assert sorted(p.name for p in run.glob("*.gif")) == sorted(p.name for p in ref.parent.glob("*.gif"))


def test_a_resumed_run_that_was_complete_computes_nothing(reference, tmp_path):
    _, ref = reference
    run = tmp_path / "run"
    shutil.copytree(ref.parent, run)
    groups = ["forward/push10", "layer_check/push10", "insertion/T1/none", "insertion/T2/none"]
    before = wall_times(run / "results.h5", groups)
    assert len(before) == len(groups)
    assert resume_simulation(open_for_resume(run), execution=Execution(jobs=1)) == 0
    assert wall_times(run / "results.h5", groups) == before
    assert_same_run(ref, run / "results.h5")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SIGKILL of a process group")
def test_sigkill_during_the_insertions_then_resume(reference, tmp_path):
    """A real `scissor simulate` killed once its first insertion's figures exist; `--resume` completes it."""
    path, ref = reference
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    cmd = [sys.executable, "-m", "scissor_cli", "simulate", str(path), "--out", str(run), "--jobs", "1"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 180
    while not (run / "insertion_force_T1.png").exists():
        assert proc.poll() is None, "the run ended before its first insertion was stored"
        assert time.monotonic() < deadline, "no insertion figure within 180 s"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    tmp = run / "results.h5.tmp"
    assert tmp.exists() and not (run / "results.h5").exists()
    with h5py.File(tmp, "r") as h5:
        finished = set(h5.attrs["finished"].astype(str))
    assert {"forward/push10", "layer_check/push10", "plan"} <= finished and "trials" not in finished
    kept = wall_times(tmp, ["forward/push10", "layer_check/push10"])

    r = subprocess.run(cmd[:4] + ["--resume", str(run), "--jobs", "1"], env=env, capture_output=True, text=True,
                       timeout=240)
    assert r.returncode == 0, r.stderr
    assert "finished stage product(s) kept" in r.stdout + r.stderr
    assert wall_times(run / "results.h5", list(kept)) == kept
    assert_same_run(ref, run / "results.h5")


def test_a_run_stopped_before_results_h5_starts_again_from_its_recorded_config_on_resume(reference, tmp_path):
    """A new run records its config (`.scissor-run.yaml`) before its first stage; a run stopped before it wrote
    results.h5 (in the slab's ladder, say: the directory holds only that file) is started again by `--resume`
    and equals an uninterrupted run; without the file `--resume` still refuses (exit 2)."""
    from typer.testing import CliRunner

    from scissor_cli.cli import app
    from scissor_cli.config import resolved_yaml
    from scissor_cli.output.results_sink import STARTED

    path, ref = reference
    runner = CliRunner()
    recorded = tmp_path / "recorded"
    RunDirectory(recorded).start(resolved_yaml(load_config(path)))
    stopped = tmp_path / "stopped"
    stopped.mkdir()
    shutil.copy(recorded / STARTED, stopped / STARTED)
    resumed = runner.invoke(app, ["simulate", "--resume", str(stopped), "--jobs", "1", "-q"])
    assert resumed.exit_code == 0, resumed.output
    assert_same_run(ref, stopped / "results.h5")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert runner.invoke(app, ["simulate", "--resume", str(empty)]).exit_code == 2


def test_a_new_run_records_its_config_before_its_first_stage(tmp_path):
    """`simulate` writes `.scissor-run.yaml` (the config with the command line's overrides) into its directory."""
    from typer.testing import CliRunner

    from scissor_cli.cli import app
    from scissor_cli.config import resolved_yaml
    from scissor_cli.output.results_sink import STARTED

    data = example_dict()
    data["tissue"]["mesh"].update(max_edge_mm=8.0, min_edge_mm=2.5)
    data["trials"] = {"count": 0}
    path = write_scene(tmp_path, data)
    run = tmp_path / "run"
    result = CliRunner().invoke(app, ["simulate", str(path), "--out", str(run), "--seed", "11", "-q"])
    assert result.exit_code == 0, result.output
    expected = load_config(path).model_copy(update={"seed": 11})
    assert (run / STARTED).read_text() == resolved_yaml(expected)
