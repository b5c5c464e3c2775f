"""`scissor report`: box plots and summary tables from runs; refusal of incomplete runs."""

import csv
import subprocess
import sys

import h5py
import numpy as np
import pytest

from scissor_cli.experiments.simulate import Execution, run_simulation
from scissor_cli.output.report import ReportError, report_trials
from scissor_cli.output.results_sink import RunDirectory

from figure_checks import assert_figure_readable, assert_png_drawn
from test_trials import reduced


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    a, b = tmp_path_factory.mktemp("pros"), tmp_path_factory.mktemp("exv")
    run_simulation(reduced(trials=4), RunDirectory(a), execution=Execution(jobs=1))
    run_simulation(reduced(trials=4, profile="ex_vivo"), RunDirectory(b), execution=Execution(jobs=1))
    return a, b


def test_report_writes_plots_and_tables(two_runs, tmp_path):
    out = report_trials(list(two_runs), tmp_path / "rep")
    assert_png_drawn(tmp_path / "rep" / "error_boxplots.png")
    rows = list(csv.DictReader(open(tmp_path / "rep" / "summary.csv")))
    assert [r["target"] for r in rows] == ["T1", "T2", "T1", "T2"]
    assert "prosthesis" in rows[0]["run"] and "ex_vivo" in rows[2]["run"]
    with h5py.File(two_runs[0] / "results.h5") as f:
        e = np.abs(f["trials/T1/final_error"][:])
    assert float(rows[0]["max_x"]) == pytest.approx(e[:, 0].max(), abs=1e-3)
    assert float(rows[0]["median_y"]) == pytest.approx(np.median(e[:, 1]), abs=1e-3)
    assert "| T2 |" in out.table_markdown


def test_report_figures_are_readable(two_runs):
    """The box plots `report_trials` draws, from the two runs' trials: labelled, titled, with data."""
    from scissor_cli.output import figures
    from scissor_cli.output.miss_figures import miss_boxplots
    from scissor_cli.output.report import load_run

    runs = [load_run(d) for d in two_runs]
    assert_figure_readable(figures.error_boxplots([(r.label, {t: d.errors for t, d in r.targets.items()})
                                                   for r in runs]))
    misses = [(r.label, {t: d.miss for t, d in r.targets.items() if d.miss is not None}) for r in runs]
    assert all(m for _, m in misses)
    assert_figure_readable(miss_boxplots(misses))
    iterations = {t: d.iterations for t, d in runs[0].targets.items()}
    assert_figure_readable(figures.iterations_histogram(iterations, "control iterations per trial"))


def test_report_refuses_incomplete_run_unless_partial(two_runs, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(two_runs[0], bad)
    with h5py.File(bad / "results.h5", "r+") as f:
        f.attrs["status"] = "failed"
    proc = subprocess.run([sys.executable, "-m", "scissor_cli.cli", "report", str(bad), "--out", str(tmp_path / "r")],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "--partial" in proc.stderr and "Traceback" not in proc.stderr
    report_trials([bad], tmp_path / "r2", partial=True)
    with pytest.raises(ReportError, match="no results.h5"):
        report_trials([tmp_path], tmp_path / "r3")


def test_study_report(tmp_path):
    """A small study through simulate and report: the plot, the cheapest-setting table, graded vs uniform."""
    from scissor_cli.config import StudyConfig, load_config

    from helpers import ROOT

    cfg = load_config(ROOT / "configs" / "example.yaml")
    cfg = cfg.model_copy(update={
        "forward": cfg.forward[1:],
        "trials": cfg.trials.model_copy(update={"count": 0}),
        "study": StudyConfig(levels=[4.0, 2.0, 1.0], models=["linear", "neo_hookean_fiber"],
                             admm_tolerances=[1e-2, 1e-4], repeats=1, admm_max_elements=10000),
    })
    run_simulation(cfg, RunDirectory(tmp_path / "run"))
    with h5py.File(tmp_path / "run" / "results.h5") as f:
        study = f["study"]
        n = len(study["case"])
        sizes = dict(zip(zip(study["kind"][:].astype(str), study["level"][:]), study["n_elements"][:]))
        with_admm = sum(1 for v in sizes.values() if v <= 10000)
        # per mesh and model: Newton, plus plain and Anderson ADMM at two tolerances where the mesh is small enough
        assert n == 2 * (len(sizes) + 4 * with_admm) and len(sizes) == 6 and with_admm == 5
        assert study["time_s"].attrs["units"] == "s" and study.attrs["reference_model"] == "neo_hookean_fiber"
        newton = study["solver"][:].astype(str) == "newton"
        assert np.all(study["error_discrete_mm"][:][newton] == 0)
    from scissor_cli.output.report import make_report

    rep = make_report([tmp_path / "run"], tmp_path / "rep")
    assert (tmp_path / "rep" / "study_cheapest.csv").exists()
    rows = list(csv.DictReader(open(tmp_path / "rep" / "study_cheapest.csv")))
    assert {r["accuracy_mm"] for r in rows} == {"1.000", "0.100", "0.010"}
    one_mm = next(r for r in rows if r["accuracy_mm"] == "1.000")
    assert one_mm["solver"] != "none reaches it" and float(one_mm["error_reference_mm"]) <= 1.0
    assert any(p.name.startswith("speed_vs_error") for p in rep.files)
    assert "graded mesh needs" in rep.table_markdown


def test_a_target_without_a_plan_counts_no_trials(two_runs, tmp_path):
    """Its trials are stored done with stop_reason no_plan and zero errors: the summary, the paper table and the
    budget's `all` row must not count them (they would read as perfect trials)."""
    import shutil

    from scissor_cli.output.error_budget.report import paper_row
    from scissor_cli.output.results import finished_trials

    run = tmp_path / "unplanned"
    shutil.copytree(two_runs[0], run)
    with h5py.File(run / "results.h5", "r+") as f:
        g = f["trials/T2"]
        g["stop_reason"][...] = np.array(["no_plan"] * g["stop_reason"].shape[0], dtype=object)
        g["final_error"][...] = 0.0
        assert not finished_trials(g).any() and finished_trials(f["trials/T1"]).all()
        n_t1 = int(f["trials/T1/done"][:].sum())
        assert paper_row("run", f)["trials"] == n_t1
    report_trials([run], tmp_path / "rep")
    rows = {r["target"]: r for r in csv.DictReader(open(tmp_path / "rep" / "summary.csv"))}
    assert rows["T2"]["trials"] == "0" and rows["T2"]["max_x"] == ""
    assert int(rows["T1"]["trials"]) == n_t1


def test_extra_iterations_count_what_the_loop_took_beyond_the_drives_speed(tmp_path):
    """iterations − ceil(max over cups of |final stroke| / (speed / rate)): the loop's own share of its time."""
    import h5py

    from scissor_cli.output.report import _extra_iterations

    columns = np.array(["time_s", "stroke_cmd_a", "stroke_a", "stroke_cmd_b", "stroke_b", "measured_x"], dtype=object)
    with h5py.File(tmp_path / "r.h5", "w") as f:
        g = f.create_group("trials/T1")
        g["iterations"] = np.array([5, 12, 9])
        for k, final in enumerate(([1.0, 0.2], [0.4, -3.2], [0.0, 0.0])):
            h = g.create_dataset(f"history/{k}",
                                 data=np.array([[0, 0, 0, 0, 0, 1.0], [0.1, 9, final[0], 9, final[1], 1.0]]))
            h.attrs["columns"] = columns
        step = np.array([0.5, 0.5])  # 5 mm/s at 10 Hz
        np.testing.assert_array_equal(_extra_iterations(g, np.array([0, 1, 2]), step), [5 - 2, 12 - 7, 9 - 0])
        np.testing.assert_array_equal(_extra_iterations(g, np.array([1]), np.array([0.5, 1.0])), [12 - 4])
        assert _extra_iterations(g, np.array([0]), None) is None
