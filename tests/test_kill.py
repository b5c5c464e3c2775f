"""A `simulate --jobs 2` killed at any moment: nothing it started survives, and `--resume` finishes it exactly.

Each test starts a real run on a small scene with enough trials, waits
until some trials are stored, and stops it with SIGKILL, SIGTERM or SIGINT
(to the whole process group, as Ctrl-C in a terminal does). It checks
(docs/contract.md#resume):

* every process of the run is gone within 5 s of the signal;
* `--resume` runs exactly the trials that had not finished, keeping the
  finished ones as they were stored (their wall times are unchanged);
* the completed results equal an uninterrupted run's bit for bit
  (`tests/golden/extract.py`'s extractor).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from scissor_cli.output import journal

from golden.extract import extract
from helpers import deep_update, example_dict, write_scene

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="process checks read /proc")

TRIALS = 14  # per target; 2 targets: a kill after 8, and a resume killed after 6 more, leave trials to run
ROOT = Path(__file__).resolve().parents[1]


def scene(tmp_path: Path) -> Path:
    data = example_dict()
    deep_update(data, "tissue.mesh.max_edge_mm", 8.0)
    deep_update(data, "tissue.mesh.min_edge_mm", 2.0)
    deep_update(data, "solver.kind", "newton")
    deep_update(data, "trials.count", TRIALS)
    data["forward"] = data["forward"][:1]
    return write_scene(tmp_path, data)


def env() -> dict:
    """The child imports this checkout's package, whatever is installed."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}


def start(*args) -> subprocess.Popen:
    # its own session: the run and its workers share a process group we can watch (and Ctrl-C)
    return subprocess.Popen([sys.executable, "-m", "scissor_cli", "simulate", *map(str, args)], env=env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def finish(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", *map(str, args)], env=env(),
                          capture_output=True, text=True, timeout=240)


def group_members(pgid: int) -> list[int]:
    """Live (not zombie) processes of a process group."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[2]) == pgid and fields[0] != "Z":
            pids.append(int(entry.name))
    return pids


def journal_trials(out: Path) -> int:
    return len(journal.read(journal.journal_path(out / "results.h5"))[1])


def wait_for_trials(proc: subprocess.Popen, out: Path, at_least: int, timeout: float = 120.0) -> int:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        assert proc.poll() is None, f"the run ended before it was killed: {proc.communicate()}"
        n = journal_trials(out)
        if n >= at_least:
            return n
        time.sleep(0.05)
    raise AssertionError(f"no {at_least} finished trials within {timeout} s")


def alive_after(pgid: int, seconds: float) -> list[int]:
    """The group's live processes once none is left or `seconds` have passed: a worker dies when the kernel
    delivers its kill (its parent's death, the pool's SIGKILL), a moment after the run itself has ended."""
    t0 = time.monotonic()
    while group_members(pgid) and time.monotonic() - t0 < seconds:
        time.sleep(0.02)
    return group_members(pgid)


def stop(proc: subprocess.Popen, sig: int) -> tuple[float, str]:
    """Send `sig` (SIGINT to the whole group, like Ctrl-C; others to the run): (seconds until all are gone, stderr)."""
    assert len(group_members(proc.pid)) >= 3, "expected the run and 2 workers"
    t0 = time.monotonic()
    if sig == signal.SIGINT:
        os.killpg(proc.pid, sig)
    else:
        os.kill(proc.pid, sig)
    left = alive_after(proc.pid, 30)
    gone = time.monotonic() - t0
    if proc.pid in left:  # the run hangs: have it print where its threads are (the CLI's SIGUSR1 handler)
        os.kill(proc.pid, signal.SIGUSR1)
        time.sleep(2.0)
    for pid in left:  # do not leave anything behind, even when the test fails
        os.kill(pid, signal.SIGKILL)
    _, stderr = proc.communicate(timeout=10)
    assert not left, f"still alive {gone:.1f} s after the signal: {left}; the run's stderr ends:\n{stderr[-6000:]}"
    return gone, " ".join(stderr.split())  # the console wraps long lines


def stored(path: Path) -> dict[str, dict[int, tuple]]:
    """Per target, the finished trials: index -> (final error, iterations, wall time)."""
    with h5py.File(path, "r") as f:
        out = {}
        for t, g in f["trials"].items():
            ok = np.flatnonzero(g["done"][:] & ~g["failed"][:])
            out[t] = {int(k): (tuple(g["final_error"][k]), int(g["iterations"][k]), float(g["time_s"][k])) for k in ok}
        return out


def ran(proc: subprocess.CompletedProcess) -> int:
    found = re.search(r"trials: (\d+) to run", proc.stderr)
    return int(found.group(1)) if found else 0


def assert_same_as_reference(out: Path, reference: dict) -> None:
    with h5py.File(out / "results.h5", "r") as f:
        assert f.attrs["status"] == "complete"
    now = extract(out / "results.h5")
    assert sorted(now) == sorted(reference)
    differ = [k for k in reference if not np.array_equal(now[k], reference[k])]
    assert not differ, f"differ from the uninterrupted run: {differ[:10]}"
    assert not (out / "results.h5.tmp").exists() and not journal.journal_path(out / "results.h5").exists()


def assert_kept(before: dict, out: Path) -> None:
    after = stored(out / "results.h5")
    for t, trials in before.items():
        for k, value in trials.items():
            assert after[t][k] == value, f"trial {t}/{k} was recomputed or changed"


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("reference")
    proc = finish(scene(tmp), "--jobs", "2", "--out", tmp / "run", "--quiet")
    assert proc.returncode == 0, proc.stderr
    return extract(tmp / "run" / "results.h5")


@pytest.mark.parametrize("sig", [signal.SIGTERM, pytest.param(signal.SIGINT, marks=pytest.mark.slow)],
                         ids=["SIGTERM", "SIGINT"])  # (one handler serves both: SIGINT's run is the slow one)
def test_stop_signal_keeps_finished_trials_and_resume_completes(sig, reference, tmp_path):
    out = tmp_path / "run"
    proc = start(scene(tmp_path), "--jobs", "2", "--out", out)
    n = wait_for_trials(proc, out, 8)
    os.kill(proc.pid, signal.SIGUSR1)  # where its threads are, on stderr; the run goes on
    wait_for_trials(proc, out, n + 1)
    gone, stderr = stop(proc, sig)
    print(f"{signal.Signals(sig).name}: all processes gone {gone:.2f} s after the signal")
    assert str(ROOT / "scissor_cli" / "cli.py") in stderr  # the main thread's stack, from the command down
    assert gone < 5.0
    assert proc.returncode == 128 + sig, stderr
    assert "interrupted" in stderr and f"--resume {out}" in stderr and "Traceback" not in stderr
    assert not (out / "results.h5.tmp").exists()
    with h5py.File(out / "results.h5", "r") as f:
        assert f.attrs["status"] == "failed" and f.attrs["failure"].startswith("interrupted")
    before = stored(out / "results.h5")
    finished = sum(len(v) for v in before.values())
    assert 8 <= finished < 2 * TRIALS

    t0 = time.monotonic()
    resumed = finish("--resume", out, "--jobs", "2")
    print(f"resume after {signal.Signals(sig).name}: {time.monotonic() - t0:.1f} s for {ran(resumed)} trials")
    assert resumed.returncode == 0, resumed.stderr
    assert ran(resumed) == 2 * TRIALS - finished
    assert_kept(before, out)
    assert_same_as_reference(out, reference)


def test_a_second_run_into_a_running_runs_directory_is_refused_and_the_first_finishes_whole(reference, tmp_path):
    """`--force` into, or `--resume` of, a directory a run is writing: exit 2 naming that run's pid, before
    anything is touched (it used to truncate the running run's file); the first run ends as if alone, and its
    lock is gone with it."""
    from scissor_cli.output.run_lock import claim

    out, config = tmp_path / "run", scene(tmp_path)
    proc = start(config, "--jobs", "2", "--out", out, "--quiet")
    try:
        t0 = time.monotonic()
        while not (out / "results.h5.tmp").exists():
            assert proc.poll() is None and time.monotonic() - t0 < 120, proc.communicate()
            time.sleep(0.02)
        # the first run paused (SIGSTOP to its group) while the others try: still running and holding its lock, it
        # cannot finish before they start, as it did on a loaded machine (the resume then found a finished run)
        os.killpg(proc.pid, signal.SIGSTOP)
        try:
            seconds = [subprocess.Popen([sys.executable, "-m", "scissor_cli", "simulate", *map(str, args)],
                                        env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                       for args in ((config, "--force", "--out", out, "--trials", "2"), ("--resume", out))]
            for second in seconds:
                _, stderr = second.communicate(timeout=240)
                said = " ".join(stderr.split())
                assert second.returncode == 2, said
                assert f"another scissor run (pid {proc.pid}) is writing there" in said and "Traceback" not in said
        finally:
            os.killpg(proc.pid, signal.SIGCONT)
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    _, stderr = proc.communicate(timeout=240)
    assert proc.returncode == 0, stderr
    assert_same_as_reference(out, reference)
    claim(out).release()  # the finished run holds nothing


def test_sigkill_damaged_file_and_killed_resume_lose_no_trial(reference, tmp_path):
    """SIGKILL leaves only results.h5.tmp and the journal. Here the kill is made worse: the
    temporary file is damaged, as a kill in the middle of an HDF5 write can leave it. The resume
    says so, rebuilds from the journal, and is itself SIGKILLed; the next resume completes."""
    out = tmp_path / "run"
    proc = start(scene(tmp_path), "--jobs", "2", "--out", out, "--quiet")
    wait_for_trials(proc, out, 8)
    gone, _ = stop(proc, signal.SIGKILL)
    print(f"SIGKILL: all processes gone {gone:.2f} s after the signal")
    assert gone < 5.0 and proc.returncode == -signal.SIGKILL
    tmp = out / "results.h5.tmp"
    assert tmp.exists() and not (out / "results.h5").exists()
    first = stored(tmp)
    in_journal = journal_trials(out)
    # a trial is journalled before it is stored, and the run stores one at a time: the kill can
    # catch the file one trial behind the journal, never more (the resume restores that one)
    assert in_journal >= 8 and sum(len(v) for v in first.values()) >= in_journal - 1

    with open(tmp, "r+b") as fh:  # a torn metadata write: the superblock and root group overwritten
        fh.write(b"\0" * 4096)
    proc = start("--resume", out, "--jobs", "2")
    n = wait_for_trials(proc, out, in_journal + 6)
    gone, stderr = stop(proc, signal.SIGKILL)
    assert gone < 5.0
    assert "cannot be read" in stderr and "rebuilding results.h5" in stderr, stderr
    assert (out / "results.h5.damaged").exists()
    kept = stored(tmp)  # the rebuilt file the killed resume left
    assert sum(len(v) for v in kept.values()) >= in_journal

    t0 = time.monotonic()
    resumed = finish("--resume", out, "--jobs", "2")
    print(f"resume after SIGKILL of a resume: {time.monotonic() - t0:.1f} s for {ran(resumed)} trials")
    assert resumed.returncode == 0, resumed.stderr
    said = " ".join(resumed.stderr.split())
    # the killed rebuild may have left its own file torn too (a kill mid-write): then the journal rebuilds it again
    assert ("resuming from results.h5.tmp" in said
            or ("cannot be read" in said and "rebuilding results.h5" in said)), said
    assert ran(resumed) <= 2 * TRIALS - n
    assert_kept(first, out)  # restored from the journal, as first stored
    assert_kept(kept, out)
    assert_same_as_reference(out, reference)


def slab_scene(tmp_path: Path, trials: int = 8) -> Path:
    """The small scene with slab truth (a thin slab: a slab-truth trial takes about a second)."""
    path = scene(tmp_path)
    import yaml
    data = yaml.safe_load(path.read_text())
    data["trials"]["count"] = trials
    data["trials"]["truth"] = "slab"
    data["layer_check"] = {"height_mm": 8.0, "layer_z_mm": 4.0, "max_layer_mm": 4.0, "accuracy_mm": None}
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.slow  # the slab-truth run with insertion below covers it (the same kill and resume, and the needle)
def test_slab_truth_run_sigkilled_then_resumed_equals_an_uninterrupted_one(tmp_path):
    """The slab truth's per-worker state (slab, nominal starts) is rebuilt by the resume's workers: same numbers."""
    killed_and_resumed_equals_reference(tmp_path, slab_scene, 4, 16)


def killed_and_resumed_equals_reference(tmp_path: Path, make_scene, kill_after: int, trials: int) -> dict:
    """An uninterrupted run of make_scene(dir) and one SIGKILLed after kill_after trials then resumed: the
    same numbers, and the resume ran some but not all of the trials. Returns the reference's numbers."""
    ref_dir = tmp_path / "ref"
    ref_dir.mkdir()
    done = finish(make_scene(ref_dir), "--jobs", "2", "--out", ref_dir / "run", "--quiet")
    assert done.returncode == 0, done.stderr
    reference = extract(ref_dir / "run" / "results.h5")
    out = tmp_path / "run"
    proc = start(make_scene(tmp_path), "--jobs", "2", "--out", out, "--quiet")
    wait_for_trials(proc, out, kill_after)
    gone, _ = stop(proc, signal.SIGKILL)
    assert gone < 5.0 and proc.returncode == -signal.SIGKILL
    resumed = finish("--resume", out, "--jobs", "2")
    assert resumed.returncode == 0, resumed.stderr
    assert 0 < ran(resumed) < trials
    assert_same_as_reference(out, reference)
    return reference


@pytest.mark.slow  # (the layer's insertion kill, tests/test_resume_stages.py, and slab-truth resume cover its parts)
def test_slab_truth_insertion_run_sigkilled_then_resumed_equals_an_uninterrupted_one(tmp_path):
    """Trials that insert in the slab (docs/model.md §14): a resume's workers rebuild the slab — on its own,
    twice as coarse plane (`in_plane_scale`: the insertion probes that plane) — and rerun the unfinished
    trials' insertions to the same numbers as an uninterrupted run."""
    import yaml

    def with_insertion(path: Path) -> Path:
        data = yaml.safe_load(path.read_text())
        data["insertion"] = {"step_mm": 2.0, "strategies": ["none"]}
        data["layer_check"]["in_plane_scale"] = 2.0  # (a trial in 2 s instead of 9)
        path.write_text(yaml.safe_dump(data))
        return path

    reference = killed_and_resumed_equals_reference(
        tmp_path, lambda directory: with_insertion(slab_scene(directory, trials=2)), 1, 4)
    assert any(k.endswith("miss_mm") for k in reference)


def budget_rows_of(results_h5: Path) -> dict[str, np.ndarray]:
    """Every number of /budget: each row's and target's final errors, misses and failed masks."""
    out = {}
    with h5py.File(results_h5, "r") as f:
        f["budget"].visititems(
            lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


@pytest.mark.slow  # (a budget row is a run's trials: their kill and resume are the default tests')
def test_a_budget_run_sigkilled_between_rows_keeps_them_and_resumes_to_the_same_numbers(tmp_path):
    """A budget row is stored and marked finished as a whole: a SIGKILL after some rows keeps those, and
    `--resume` runs only the others, ending with the uninterrupted run's numbers (trials and every row)."""
    def budget_scene(directory: Path) -> Path:
        import yaml
        path = scene(directory)  # the small scene, with 3 trials per target: a budget row takes about half a second
        data = yaml.safe_load(path.read_text())
        data["trials"]["count"] = 3
        path.write_text(yaml.safe_dump(data))
        return path

    ref_dir = tmp_path / "ref"
    ref_dir.mkdir()
    done = finish(budget_scene(ref_dir), "--budget", "--jobs", "2", "--out", ref_dir / "run", "--quiet")
    assert done.returncode == 0, done.stderr
    with h5py.File(ref_dir / "run" / "results.h5", "r") as f:
        rows = len(f["budget"].attrs["sources"]) - 1  # the `all` row is the run's own trials
    out, log = tmp_path / "run", tmp_path / "stderr.txt"
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "scissor_cli", "simulate", str(budget_scene(tmp_path)),
                                 "--budget", "--jobs", "2", "--out", str(out)], env=env(), stdout=subprocess.DEVNULL,
                                stderr=err, text=True, start_new_session=True)
        t0 = time.monotonic()
        while "budget localisation: done" not in log.read_text():
            assert proc.poll() is None, f"the run ended before it was killed: {log.read_text()}"
            assert time.monotonic() - t0 < 120, "no budget row finished within 120 s"
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        left = alive_after(proc.pid, 30)
        for pid in left:
            os.kill(pid, signal.SIGKILL)
        assert not left, f"workers outlived the SIGKILLed run: {left}"
    resumed = finish("--resume", out, "--jobs", "2")
    assert resumed.returncode == 0, resumed.stderr
    said = " ".join(resumed.stderr.split())
    redone = re.search(r"budget: (\d+) row\(s\)", said)
    assert redone is not None and 0 < int(redone.group(1)) <= rows - 2, said  # camera and localisation kept
    assert_same_as_reference(out, extract(ref_dir / "run" / "results.h5"))
    reference, now = budget_rows_of(ref_dir / "run" / "results.h5"), budget_rows_of(out / "results.h5")
    assert sorted(now) == sorted(reference)
    assert not [k for k in reference if not np.array_equal(now[k], reference[k])]


def run_pool_script(script: Path, text: str) -> tuple[subprocess.Popen, str, str, list[int]]:
    """Run a pool script in a session of its own (as a run is: a pool forked from the test runner's worker shares,
    and once took down, that worker); (process, stdout, stderr, the pids of its group still alive 10 s after it
    ended), nothing of its group left alive. (The group was once read at once and a worker the kernel was
    killing still counted.)"""
    script.write_text(text)
    proc = subprocess.Popen([sys.executable, str(script)], env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=60)
    finally:
        left = alive_after(proc.pid, 10)
        for pid in left:
            os.kill(pid, signal.SIGKILL)
    return proc, out, err, left


LOST_STOP_RUN = """
import signal, sys, time

from scissor_cli.experiments import pool


def sleep_then_nothing(seconds):
    time.sleep(seconds)
    return []


if __name__ == "__main__":
    pool._state.update(defer=0, pending=None, signum=None)
    try:
        pool._on_signal(signal.SIGTERM, None)
    except pool.Interrupted:
        pass  # (lost, as in a finaliser)
    t0 = time.perf_counter()
    try:
        list(pool.run_pool(sleep_then_nothing, [(30.0,), (30.0,)], 2))
    except pool.Interrupted as stop:
        print(f"stopped {time.perf_counter() - t0:.2f}", flush=True)
        sys.exit(stop.exit_code)
    sys.exit(0)
"""


def test_a_stop_whose_exception_was_lost_still_stops_the_pool(tmp_path):
    """A handler's exception raised inside a finaliser is dropped by Python ("Exception ignored in"); the run then
    ignored later signals as its own clean-up's and went on (seen: a SIGTERM'd slab-truth budget ran on). The pool's
    wait raises the stop again within STOP_POLL_S and its workers go. (A process of its own, as a run is: a pool
    forked from the test runner's worker shares that worker's pipes and signals.)"""
    proc, out, err, left = run_pool_script(tmp_path / "lost_stop.py", LOST_STOP_RUN)
    assert proc.returncode == 128 + signal.SIGTERM, err
    seconds = float(re.search(r"stopped ([0-9.]+)", out).group(1))
    assert seconds < 15.0  # (the workers' start-up and one poll, not their 30 s)
    assert not left, "a worker outlived the stopped run"


DYING_WORKER_RUN = """
import os, sys

from scissor_cli.experiments import pool


def die(k):
    os._exit(1)


if __name__ == "__main__":
    try:
        list(pool.run_pool(die, [(0,), (1,)], 2))
    except pool.WorkerLost as lost:
        print(f"lost: {lost}", flush=True)
        sys.exit(1)
    sys.exit(0)
"""


def test_a_worker_that_dies_is_a_clear_error(tmp_path):
    """A worker that dies is `WorkerLost` naming --resume, and the run's other workers go with it. (A process of its
    own, as a run is: a pool forked from the test runner's worker once took that worker down with it in CI.)"""
    proc, out, err, left = run_pool_script(tmp_path / "dying_worker.py", DYING_WORKER_RUN)
    assert proc.returncode == 1, err
    assert "worker process died" in out and "--resume" in out, out
    assert not left, "a worker outlived the run"
