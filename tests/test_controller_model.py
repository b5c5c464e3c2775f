"""The controller's model of the tissue (docs/model.md §15): calibrated, surrogate, slab — against the slab."""

from __future__ import annotations

import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from scissor_cli import progress
from scissor_cli.config import parse_config, resolved_yaml
from scissor_cli.control.models import INVERSE_TOL_MM, MapController, strokes_for
from scissor_cli.experiments.build import build_model
from scissor_cli.layer3d.calibration import calibration_strokes, fit_transmission
from scissor_cli.layer3d.check import slab_spec
from scissor_cli.layer3d.slab import build_slab, layer_probe, slab_probe
from scissor_cli.layer3d.surrogate import Surrogate, design, solve_samples
from scissor_cli.layer3d.tissue_models import ControllerModel, ModelData, build_model_data, slab_map
from scissor_cli.layer3d.truth import SLAB_TRUTH_TOL
from scissor_cli.mesh.probe import probe_targets, target_positions

from figure_checks import assert_png_drawn
from helpers import deep_update, example_dict, write_scene

ROOT = Path(__file__).resolve().parents[1]


def small(model: str = "layer", trials: int = 0) -> dict:
    """The example scene, coarse, against a thin slab whose chest wall is free (so a cup moves it)."""
    data = example_dict()
    deep_update(data, "tissue.mesh.max_edge_mm", 8.0)
    deep_update(data, "tissue.mesh.min_edge_mm", 2.0)
    deep_update(data, "solver.kind", "newton")
    data["forward"] = data["forward"][:1]
    data["targets"][0]["desired_mm"] = [50.0, 26.0]
    data["targets"][1]["desired_mm"] = [58.0, 21.0]
    data["trials"]["count"] = trials
    data["trials"]["truth"] = "slab"
    data["layer_check"] = {"height_mm": 8.0, "layer_z_mm": 4.0, "max_layer_mm": 4.0, "chest_wall_fixed": False,
                          "accuracy_mm": None}
    data["controller"]["model"] = model
    data["controller"]["surrogate"] = {"samples": 8}
    return data


@pytest.fixture(scope="module")
def scene():
    cfg = parse_config(resolved_yaml(parse_config(yaml.safe_dump(small()))))
    _, mesh, tissue = build_model(cfg)
    slab = build_slab(tissue.scene, mesh, slab_spec(cfg.layer_check, cfg.tissue.mesh), model=tissue.params.model)
    rests = np.array([t.rest for t in tissue.scene.targets])
    return cfg, tissue, slab, rests


@pytest.fixture(scope="module")
def surrogate_data(scene):
    cfg, tissue, slab, _ = scene
    return build_model_data("surrogate", tissue, slab, [], 8)


def test_design_spans_the_stroke_box_with_its_corners_and_keeps_held_out_points_apart():
    lo, hi = np.array([-15.0, -5.0]), np.array([15.0, 10.0])
    train, held = design(lo, hi, 16)
    assert train.shape == (16, 2) and held.shape == (4, 2)
    assert np.all(train >= lo) and np.all(train <= hi) and np.all(held >= lo) and np.all(held <= hi)
    for corner in ([-15, -5], [-15, 10], [15, -5], [15, 10]):
        assert np.any(np.all(train == corner, axis=1))
    assert np.min(np.linalg.norm(train[:, None] - held[None], axis=2)) > 1e-6


def test_surrogate_is_exact_at_its_samples_and_within_0_05_mm_in_plane_of_held_out_slab_solves(scene, surrogate_data):
    _, tissue, slab, rests = scene
    s = Surrogate(surrogate_data.samples)
    d = surrogate_data.samples
    assert np.allclose(s.predict(d.strokes), d.targets, atol=1e-6)
    assert surrogate_data.validation_error_mm == pytest.approx(s.validation_error_mm())
    # a fresh slab solve at strokes in neither set
    fresh = np.array([[-11.3], [2.7], [9.1]])
    truth, truth_layer = solve_samples(slab, slab_probe(slab, rests), fresh, SLAB_TRUTH_TOL,
                                       layer=layer_probe(slab, tissue.mesh))
    assert np.max(np.linalg.norm((s.predict(fresh) - truth)[:, :, :2], axis=2)) <= 0.05
    assert surrogate_data.validation_error_mm <= 0.05
    # the layer too (what a plan made again with the model judges its obstacles on): exact at the samples,
    # and close to fresh solves; at rest it is the 2-D mesh
    assert s.knows_layer and np.allclose(s.layer_at(d.strokes[0]), d.layer[0], atol=1e-6)
    layer_miss = max(np.max(np.linalg.norm(s.layer_at(f) - truth_layer[k], axis=1)) for k, f in enumerate(fresh))
    assert layer_miss <= 0.2 and s.layer_error_mm() <= 0.2  # (8 samples: 0.07 / 0.10 mm, worst at the cup)


def test_surrogate_jacobian_matches_the_slabs_tangent(scene, surrogate_data):
    """J of the learned map against the nominal slab's exact tangent response at the same strokes."""
    _, tissue, slab, rests = scene
    model = ControllerModel(surrogate_data, tissue, slab)
    slab_answer = slab_map(slab, tissue, rests)
    for stroke in (-6.0, 4.0):
        y_m, J_m = model.scene_map()(np.array([stroke]))
        y_s, J_s = slab_answer(np.array([stroke]))
        assert np.max(np.abs(y_m - y_s)) <= 0.05
        assert np.max(np.abs(J_m - J_s)) <= 0.05 * np.max(np.abs(J_s))


def test_every_model_answers_the_same_questions(scene, surrogate_data):
    """positions and J of all four through one interface; the controller moves with its command."""
    cfg, tissue, slab, rests = scene
    datas = [ModelData("layer"), build_model_data("calibrated", tissue, slab, [np.array([4.0])], 8), surrogate_data,
             ModelData("slab")]
    for data in datas:
        model = ControllerModel(data, tissue, slab)
        y, J = model.scene_map()(np.array([3.0]))
        assert y.shape == (2, 2) and J.shape == (2, 2, 1) and np.all(np.isfinite(J))
        c = model.controller(1, [-15.0], [15.0])
        J0 = c.jacobian.copy()
        c.update(np.array([5.0]))
        assert c.jacobian.shape == (2, 1) and np.array_equal(c.strokes, [5.0])
        assert not np.array_equal(c.jacobian, J0)  # the tissue is nonlinear: J moves with the stroke


def test_calibration_finds_the_slab_moves_less_than_the_layer_and_fits_it_better(scene):
    cfg, tissue, slab, rests = scene
    lo, hi = np.array([-15.0]), np.array([15.0])
    values = calibration_strokes(lo, hi, [np.array([4.0])])
    assert np.allclose(values[0], [2.0, 4.0, 15.0])
    probe = probe_targets(tissue.mesh, rests)
    cal = fit_transmission(tissue, probe, slab, slab_probe(slab, rests), values, SLAB_TRUTH_TOL)
    assert 0.0 < cal.transmission[0] < 1.0  # the layer overstates the cup's effect
    layer = ControllerModel(ModelData("layer"), tissue).scene_map()
    calibrated = ControllerModel(ModelData("calibrated", calibration=cal), tissue).scene_map()
    s = np.array([4.0])
    slab_y = cal.targets[1, :, :2]  # the slab at the fitting stroke 4 mm
    assert np.max(np.linalg.norm(calibrated(s)[0] - slab_y, axis=1)) <= cal.error_mm + 1e-9
    # over every fitting stroke the calibrated layer's worst distance to the slab is below the plain layer's
    layer_worst = max(np.max(np.linalg.norm(layer(np.array([v]))[0] - cal.targets[k, :, :2], axis=1))
                      for k, v in enumerate(values[0]))
    assert cal.error_mm < layer_worst


def _linear_map(A: np.ndarray, y0: np.ndarray):
    return lambda s: (y0 + A @ s, A)


def test_inverse_reaches_a_reachable_point_and_says_how_far_an_unreachable_one_stays():
    A = np.array([[0.1, 0.0], [-0.3, 0.2]])
    y0 = np.array([50.0, 30.0])
    want = y0 + A @ np.array([4.0, -2.0])
    s, left = strokes_for(_linear_map(A, y0), want, [-10, -10], [10, 10], None, "position")
    assert left <= INVERSE_TOL_MM and np.allclose(s, [4.0, -2.0], atol=0.05)
    # miss mode, needle along x: only y is driven; one cup suffices
    s, left = strokes_for(_linear_map(A[:, :1], y0), y0 + np.array([5.0, -0.9]), [-10], [10], np.array([1.0, 0.0]))
    assert left <= INVERSE_TOL_MM and s[0] == pytest.approx(3.0, abs=0.01)
    s, left = strokes_for(_linear_map(A[:, :1], y0), y0 + np.array([0.0, -6.0]), [-10], [10], np.array([1.0, 0.0]))
    assert s[0] == pytest.approx(10.0) and left == pytest.approx(3.0, abs=1e-6)


def test_map_controller_is_the_maps_answer_at_the_command():
    A = np.array([[0.1], [-0.3]])
    c = MapController(_linear_map(A, np.zeros(2)), 1, [-5], [5])
    c.update(np.array([2.0]))
    assert np.allclose(c.position, [0.2, -0.6]) and np.allclose(c.jacobian, A) and not c.shares(None)


@pytest.mark.parametrize("model", ["calibrated", "surrogate", "slab"])
def test_a_model_made_from_the_slab_needs_a_layer_check(tmp_path, model):
    data = small(model)
    del data["layer_check"]
    data["trials"]["truth"] = "layer"
    r = _cli("validate", write_scene(tmp_path, data))
    assert r.returncode == 2 and "controller.model" in r.stderr and "layer_check" in r.stderr


def test_a_surrogate_needs_enough_samples_for_its_cups(tmp_path):
    data = small("surrogate")
    data["controller"]["surrogate"] = {"samples": 5}
    r = _cli("validate", write_scene(tmp_path, data))
    assert r.returncode == 2 and "controller.surrogate.samples" in r.stderr and "at least 8" in r.stderr


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "scissor_cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, cwd=cwd)


@pytest.mark.slow  # (two whole runs, 40 s: the surrogate's fit, J, inverse and plans are the default tests above)
def test_surrogate_run_records_the_model_plans_with_it_and_reuses_its_cache(tmp_path):
    """simulate: /controller_model with its samples, the plans' model and slab strokes, the path figure; a
    second run takes the model from the cache beside the runs and gives the same trials."""
    scene_path = write_scene(tmp_path, small("surrogate", trials=2))
    first = _cli("simulate", scene_path, "--out", tmp_path / "runs" / "a", "--jobs", "1")
    assert first.returncode == 0, first.stderr
    out = " ".join(first.stdout.split() + first.stderr.split())
    assert "controller model surrogate: in" in out
    with h5py.File(tmp_path / "runs" / "a" / "results.h5") as f:
        g = f["controller_model"]
        assert g.attrs["kind"] == "surrogate" and g.attrs["validation_error_mm"] <= 0.05
        assert g["samples/strokes"].shape == (8, 1) and g["samples/targets/T1"].shape == (8, 3)
        assert g["held_out/strokes"].shape == (4, 1)
        plan = f["plan/T2"].attrs
        assert np.array_equal(plan["strokes"], plan["model_strokes"])
        assert abs(plan["model_strokes"][0] - plan["slab_strokes"][0]) <= 0.25  # (the layer asks 1.3 mm less)
        assert 0 <= plan["model_error_mm"] <= 0.05  # the surrogate is the slab at its plan
        first_errors = f["trials/T2/final_error"][()]
    assert_png_drawn(tmp_path / "runs" / "a" / "controller_model.png")
    with h5py.File(tmp_path / "runs" / "a" / "results.h5") as f:
        assert f["controller_model/paths"].attrs["kind"] == "surrogate"  # what report draws beside other models
    second = _cli("simulate", scene_path, "--out", tmp_path / "runs" / "b", "--jobs", "1")
    assert second.returncode == 0, second.stderr
    assert "from the cache" in " ".join(second.stdout.split() + second.stderr.split())
    with h5py.File(tmp_path / "runs" / "b" / "results.h5") as f:
        assert np.array_equal(f["trials/T2/final_error"][()], first_errors)
    # the report's table names the model beside the stops at the stroke limit and the time per iteration
    report = _cli("report", tmp_path / "runs" / "a", "--out", tmp_path / "report")
    assert report.returncode == 0, report.stderr
    csv = (tmp_path / "report" / "summary.csv").read_text().splitlines()
    header = csv[0].split(",")
    row = dict(zip(header, csv[1].split(",")))
    assert row["controller"] == "surrogate" and int(row["stroke_limit_stops"]) >= 0
    assert float(row["model_error_mm"]) <= 0.05 and float(row["time_per_iteration_s"]) > 0
    assert 0 <= float(row["plan_model_error_mm"]) <= 0.05
    assert_png_drawn(tmp_path / "report" / "controller_models.png")


@pytest.mark.slow  # (a plan refused before the trials: tests/test_planner.py's infeasible plans are the default's)
def test_a_target_the_slab_cannot_reach_is_reported_before_any_trial(tmp_path):
    """With the chest wall held the thin slab barely moves: the calibrated plan is infeasible, said up front."""
    data = small("calibrated", trials=2)
    data["layer_check"]["chest_wall_fixed"] = True
    data["targets"] = data["targets"][:1]
    r = _cli("simulate", write_scene(tmp_path, data), "--out", tmp_path / "run", "--jobs", "1")
    assert r.returncode == 0, r.stderr
    said = " ".join(r.stdout.split() + r.stderr.split())
    assert "plan T1: infeasible: the calibrated controller model cannot bring the target" in said
    assert "trials done" not in said or "0 to run" in said
    with h5py.File(tmp_path / "run" / "results.h5") as f:
        assert not f["plan/T1"].attrs["feasible"] and "slab_strokes" in f["plan/T1"].attrs


def test_surrogate_trained_in_two_workers_equals_one_after_the_other(scene, surrogate_data):
    """The design's two groups solved in worker processes: the same numbers, bit for bit."""
    from scissor_cli.experiments.controller_model_stage import fitted_model

    _, tissue, slab, _ = scene
    cfg = parse_config(resolved_yaml(parse_config(yaml.safe_dump(small("surrogate")))))
    data, cached = fitted_model(cfg, tissue, slab, [], None, jobs=2)
    assert not cached
    assert np.array_equal(data.samples.targets, surrogate_data.samples.targets)
    assert np.array_equal(data.samples.held_targets, surrogate_data.samples.held_targets)


@pytest.mark.slow  # (tests/test_resume_stages.py resumes after the plans; this adds the stored model's path)
def test_a_resumed_run_steers_with_the_model_it_stored(tmp_path, monkeypatch):
    """Stopped after its plans, cache deleted: --resume reads /controller_model (its plans were made with it)
    and finishes with the numbers of an uninterrupted run."""
    from scissor_cli.config import load_config
    from scissor_cli.experiments.simulate import Execution, resume_simulation, run_simulation
    from scissor_cli.output import results_sink as sink_module
    from scissor_cli.output.results_sink import RunDirectory, open_for_resume

    path = write_scene(tmp_path, small("calibrated", trials=1))
    run_simulation(load_config(path), RunDirectory(tmp_path / "runs" / "reference"), execution=Execution(jobs=1))

    def stopped(self, *args):
        raise KeyboardInterrupt("SIGINT")

    monkeypatch.setattr(sink_module.ResultsSink, "manipulation", stopped)
    run = tmp_path / "runs" / "stopped"
    with pytest.raises(KeyboardInterrupt):
        run_simulation(load_config(path), RunDirectory(run), execution=Execution(jobs=1))
    monkeypatch.undo()
    shutil.rmtree(tmp_path / "runs" / ".scissor-cache")  # the model can only come from the file
    assert resume_simulation(open_for_resume(run), execution=Execution(jobs=1)) == 2
    with h5py.File(tmp_path / "runs" / "reference" / "results.h5") as a, h5py.File(run / "results.h5") as b:
        assert b.attrs["status"] == "complete"
        assert np.array_equal(a["controller_model"].attrs["transmission"], b["controller_model"].attrs["transmission"])
        for t in ("T1", "T2"):
            assert np.array_equal(a[f"plan/{t}"].attrs["model_strokes"], b[f"plan/{t}"].attrs["model_strokes"])
            assert a[f"plan/{t}"].attrs["model_error_mm"] == b[f"plan/{t}"].attrs["model_error_mm"]
            assert np.array_equal(a[f"trials/{t}/final_error"][()], b[f"trials/{t}/final_error"][()])


class _Said(progress.SilentReporter):
    """A reporter that keeps the lines it is told."""

    def __init__(self):
        self.lines = []

    def info(self, line):
        self.lines.append(line)


def _planned(cfg, plans, model, slab_answer, said, replan=None):
    """`plan_with_model`, its messages to `said`."""
    from scissor_cli.experiments.model_planning import plan_with_model

    with progress.reporting(said):
        return plan_with_model(cfg, plans, model, slab_answer, replan)


def test_a_model_that_cannot_reach_the_layers_point_gets_its_own_plan():
    """A 3-D-aware model whose target moves half as far as the layer's: the layer's desired point is out of its
    reach, so the planner chose again on the model's positions (the model reaches the new point at the plan's
    strokes); a desired point from the config is never moved: that plan is refused, saying why."""
    from types import SimpleNamespace

    from scissor_cli.config import load_config
    from scissor_cli.experiments.model_planning import reserved_scene
    from scissor_cli.planning.needle_plan import plan_target
    from scissor_cli.planning.states import StateCache

    cfg = load_config(ROOT / "configs" / "paper_push.yaml")
    # (a target half as far finds a clear corridor for T1 inside ±14.25 mm, none inside the default ±13.5)
    cfg = cfg.model_copy(update={"controller": cfg.controller.model_copy(update={"stroke_reserve": 0.05})})
    _, mesh, tissue = build_model(cfg, mesh_scale=2.0)
    scene = tissue.scene
    probe = probe_targets(mesh, np.array([t.rest for t in scene.targets]))
    cache = StateCache(tissue)
    rests = np.array([t.rest for t in scene.targets])

    def half_as_far(strokes):
        return rests + 0.5 * (target_positions(probe, cache.state(np.asarray(strokes, float))) - rests)

    def answer(strokes, h=0.25):
        J = (half_as_far(strokes + h) - half_as_far(strokes - h)) / (2 * h)
        return half_as_far(strokes), J[:, :, None]

    model = SimpleNamespace(kind="surrogate", transmission=None, scene_map=lambda: answer, layer_map=lambda: None)
    plans = [plan_target(tissue, scene, t, cfg.needle, cache=cache) for t in scene.targets]

    def replan(t, target_at, layer_at=None):  # as simulate plans again: inside the stroke reserve
        return plan_target(tissue, reserved_scene(scene, cfg.controller.stroke_reserve), scene.targets[t],
                           cfg.needle, cache=cache, target_at=target_at)

    said = _Said()
    again = _planned(cfg, plans, model, None, said, replan)
    tol = cfg.controller.tolerance_mm
    for t, (plan, layer_plan) in enumerate(zip(again, plans)):
        assert np.linalg.norm(half_as_far(layer_plan.strokes)[t] - layer_plan.desired) > tol  # out of reach
        if plan.feasible:
            assert plan.planned_with == "surrogate"
            np.testing.assert_array_equal(plan.strokes, plan.model_strokes)
            assert np.linalg.norm(half_as_far(plan.strokes)[t] - plan.desired) <= tol
        else:  # (T2: no corridor clears the nerve at the positions this model reaches) both verdicts said
            assert "cannot bring the target" in plan.reason
            assert "planned again on the model's target positions: no entry side" in plan.reason
    replanned = [p.target for p in again if p.planned_with == "surrogate"]
    assert replanned == ["T1"]
    assert sum("planned again on the model's target positions" in line for line in said.lines) == 1
    # the same point from the config: refused, not moved
    fixed = cfg.model_copy(update={"targets": [t.model_copy(update={"desired_mm": list(p.desired)})
                                               for t, p in zip(cfg.targets, plans)]})
    refused = _planned(fixed, plans, model, None, _Said(), replan)
    assert not any(p.feasible for p in refused)
    assert all("cannot bring the target" in p.reason and p.planned_with == "layer" for p in refused)


def test_a_3d_model_whose_plan_the_slab_blocks_plans_again_on_its_own_obstacles():
    """The layer's plan is reachable for the model but the nominal slab blocks its corridor: the target is
    planned again with the model's target positions and its layer (obstacles, skin), and that plan is judged
    on the slab again; if the new plan fails too, the refusal gives both reasons."""
    from types import SimpleNamespace

    from scissor_cli.config import load_config
    from scissor_cli.planning.needle_plan import plan_target
    from scissor_cli.planning.states import StateCache

    cfg = load_config(ROOT / "configs" / "paper_push.yaml")
    cfg = cfg.model_copy(update={"targets": cfg.targets[:1]})
    _, mesh, tissue = build_model(cfg, mesh_scale=2.0)
    cache = StateCache(tissue)
    plan = plan_target(tissue, tissue.scene, tissue.scene.targets[0], cfg.needle, cache=cache)
    assert plan.feasible

    def answer(strokes):
        return np.array([plan.desired]), np.ones((1, 2, 1))

    def model_layer(strokes):
        return cache.state(np.asarray(strokes, float))

    class SlabSays:
        """Blocked where the layer's plan goes, clear once the plan was made again."""

        def __call__(self, strokes):
            return np.array([plan.desired]), np.ones((1, 2, 1))

        def clearance(self, strokes, point, corridor):
            return -0.4 if not asked else 0.8

    asked = []

    def replan(t, target_at, layer_at=None):
        asked.append(layer_at)
        return plan_target(tissue, tissue.scene, tissue.scene.targets[t], cfg.needle, cache=cache,
                           target_at=target_at, layer_at=layer_at)

    surrogate = SimpleNamespace(kind="surrogate", transmission=None, scene_map=lambda: answer,
                                layer_map=lambda: model_layer)
    said = _Said()
    again = _planned(cfg, [plan], surrogate, SlabSays(), said, replan)[0]
    assert asked == [model_layer]
    assert again.feasible and again.planned_with == "surrogate"
    assert any("planned again on the surrogate model's target positions and obstacles" in line for line in said.lines)

    def no_plan(t, target_at, layer_at=None):
        asked.append(layer_at)
        return replace(plan, feasible=False, reason="no entry side/direction clears the obstacles")

    asked.clear()
    refused = _planned(cfg, [plan], surrogate, SlabSays(), _Said(), no_plan)[0]
    assert not refused.feasible and asked == [model_layer]
    assert "blocked (clearance -0.40 mm)" in refused.reason and "no entry side" in refused.reason


def test_planner_on_a_given_layer_is_the_planner_on_the_tissue_when_they_agree():
    """`layer_at` carries the obstacles and the skin: handed the tissue's own states, the plan is the same."""
    from scissor_cli.config import load_config
    from scissor_cli.planning.needle_plan import plan_target
    from scissor_cli.planning.states import StateCache

    cfg = load_config(ROOT / "configs" / "paper_push.yaml")
    _, mesh, tissue = build_model(cfg, mesh_scale=2.0)
    cache = StateCache(tissue)
    seen = []

    def layer_at(strokes):
        seen.append(np.asarray(strokes, float))
        return cache.state(strokes)

    for target in tissue.scene.targets:
        own = plan_target(tissue, tissue.scene, target, cfg.needle, cache=cache)
        given = plan_target(tissue, tissue.scene, target, cfg.needle, cache=cache, layer_at=layer_at)
        assert (own.feasible, own.side) == (given.feasible, given.side)
        np.testing.assert_array_equal(own.strokes, given.strokes)
        np.testing.assert_array_equal(own.desired, given.desired)
    assert seen


def test_reserved_limits_move_each_limit_towards_rest_and_never_past_it():
    from scissor_cli.experiments.model_planning import reserved_limits

    lo, hi = reserved_limits(np.array([-15.0, 0.0, 2.0]), np.array([15.0, 10.0, 8.0]), 0.1)
    np.testing.assert_allclose(lo, [-13.5, 0.0, 2.0])
    np.testing.assert_allclose(hi, [13.5, 9.0, 7.2])
    lo, hi = reserved_limits(np.array([-15.0]), np.array([15.0]), 0.0)
    np.testing.assert_array_equal([lo[0], hi[0]], [-15.0, 15.0])


def test_a_plan_in_the_stroke_reserve_is_refused_before_any_trial():
    """A 3-D-aware model whose desired point needs 14.5 of the cup's 15 mm: accepted without a reserve (the plan
    asks 14.5 mm), refused with the default 10 % (13.5 mm may be used), saying so; a layer plan is never refused
    for it (the paper's method uses the whole range)."""
    from types import SimpleNamespace

    from scissor_cli.config import load_config
    from scissor_cli.planning.needle_plan import plan_target
    from scissor_cli.planning.states import StateCache

    cfg = load_config(ROOT / "configs" / "paper_push.yaml")
    assert cfg.cups[0].stroke_mm[1] == 15.0 and cfg.controller.stroke_reserve == 0.1
    _, mesh, tissue = build_model(cfg, mesh_scale=2.0)
    scene = tissue.scene
    rests = np.array([t.rest for t in scene.targets])
    rate = np.array([0.0, -0.5])  # mm of target per mm of stroke: the target moves along y only

    def answer(strokes):
        s = float(np.asarray(strokes, float)[0])
        return rests + rate * s, np.repeat(rate[None, :, None], len(rests), axis=0)

    model = SimpleNamespace(kind="surrogate", transmission=None, scene_map=lambda: answer, layer_map=lambda: None)
    cache = StateCache(tissue)
    plans = [plan_target(tissue, scene, t, cfg.needle, cache=cache) for t in scene.targets[:1]]
    assert plans[0].feasible
    far = [replace(plans[0], desired=rests[0] + rate * 14.5)]
    with_cfg = cfg.model_copy(update={"targets": cfg.targets[:1]})
    none = with_cfg.model_copy(update={"controller": cfg.controller.model_copy(update={"stroke_reserve": 0.0})})
    accepted = _planned(none, far, model, None, _Said())[0]
    assert accepted.feasible
    np.testing.assert_allclose(accepted.strokes, [14.5], atol=0.05)
    refused = _planned(with_cfg, far, model, None, _Said())[0]
    assert not refused.feasible
    assert "stroke reserve of 0.1" in refused.reason
    assert refused.strokes[0] <= 13.5 + 1e-9
    layer = SimpleNamespace(kind="layer", transmission=None, scene_map=lambda: answer, layer_map=lambda: None)
    assert _planned(with_cfg, far, layer, None, _Said())[0].feasible


def test_slab_corridor_at_rest_is_the_layers_and_moves_with_the_slab(scene):
    """At rest the slab's layer is the 2-D mesh: the same clearance as the layer's; pushed, the slab's own."""
    from scissor_cli.control import Corridor, corridor_at

    cfg, tissue, slab, rests = scene
    answer = slab_map(slab, tissue, rests)
    corridor = Corridor("left", np.array([1.0, 0.0]), 1.6)
    point = rests[0]
    layer_clearance = corridor_at(tissue, tissue.rest, point, corridor)[1]
    assert answer.clearance(np.zeros(1), point, corridor) == pytest.approx(layer_clearance, abs=1e-6)
    moved = answer.clearance(np.array([6.0]), point, corridor)
    assert np.isfinite(moved) and moved != pytest.approx(layer_clearance, abs=1e-3)


def test_a_plan_whose_corridor_the_slab_blocks_is_refused_for_a_3d_model_and_reported_for_the_layer():
    from types import SimpleNamespace

    from scissor_cli.config import load_config
    from scissor_cli.planning.needle_plan import plan_target
    from scissor_cli.planning.states import StateCache

    cfg = load_config(ROOT / "configs" / "paper_push.yaml")
    cfg = cfg.model_copy(update={"targets": cfg.targets[:1]})
    _, mesh, tissue = build_model(cfg, mesh_scale=2.0)
    plan = plan_target(tissue, tissue.scene, tissue.scene.targets[0], cfg.needle, cache=StateCache(tissue))
    assert plan.feasible and plan.side

    class Blocking:
        """A slab answer that reaches every point where the plan does, with the corridor blocked there."""

        def __init__(self, clearance):
            self.clearance_mm, self.asked = clearance, []

        def __call__(self, strokes):
            return np.array([plan.desired]), np.ones((1, 2, 1))

        def clearance(self, strokes, point, corridor):
            self.asked.append((np.asarray(strokes, float), np.asarray(point, float), corridor.side))
            return self.clearance_mm

    def answer(strokes):
        return np.array([plan.desired]), np.ones((1, 2, 1))

    surrogate = SimpleNamespace(kind="surrogate", transmission=None, scene_map=lambda: answer, layer_map=lambda: None)
    layer = SimpleNamespace(kind="layer", transmission=None, scene_map=lambda: answer, layer_map=lambda: None)
    blocked = Blocking(-0.4)
    refused = _planned(cfg, [plan], surrogate, blocked, _Said())[0]
    assert not refused.feasible and "blocked (clearance -0.40 mm)" in refused.reason
    assert blocked.asked and blocked.asked[0][2] == plan.side
    np.testing.assert_array_equal(blocked.asked[0][1], plan.desired)
    said = _Said()
    kept = _planned(cfg, [plan], layer, Blocking(-0.4), said)[0]
    assert kept.feasible and any("blocked" in line for line in said.lines)
    assert _planned(cfg, [plan], surrogate, Blocking(0.8), _Said())[0].feasible


def test_each_plan_records_its_models_error_against_the_slab_at_the_strokes_it_asks_for():
    """/plan/<t> model_error_mm: the distance between where the controller's model and the nominal slab put the
    target at the model's strokes; a slab that moves it half as far is off by half the model's move; the slab
    model is the slab (0)."""
    from types import SimpleNamespace

    from scissor_cli.config import load_config
    from scissor_cli.planning.needle_plan import plan_target
    from scissor_cli.planning.states import StateCache

    cfg = load_config(ROOT / "configs" / "paper_push.yaml")
    cfg = cfg.model_copy(update={"targets": cfg.targets[:1]})
    _, mesh, tissue = build_model(cfg, mesh_scale=2.0)
    plan = plan_target(tissue, tissue.scene, tissue.scene.targets[0], cfg.needle, cache=StateCache(tissue))
    assert plan.feasible and plan.manipulated
    rest = np.asarray(tissue.scene.targets[0].rest, float)
    move = (np.asarray(plan.desired) - rest) / plan.strokes[0]  # the layer's move per mm of stroke, along its path

    def along(gain):
        return lambda strokes: (np.array([rest + gain * move * strokes[0]]), (gain * move)[None, :, None])

    slab_half = along(0.5)
    slab_answer = type("HalfSlab", (), {"__call__": lambda self, s: slab_half(s),
                                        "clearance": lambda self, s, p, c: 1.0})()
    layer = SimpleNamespace(kind="layer", transmission=None, scene_map=lambda: along(1.0), layer_map=lambda: None)
    judged = _planned(cfg, [plan], layer, slab_answer, _Said())[0]
    np.testing.assert_allclose(judged.model_strokes, plan.strokes)
    expected = 0.5 * np.linalg.norm(move * plan.strokes[0])
    assert judged.model_error_mm == pytest.approx(expected, rel=1e-9) and expected > 1.0
    reference = SimpleNamespace(kind="slab", transmission=None, scene_map=lambda: slab_half, layer_map=lambda: None)
    assert _planned(cfg, [plan], reference, slab_answer, _Said())[0].model_error_mm == 0.0
    assert _planned(cfg, [plan], layer, None, _Said())[0].model_error_mm is None  # no slab: not asked


def test_stored_model_paths_read_back_and_draw_every_model_against_the_slab(tmp_path):
    """/controller_model/paths round-trips; report's controller_models.png holds one line per model kind (a
    +Broyden run shares its model's line) beside the slab's points and the layer's line."""
    from scissor_cli.layer3d.tissue_models import ModelPaths
    from scissor_cli.output.controller_model import read_paths, report_models_figure, write_paths

    grid, dots = np.linspace(-15, 15, 7), np.linspace(-15, 15, 4)

    def paths(kind, gain):
        def line(s, g):  # (G, T=2, 2)
            return np.stack([np.stack([g * s, -g * s], axis=1)] * 2, axis=1)

        return ModelPaths(kind, ["cup"], ["T1", "T2"], [grid], [line(grid, gain)], [line(grid, 0.3)], [dots],
                          [line(dots, 0.15)], np.zeros((2, 2)))

    runs = []
    for name, kind, gain in (("a", "surrogate", 0.15), ("b", "surrogate", 0.15), ("c", "calibrated", 0.17)):
        with h5py.File(tmp_path / f"{name}.h5", "w") as f:
            f.create_group("controller_model")
            write_paths(f, paths(kind, gain))
        runs.append((f"scene ({name})", tmp_path / f"{name}.h5"))
    with h5py.File(tmp_path / "a.h5") as f:
        back = read_paths(f)
    want = paths("surrogate", 0.15)
    assert back.kind == "surrogate" and back.cup_names == ["cup"] and back.target_names == ["T1", "T2"]
    for field in ("strokes", "model", "layer", "slab_strokes", "slab"):
        np.testing.assert_array_equal(getattr(back, field)[0], getattr(want, field)[0])
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f.create_group("controller_model")
    with h5py.File(tmp_path / "plain.h5") as f:
        assert read_paths(f) is None
    files = report_models_figure(runs + [("scene (plain)", tmp_path / "plain.h5")], tmp_path / "rep")
    assert [p.name for p in files] == ["controller_models.png"] and files[0].stat().st_size > 0
    assert report_models_figure([("scene (plain)", tmp_path / "plain.h5")], tmp_path / "rep2") == []
