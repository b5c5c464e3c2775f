"""The error budget (docs/model.md §16): rows are ordinary trial runs of variant configs, bit for bit."""

from __future__ import annotations

import subprocess
import sys

import h5py
import numpy as np
import pytest
import yaml

from scissor_cli.config import parse_config, resolved_yaml
from scissor_cli.experiments.error_budget import ROWS, budget_plan, identical_trials
from scissor_cli.output.error_budget.results import BudgetCell, budget_rows

from figure_checks import assert_png_drawn
from helpers import deep_update, example_dict, write_scene


def _small(count: int = 3) -> dict:
    data = example_dict()
    deep_update(data, "tissue.mesh.max_edge_mm", 8.0)
    deep_update(data, "tissue.mesh.min_edge_mm", 2.0)
    deep_update(data, "solver.kind", "newton")
    deep_update(data, "trials.count", count)
    return data


def _simulate(path, out, *extra):
    proc = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(path), "--out", str(out), "--quiet",
                           "--jobs", "2", *extra], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return out / "results.h5"


def _here(path, out):
    """The config at `path` run through the API in this process, as `scissor simulate` runs it; its results.h5.
    (The runs a budget row is compared with: their numbers, not the command, are on test.)"""
    from scissor_cli import api

    api.simulate(api.load_config(path), out)
    return out / "results.h5"


@pytest.fixture(scope="module")
def budget_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("budget")
    scene = write_scene(tmp, _small())
    return tmp, scene, _simulate(scene, tmp / "run", "--budget")


def test_a_row_is_the_trials_of_its_variant_config(budget_run):
    tmp, scene, h5_path = budget_run
    cfg = parse_config(scene.read_text())
    variant = budget_plan(cfg).rows["localisation"]
    assert variant.trials.pixel_noise_px == 0 and variant.trials.E_log_sd == 0 and variant.trials.backlash_mm == 0
    path = tmp / "variant.yaml"
    path.write_text(resolved_yaml(variant))
    alone = _here(path, tmp / "alone")
    with h5py.File(h5_path) as a, h5py.File(alone) as b:
        for target in ("T1", "T2"):
            assert np.array_equal(a[f"budget/localisation/{target}/final_error"][()],
                                  b[f"trials/{target}/final_error"][()])
            assert np.array_equal(a[f"budget/localisation/{target}/miss_mm"][()],
                                  b[f"trials/{target}/manipulation_miss_mm"][()])


def test_a_row_that_draws_nothing_runs_once_and_equals_its_variant_run_in_full(budget_run):
    """The `none` row switches every source off: its trials are all the same, so the budget runs one per target.
    Its stored trials equal those of its variant config run alone with every trial run, bit for bit."""
    tmp, scene, h5_path = budget_run
    cfg = parse_config(scene.read_text())
    plan = budget_plan(cfg)
    assert identical_trials(plan.rows["none"]) and not identical_trials(plan.rows["camera"])
    path = tmp / "none.yaml"
    path.write_text(resolved_yaml(plan.rows["none"]))
    alone = _here(path, tmp / "none")
    with h5py.File(h5_path) as a, h5py.File(alone) as b:
        assert a["budget/none"].attrs["identical_trials"] and "identical_trials" not in a["budget/camera"].attrs
        for target in ("T1", "T2"):
            stored = a[f"budget/none/{target}/final_error"][()]
            assert stored.shape == (cfg.trials.count, 2)
            assert np.array_equal(stored, b[f"trials/{target}/final_error"][()])
            assert np.array_equal(a[f"budget/none/{target}/miss_mm"][()],
                                  b[f"trials/{target}/manipulation_miss_mm"][()])


def test_only_rows_without_a_drawn_source_or_speckle_are_identical():
    data = _small()
    data["layer_check"] = {"height_mm": 20.0, "layer_z_mm": 10.0, "max_layer_mm": 10.0, "accuracy_mm": None}
    plan = budget_plan(parse_config(yaml.safe_dump(data)))
    assert {name for name, row in plan.rows.items() if identical_trials(row)} == {"none", "slab"}
    # (with imaging the speckle is drawn in every row: tests/test_ultrasound_loop.py)


def test_the_all_row_is_the_ordinary_trials(budget_run):
    tmp, scene, h5_path = budget_run
    plain = _here(scene, tmp / "plain")
    with h5py.File(h5_path) as a, h5py.File(plain) as b:
        assert list(a["budget"].attrs["sources"])[0] == "all"
        for target in ("T1", "T2"):
            assert np.array_equal(a[f"trials/{target}/final_error"][()], b[f"trials/{target}/final_error"][()])
        rows = [r for r in a["budget"].attrs["sources"] if r != "all"]
        assert set(rows) == {"camera", "localisation", "E", "nu", "eta", "fiber", "actuator", "none"}
        assert a["budget"].attrs["paper_max_mm"].shape == (2, 2)
    assert_png_drawn(tmp / "run" / "budget.png")


def test_rows_the_scene_cannot_have_are_skipped_with_a_note():
    data = _small()
    plan = budget_plan(parse_config(yaml.safe_dump(data)))
    assert "slab" not in plan.rows and "needle" not in plan.rows and "release_slip" not in plan.rows
    assert any("layer_check" in n for n in plan.notes) and any("insertion" in n for n in plan.notes)
    deep_update(data, "trials.profile", "ideal")
    plan = budget_plan(parse_config(yaml.safe_dump(data)))
    assert list(plan.rows) == ["none"]  # every spread is 0: only the floor is left
    data = _small()
    data["layer_check"] = {"height_mm": 20.0, "layer_z_mm": 10.0, "max_layer_mm": 10.0, "accuracy_mm": None}
    plan = budget_plan(parse_config(yaml.safe_dump(data)))
    assert plan.rows["slab"].trials.truth == "slab" and plan.rows["camera"].trials.truth == "layer"
    assert set(ROWS) >= set(plan.rows)


def test_budget_without_trials_is_refused(tmp_path):
    data = deep_update(deep_update(_small(), "trials.count", 0), "trials.budget", True)
    proc = subprocess.run([sys.executable, "-m", "scissor_cli", "validate", str(write_scene(tmp_path, data))],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "trials.budget" in proc.stderr and "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate",
                           str(write_scene(tmp_path, _small(), "b.yaml")),
                           "--budget", "--trials", "0", "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert proc.returncode == 2 and "--budget" in proc.stderr and "Traceback" not in proc.stderr


def test_variance_shares_of_independent_sources_add_up():
    rng = np.random.default_rng(3)
    a, b = rng.normal(0, 0.3, (4000, 2)), rng.normal(0, 0.4, (4000, 2))
    cells = {"all": {"T": BudgetCell(a + b, np.zeros(4000))}, "a": {"T": BudgetCell(a, np.zeros(4000))},
             "b": {"T": BudgetCell(b, np.zeros(4000))}}
    share = {r["source"]: r["variance_share"] for r in budget_rows(cells)}
    assert share["all"] == 1.0
    assert share["a"] == pytest.approx(0.36, abs=0.03) and share["b"] == pytest.approx(0.64, abs=0.03)


def test_a_bias_has_no_variance_but_its_mean_square_share_says_it_dominates():
    """The slab truth moves every trial the same way (it ends short at the stroke limit): variance 0, yet it is
    most of the error; the mean-square share counts it, and equals the variance share for zero-mean sources."""
    rng = np.random.default_rng(5)
    noise, bias = rng.normal(0, 0.2, (4000, 2)), np.tile([0.0, 2.0], (4000, 1))
    cells = {"all": {"T": BudgetCell(noise + bias, np.zeros(4000))}, "slab": {"T": BudgetCell(bias, np.zeros(4000))},
             "camera": {"T": BudgetCell(noise, np.zeros(4000))}}
    rows = {r["source"]: r for r in budget_rows(cells)}
    assert rows["slab"]["variance_share"] == 0.0
    assert rows["slab"]["mean_square_share"] == pytest.approx(4.0 / 4.08, abs=0.01)
    assert rows["camera"]["mean_square_share"] == pytest.approx(0.08 / 4.08, abs=0.005)
    assert rows["all"]["mean_square_share"] == 1.0


@pytest.mark.slow  # (its rows are runs' trials, which the layer budget above and the slab-truth trials test by default)
def test_slab_truth_budget_runs_with_its_3d_row(tmp_path):
    """--truth slab --budget: the all row against the slab, a slab row, the other rows on the layer; the report's
    paper table names the truth."""
    data = _small(1)
    # (a slab on its own plane twice as coarse as the layer's: the budget's rows, not the slab's fidelity, on test)
    data["layer_check"] = {"height_mm": 8.0, "layer_z_mm": 4.0, "max_layer_mm": 4.0, "in_plane_scale": 2.0,
                          "accuracy_mm": None}
    data["forward"] = [{"name": "push4", "strokes": {"cup": 4.0}}]
    scene = write_scene(tmp_path, data)
    h5 = _simulate(scene, tmp_path / "run", "--budget", "--truth", "slab")
    with h5py.File(h5) as f:
        rows = set(f["budget"].keys())
        assert {"slab", "camera", "none"} <= rows and "trials" in f  # the all row is the run's own /trials
    assert_png_drawn(tmp_path / "run" / "budget.png")
    rep = subprocess.run([sys.executable, "-m", "scissor_cli", "report", str(tmp_path / "run"), "--out",
                          str(tmp_path / "rep")], capture_output=True, text=True, timeout=600)
    assert rep.returncode == 0, rep.stderr
    table = (tmp_path / "rep" / "paper_table.csv").read_text()
    assert "slab" in table and "prone" in table
