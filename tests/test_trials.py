"""Trials end to end: HDF5 layout, reproducibility across executors, crash and resume."""

import h5py
import numpy as np
import pytest

from scissor_cli import control
from scissor_cli.config import load_config
from scissor_cli.experiments.profiles import draw_trial, error_model
from scissor_cli.experiments.simulate import Execution, TrialsFailed, resume_simulation, run_simulation
from scissor_cli.output.results_sink import RunDirectory, open_for_resume
from scissor_cli.sensing.sensor import EXACT

from figure_checks import assert_png_drawn
from helpers import ROOT


def reduced(trials=5, profile="prosthesis"):
    """The paper's push scene on a coarse mesh: 2 targets x `trials` trials, Newton forward solves."""
    cfg = load_config(ROOT / "configs" / "paper_push.yaml")
    mesh = cfg.tissue.mesh.model_copy(update={"scale": 2.0})
    return cfg.model_copy(update={
        "tissue": cfg.tissue.model_copy(update={"mesh": mesh}),
        "solver": cfg.solver.model_copy(update={"kind": "newton"}),
        "forward": cfg.forward[:1],
        "trials": cfg.trials.model_copy(update={"count": trials, "profile": profile}),
    })


def final_errors(path):
    with h5py.File(path) as f:
        return {t: f[f"trials/{t}/final_error"][:] for t in f["trials"]}


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    run_simulation(reduced(), RunDirectory(out), execution=Execution(jobs=1))
    return out


def test_trials_layout(serial_run):
    with h5py.File(serial_run / "results.h5") as f:
        assert f.attrs["status"] == "complete"
        for t in ("T1", "T2"):
            g = f[f"trials/{t}"]
            assert g["final_error"].shape == (5, 2) and g["final_error"].attrs["units"] == "mm"
            assert g["iterations"].shape == (5,) and g["iterations"].dtype == np.int64
            assert g["time_s"].shape == (5,) and np.all(g["time_s"][:] > 0)
            assert g["corridor_clear"].shape == (5,) and g["done"][:].all() and not g["failed"][:].any()
            assert np.all(np.isfinite(g["final_error"][:])) and np.all(g["iterations"][:] >= 1)
            h = g["history/0"]
            cols = list(h.attrs["columns"])
            assert cols[0] == "time_s" and "true_x" in cols and "error_y" in cols
            assert h.shape == (g["iterations"][0] + 1, len(cols))
            # the last history row's error is the stored final error (no slip in this profile)
            assert np.allclose(h[-1, [cols.index("error_x"), cols.index("error_y")]], g["final_error"][0])
            m = f[f"manipulation/{t}"].attrs
            assert np.linalg.norm(m["closed_final_error"]) <= 0.1 < np.linalg.norm(m["open_final_error"])
    for png in ("trials_error_boxplot.png", "trials_iterations.png", "manipulation_T1.png"):
        assert_png_drawn(serial_run / png)


def test_trial_draws_depend_only_on_seed_target_and_index():
    cfg = reduced()
    em = error_model(cfg.trials)
    cent = np.random.default_rng(0).uniform(0, 50, (40, 2))
    a = draw_trial(em, 0.45, cent, 7, 1, 3)
    b = draw_trial(em, 0.45, cent, 7, 1, 3)
    c = draw_trial(em, 0.45, cent, 7, 1, 4)
    assert np.array_equal(a.E_field, b.E_field) and a.nu == b.nu and np.array_equal(a.localisation_z, b.localisation_z)
    assert not np.array_equal(a.E_field, c.E_field)


def test_two_jobs_are_bit_identical(serial_run, tmp_path):
    run_simulation(reduced(), RunDirectory(tmp_path), execution=Execution(jobs=2))
    a, b = final_errors(serial_run / "results.h5"), final_errors(tmp_path / "results.h5")
    assert all(np.array_equal(a[t], b[t]) for t in a)


def test_dask_local_cluster_is_bit_identical(serial_run, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        run_simulation(reduced(), RunDirectory(tmp_path),
                       execution=Execution(jobs=2, executor="dask", scheduler=cluster.scheduler_address))
    a, b = final_errors(serial_run / "results.h5"), final_errors(tmp_path / "results.h5")
    assert all(np.array_equal(a[t], b[t]) for t in a)


def test_crashed_trial_is_kept_marked_and_resumed(serial_run, tmp_path, monkeypatch):
    real = control.run_target

    def flaky(*args, **kw):
        run = args[4] if len(args) > 4 else kw.get("run", control.TargetRun())
        if run.target == "T2" and run.sensor is not EXACT:  # a trial, not the nominal run
            flaky.calls += 1
            if flaky.calls == 3:
                raise RuntimeError("simulated crash")
        return real(*args, **kw)

    flaky.calls = 0
    monkeypatch.setattr(control, "run_target", flaky)
    with pytest.raises(TrialsFailed, match="1 trial"):
        run_simulation(reduced(), RunDirectory(tmp_path), execution=Execution(jobs=1))
    with h5py.File(tmp_path / "results.h5") as f:
        assert f.attrs["status"] == "failed"
        assert f["trials/T2/failed"][:].sum() == 1 and f["trials/T1/done"][:].all()
        messages = "".join(m.decode() if isinstance(m, bytes) else m for m in f["trials/T2/message"][:])
        assert "simulated crash" in messages
    monkeypatch.setattr(control, "run_target", real)
    assert resume_simulation(open_for_resume(tmp_path), execution=Execution(jobs=1)) == 1
    with h5py.File(tmp_path / "results.h5") as f:
        assert f.attrs["status"] == "complete" and not f["trials/T2/failed"][:].any()
    a, b = final_errors(serial_run / "results.h5"), final_errors(tmp_path / "results.h5")
    assert all(np.array_equal(a[t], b[t]) for t in a)


def test_resume_restores_from_the_journal_what_a_kill_kept_out_of_the_file(serial_run, tmp_path, monkeypatch):
    """A SIGKILL between journalling a trial and storing it, and one in the middle of storing another."""
    import sys

    from scissor_cli.output import results_sink as sink_module

    sys.path.insert(0, str(ROOT / "tests" / "golden"))
    from extract import extract

    def killed(self, *exc):  # like SIGKILL: nothing is renamed, the journal stays
        self.out.h5.close()
        self._journal.close()

    monkeypatch.setattr(sink_module.ResultsSink, "__exit__", killed)
    run_simulation(reduced(), RunDirectory(tmp_path), execution=Execution(jobs=1))
    monkeypatch.undo()
    tmp = tmp_path / "results.h5.tmp"
    assert tmp.exists() and not (tmp_path / "results.h5").exists()
    with h5py.File(tmp, "r+") as f:
        f["trials/T2/done"][4] = False  # journalled, never stored
        del f["trials/T2/history/3"]  # marked done, its history lost
    sink = open_for_resume(tmp_path)
    notes = " ".join(sink.notes())
    assert "resuming from results.h5.tmp" in notes and "1 trial(s) marked done had no history" in notes
    assert "restored 2 finished trial(s)" in notes
    assert resume_simulation(sink, execution=Execution(jobs=1)) == 0  # nothing recomputed
    now, before = extract(tmp_path / "results.h5"), extract(serial_run / "results.h5")
    assert sorted(now) == sorted(before) and all(np.array_equal(now[k], before[k]) for k in before)
    assert not tmp.exists() and not (tmp_path / "results.h5.journal").exists()


def test_ideal_single_trial_is_the_deterministic_check(tmp_path):
    run_simulation(reduced(trials=1, profile="ideal"), RunDirectory(tmp_path), execution=Execution(jobs=1))
    with h5py.File(tmp_path / "results.h5") as f:
        for t in ("T1", "T2"):
            assert f[f"trials/{t}/manipulation_miss_mm"][0] <= 0.1
            # moves of at most speed x period: 0.5 mm at 5 mm/s and 10 Hz
            assert f[f"trials/{t}/corridor_clear"][0] and f[f"trials/{t}/iterations"][0] <= 50


def non_finite(path) -> list[str]:
    """Every float dataset or attribute of the file holding a NaN or infinity."""
    bad = []
    with h5py.File(path) as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and obj.dtype.kind == "f" and not np.all(np.isfinite(obj[()])):
                bad.append(name)
            for key, value in obj.attrs.items():
                a = np.asarray(value)
                if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                    bad.append(f"{name}@{key}")
        visit("/", f)
        f.visititems(visit)
    return bad


def test_no_nan_reaches_the_file_crashed_trials_hold_fill_values(tmp_path, monkeypatch):
    """A crashed trial, a target without obstacles (clearance +inf) and undone trials: masks and finite fills only."""
    real = control.run_target

    def flaky(*args, **kw):
        run = args[4] if len(args) > 4 else kw.get("run", control.TargetRun())
        if run.target == "T1" and run.sensor is not EXACT:  # a trial, not the nominal run
            flaky.calls += 1
            if flaky.calls == 2:
                raise RuntimeError("simulated crash")
        return real(*args, **kw)

    flaky.calls = 0
    monkeypatch.setattr(control, "run_target", flaky)
    cfg = reduced(trials=3)
    cfg = cfg.model_copy(update={"obstacles": []})
    with pytest.raises(TrialsFailed):
        run_simulation(cfg, RunDirectory(tmp_path), execution=Execution(jobs=1))
    assert non_finite(tmp_path / "results.h5") == []
    with h5py.File(tmp_path / "results.h5") as f:
        g = f["trials/T1"]
        crashed = np.flatnonzero(g["failed"][:])
        assert len(crashed) == 1 and g["done"][crashed[0]]
        assert np.array_equal(g["final_error"][crashed[0]], [0.0, 0.0]) and g["iterations"][crashed[0]] == -1
        assert g["clearance_mm"][:].tolist() == [0.0] * 3  # no obstacles: undefined, stored as the fill value
        assert all(g["corridor_clear"][k] for k in range(3) if k != crashed[0])
        assert f["plan/T1"].attrs["clearance_mm"] == 0.0 and "fill_values" in f["trials"].attrs


def test_non_finite_trial_is_a_run_time_error_naming_where(tmp_path, monkeypatch):
    from scissor_cli.experiments.simulate import NonFiniteError

    real = control.run_target

    def poisoned(*args, **kw):
        r = real(*args, **kw)
        run = args[4] if len(args) > 4 else kw.get("run", control.TargetRun())
        if run.target == "T2" and run.sensor is not EXACT:  # a trial, not the nominal run
            poisoned.calls += 1
            if poisoned.calls == 2:
                r.final_error = np.array([np.nan, 0.0])
        return r

    poisoned.calls = 0
    monkeypatch.setattr(control, "run_target", poisoned)
    with pytest.raises(NonFiniteError, match=r"/trials/T2/final_error \(trial 1\)"):
        run_simulation(reduced(trials=3), RunDirectory(tmp_path), execution=Execution(jobs=1))
    assert non_finite(tmp_path / "results.h5") == []
    with h5py.File(tmp_path / "results.h5") as f:
        assert f.attrs["status"] == "failed" and "/trials/T2/final_error" in f.attrs["failure"]
        assert f["trials/T1/done"][:].all() and f["trials/T2/done"][:].tolist() == [True, False, False]


def test_writer_refuses_non_finite_values(tmp_path):
    from scissor_cli.experiments.simulate import NonFiniteError
    from scissor_cli.output.results import ResultsFile

    out = ResultsFile.create(tmp_path / "results.h5", "name: x\n", 0)
    with out:
        out.dataset("a/ok", np.arange(3.0))
        with pytest.raises(NonFiniteError, match=r"/a/b: nan \(1 of 3"):
            out.dataset("a/b", np.array([1.0, np.nan, 2.0]))
        with pytest.raises(NonFiniteError, match=r"/a/ok@scale: inf"):
            out.attrs("a/ok", {"scale": np.inf})
        with pytest.raises(NonFiniteError, match=r"/a/ok\[1\]"):
            out.put("a/ok", 1, -np.inf)
    assert non_finite(tmp_path / "results.h5") == []


def test_journal_ignores_a_torn_last_record(tmp_path):
    from scissor_cli.output import journal

    path = tmp_path / "results.h5.journal"
    j = journal.Journal.create(path, "name: x\n", 3)
    history = np.random.default_rng(0).normal(size=(4, 3))
    j.append({"target": "T1", "trial": 0, "ok": True, "history": history, "history_columns": ["a", "b", "c"]})
    j.append({"target": "T1", "trial": 1, "ok": False, "history": np.zeros((0, 0)), "history_columns": []})
    j.close()
    whole = path.read_bytes()
    path.write_bytes(whole[:-7])  # killed while appending the second trial
    header, records, valid = journal.read(path)
    assert header["config_yaml"] == "name: x\n" and header["seed"] == 3
    assert len(records) == 1 and np.array_equal(records[0]["history"], history)  # bit for bit
    assert records[0]["history_columns"] == ["a", "b", "c"] and records[0]["ok"] is True
    j = journal.Journal.resume(path, valid)  # the torn tail is cut before appending
    j.append({"target": "T1", "trial": 1, "ok": False, "history": np.zeros((0, 0)), "history_columns": []})
    j.close()
    assert [r["trial"] for r in journal.read(path)[1]] == [0, 1]
    bad = bytearray(path.read_bytes())
    bad[valid - 3] ^= 0xFF  # a damaged byte in the first trial: it and everything after it are distrusted
    path.write_bytes(bytes(bad))
    assert journal.read(path)[1] == []


def test_expected_duration_counts_trials_per_worker():
    from scissor_cli.experiments.simulate import Execution, expected_duration

    assert "about 20 min with 2 worker(s)" in expected_duration(10.0, 240, Execution(jobs=2))  # 120 per worker
    assert "about 1.7 h with 1 worker(s)" in expected_duration(50.0, 120, Execution(jobs=1))
    assert "about 2.0 s with 2 worker(s)" in expected_duration(2.0, 2, Execution(jobs=8))  # no idle workers counted
    line = expected_duration(2.0, 3, Execution(jobs=2))  # 2 workers, the busier one runs 2 trials
    assert "the first took 2.0 s" in line and "about 4.0 s with 2 worker(s)" in line
    line = expected_duration(600.0, 4, Execution(jobs=2), loop_s=60.0)  # a slab insertion: 9 parts in 10
    assert "the first took 10 min (the loop 60 s, the needle's insertion 9 min)" in line and "about 20 min" in line
    assert "insertion" not in expected_duration(10.0, 4, Execution(jobs=2), loop_s=9.5)  # the loop is the trial
    # a body's nominal insertions and manipulations in the same pool come on top, and the line says so
    assert "the 4 nominal run(s) beside" in expected_duration(10.0, 4, Execution(jobs=2), beside=4)
    assert "nominal" not in expected_duration(10.0, 4, Execution(jobs=2))


def test_the_rest_is_estimated_from_the_finished_trials_mean_time():
    from scissor_cli.experiments.trial_stage import Execution, estimate_checkpoint, remaining_duration

    assert estimate_checkpoint(60, Execution(jobs=2)) == 6  # a tenth
    assert estimate_checkpoint(10, Execution(jobs=2)) == 5  # the first and two more per worker
    assert estimate_checkpoint(120, Execution(jobs=1)) == 12
    assert estimate_checkpoint(8, Execution(jobs=2)) is None  # fewer would be left than are done
    assert estimate_checkpoint(2, Execution(jobs=8)) is None
    line = remaining_duration(10.0, 6, 60, Execution(jobs=2))  # 54 left, 27 per worker at 10 s
    assert "6 of 60 done, 10 s each on average" in line and "the other 54 should take about 4 min" in line
    assert "about 10 s" in remaining_duration(10.0, 5, 6, Execution(jobs=2))  # one left: one worker busy


def test_a_trials_time_holds_its_insertion_not_only_its_loop(monkeypatch):
    """The estimate a run prints is built on the whole trial: with slab insertion the loop was a tenth of it."""
    import time

    from scissor_cli.config import resolved_yaml
    from scissor_cli.experiments.simulate import trial_tasks
    from scissor_cli.experiments.trials import TrialContext
    from scissor_cli.planning.needle_plan import plan_targets

    cfg = load_config(ROOT / "configs" / "example.yaml")
    cfg = cfg.model_copy(update={"trials": cfg.trials.model_copy(update={"profile": "ideal", "count": 1})})
    ctx = TrialContext(resolved_yaml(cfg))
    task = trial_tasks(ctx.tissue, plan_targets(ctx.tissue, ctx.scene, cfg.needle))[0]
    monkeypatch.setattr(TrialContext, "insert", lambda *a: (time.sleep(0.3), (np.zeros(0), np.zeros(0)))[1])
    o = ctx.run(task, 0)
    assert o.ok and o.trial_time_s >= o.time_s + 0.3
