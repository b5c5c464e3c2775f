"""A controller that knows a coarser body than the one it moves (docs/model.md §19, "Control and trials"): the model's
body at `controller.mesh_scale` (set by `tissue.accuracy_mm`), the trials' truth the configured mesh."""

from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import pytest
import yaml

from scissor_cli.config.loading import parse_config
from scissor_cli.control.loop import loop_parts
from scissor_cli.control.plant import TruthPerturbation
from scissor_cli.experiments.body_trials import BODY_MODEL_TOL, BODY_TRUTH_TOL, BodyTrialContext, BodyTruth
from scissor_cli.experiments.build import body_model
from scissor_cli.experiments.trial_types import TargetTask
from scissor_cli.mechanics.tissue import BoundaryError
from scissor_cli.mesh.probe import apply_probe, target_positions
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.tracking import TrackedEquilibrium

from helpers import simulate_here, write_scene
from test_body_loop import SCENE, _true_miss
from test_cli import run_cli


def _scene(**controller) -> dict:
    return dict(SCENE, controller={"model": "body", **controller})


def test_the_truth_is_the_configured_mesh_and_the_model_is_coarser():
    cfg = parse_config(yaml.safe_dump(_scene(mesh_scale=2.0)), "<test>")
    _, model_mesh, model = body_model(cfg, scale=cfg.controller.mesh_scale)
    truth = BodyTruth(cfg, model)
    _, fine_mesh, _ = body_model(cfg)
    assert truth.tissue.mesh.n_elements == fine_mesh.n_elements > model_mesh.n_elements
    assert truth.centroids.shape == (fine_mesh.n_elements, 3)
    rest = np.asarray(SCENE["targets"][0]["position_mm"], float)
    tissue, view = truth.factory(rest)(TruthPerturbation())
    assert tissue is truth.tissue  # nothing drawn: the fine body itself
    assert np.allclose(view.target(tissue.rest), rest, atol=1e-9)  # the lesion probed in the fine tetrahedra
    same = parse_config(yaml.safe_dump(_scene()), "<test>")
    _, _, same_model = body_model(same)
    assert BodyTruth(same, same_model).factory(rest) is None  # mesh_scale 1: the truth is the model's mesh


def test_a_trials_truth_settles_to_the_body_truth_tolerance_and_the_model_to_its_own():
    """BODY_TRUTH_TOL reaches a trial's perturbed truth, BODY_MODEL_TOL the controller's model (the body), and a
    truth that is the model itself keeps the model's; a nominal manipulation's loop has the same. Along a few
    moves the lesion settled at BODY_TRUTH_TOL stays within 1e-4 mm of its 1e-10 settle, far below a camera's
    noise (σ ≈ 0.15 mm)."""
    ctx = BodyTrialContext(yaml.safe_dump(dict(_scene(), trials={"count": 1, "profile": "prosthesis"})))
    target = ctx.cfg.targets[0]
    task = TargetTask(0, target.name, np.asarray(target.position_mm, float), np.asarray(target.desired_mm, float),
                      np.zeros(ctx.tissue.n_cups), "", np.array([-1.0, 0.0, 0.0]))
    run, _ = ctx.target_run(task, 0)
    plant, controller, _ = loop_parts(ctx.tissue, task.rest, run)
    assert plant.tissue is not ctx.tissue and plant.eq.tol == BODY_TRUTH_TOL
    assert controller.eq.tol == run.tol == BODY_MODEL_TOL
    shared, _, _ = loop_parts(ctx.tissue, task.rest, dataclasses.replace(run, truth=TruthPerturbation()))
    assert shared.tissue is ctx.tissue and shared.eq.tol == run.tol
    nominal = ctx.nominal_run(task)  # the same loop without the trial's errors: the same tolerances
    assert (nominal.tol, nominal.truth_tol) == (run.tol, run.truth_tol) == (BODY_MODEL_TOL, BODY_TRUTH_TOL)
    probe = plant.tissue.probe(task.rest[None])
    loose, tight = TrackedEquilibrium(plant.tissue, BODY_TRUTH_TOL), TrackedEquilibrium(plant.tissue, 1e-10)
    for strokes in ([1.5, 0.0], [3.0, -1.0], [3.5, -2.0]):
        loose.move_to(np.array(strokes), tangent=False)
        tight.move_to(np.array(strokes), tangent=False)
        assert np.linalg.norm(target_positions(probe, loose.x) - target_positions(probe, tight.x)) <= 1e-4


def test_the_trials_model_keeps_a_factor_that_preconditions_and_its_J_stays_the_tight_models():
    """Settled to BODY_MODEL_TOL the controller's model goes on with its factorisation while it preconditions well,
    where a model settled to 1e-10 factors at every move's start; along a loop's approach (moves of 0.4 mm) its J
    stays within 1e-4 of the tight model's, relative: far below what a camera read to 0.15 mm can steer by."""
    ctx = BodyTrialContext(yaml.safe_dump(dict(_scene(), trials={"count": 1})))
    tissue = ctx.tissue
    probe = tissue.probe(np.asarray(SCENE["targets"][0]["position_mm"], float)[None])
    loose, tight = TrackedEquilibrium(tissue, BODY_MODEL_TOL), TrackedEquilibrium(tissue, 1e-10)
    for k in range(1, 7):
        strokes = np.array([0.4 * k, -0.1 * k])
        loose.move_to(strokes, tangent=True)
        tight.move_to(strokes, tangent=True)
        J_loose, J_tight = apply_probe(probe, loose.response, 3), apply_probe(probe, tight.response, 3)
        assert np.linalg.norm(J_loose - J_tight) <= 1e-4 * np.linalg.norm(J_tight)
    assert loose.stats["refactors"] < tight.stats["refactors"]
    assert tight.stats["refactors"] >= tight.stats["moves"] - 1  # (the first from rest may reuse rest's)


def test_loops_table_under_the_needle_is_made_on_the_controllers_coarser_body(tmp_path, monkeypatch):
    """With `controller.mesh_scale` 2 the table `loop` steers with under the needle (docs/model.md §20) is the
    controller's own coarse body's; a table of the lesion, not of nodes, it steers the needle in the finer truth."""
    import scissor_cli.experiments.body_insertion as body_insertion

    made = []
    tabulate = body_insertion.tabulate

    def spy(tissue, *args, **kwargs):
        made.append(tissue.mesh.n_nodes)
        return tabulate(tissue, *args, **kwargs)

    monkeypatch.setattr(body_insertion, "tabulate", spy)
    data = dict(_scene(mesh_scale=2.0), targets=SCENE["targets"][:1], trials={"count": 0},
                insertion={"step_mm": 1.0, "capture_radius_mm": 2.5, "strategies": ["loop"]})
    with h5py.File(simulate_here(tmp_path, data) / "results.h5", "r") as f:
        coarse = len(f["mesh/nodes"])  # the run's body: the controller's
        loop = f["insertion/T1/loop"]
        assert made == [coarse] and len(f["insertion/T1/loop/needle_model/depth_mm"]) > 5
        assert loop.attrs["completed"] and loop["displacement"].shape[1] > coarse  # in the finer truth
        assert loop.attrs["miss_mm"] < 0.5


@pytest.mark.slow  # (its parts: the coarser model's trials above; Broyden on a body's camera rows and in a loop,
# tests/test_broyden.py)
def test_a_coarser_model_with_broyden_still_puts_every_lesion_on_the_finer_truths_needle(tmp_path):
    """Broyden's correction of the coarse model's J (3 × cups) from the two cameras' moves (its rows under one
    camera: tests/test_broyden.py)."""
    data = _scene(mesh_scale=2.0, jacobian_update="broyden")
    with h5py.File(simulate_here(tmp_path, data) / "results.h5", "r") as f:
        for t in ("T1", "T2"):
            direction = f[f"plan/{t}"].attrs["direction"]
            assert f[f"trials/{t}/manipulation_miss_mm"][0] <= 0.1
            assert _true_miss(f[f"trials/{t}/final_error"][()], direction).max() <= 0.1
        assert f["/"].attrs["status"] == "complete"


def test_accuracy_picks_the_models_body_and_element_and_leaves_the_truth_configured(tmp_path):
    """With `element: auto` the pick names the element too (docs/model.md §21): the run computes on it, records
    it in the config it keeps (so trials and --resume rebuild it), and measured its candidates against nodal."""
    mesh = dict(SCENE["tissue"]["mesh"], element="auto")
    data = dict(_scene(), tissue=dict(SCENE["tissue"], accuracy_mm=0.5, mesh=mesh), trials={"count": 0})
    data["forward"] = [{"name": "push", "strokes": {"side": 4.0}}]
    simulate_here(tmp_path, data)
    with h5py.File(tmp_path / "run" / "results.h5", "r") as f:
        resolution = f["mesh_resolution"]
        pick = int(resolution.attrs["pick"])
        errors = resolution["error_mm"][()]
        assert errors[pick] <= 0.5 and resolution.attrs["chosen_scale"] == resolution["scale"][pick]
        assert len(f["mesh/tetrahedra"]) == resolution["n_tetrahedra"][pick]  # the run's body is the pick
        element = resolution.attrs["element"]
        assert element == resolution["element"][pick].decode() and f["mesh"].attrs["element"] == element
        assert resolution.attrs["reference_element"] == "nodal" and errors[0] == 0.0
        skipped = [v.decode() for v in resolution["skipped"][()]]
        assert len(skipped) == len(errors) and all(errors[k] == -1.0 for k, why in enumerate(skipped) if why)
        recorded = yaml.safe_load(f.attrs["config_yaml"])
    assert recorded["tissue"]["accuracy_mm"] is None and recorded["tissue"]["mesh"]["scale"] == 1.0
    assert recorded["tissue"]["mesh"]["element"] == element
    assert recorded["controller"]["mesh_scale"] == resolution_scale(tmp_path)


@pytest.mark.parametrize("error", [BoundaryError, SolverError])
def test_a_coarser_candidate_that_cannot_be_built_or_solved_is_skipped_with_its_reason(monkeypatch, error):
    """A coarse candidate may not grip a cup (its nearest skin node stands for more than the cup) or may not
    solve: the ladder goes on to the next finer one and records why (docs/model.md §21)."""
    from scissor_cli.experiments import body_resolution

    solve = body_resolution._solve

    def failing(cfg, scale, element, cache):
        if scale == body_resolution.SCALES[1]:
            raise error("cup 'side' cannot be gripped here")
        return solve(cfg, scale, element, cache)

    monkeypatch.setattr(body_resolution, "_solve", failing)
    data = dict(_scene(), tissue=dict(SCENE["tissue"], accuracy_mm=10.0), trials={"count": 0})
    data["forward"] = [{"name": "push", "strokes": {"side": 4.0}}]
    choice = body_resolution.choose_body_scale(parse_config(yaml.safe_dump(data), "<test>"))
    coarsest, next_finer = choice.candidates[1:3]
    assert coarsest.scale == body_resolution.SCALES[1] and "cup 'side'" in coarsest.skipped and not coarsest.solved
    assert choice.pick == 2 and next_finer.solved and not next_finer.skipped and next_finer.error_mm <= 10.0


def resolution_scale(tmp_path) -> float:
    with h5py.File(tmp_path / "run" / "results.h5", "r") as f:
        return float(f["mesh_resolution"].attrs["chosen_scale"])


def test_a_mesh_file_pins_the_models_body_too(tmp_path):
    mesh = tmp_path / "body.npz"
    _, m, _ = body_model(parse_config(yaml.safe_dump(_scene()), "<test>"))
    np.savez(mesh, nodes=m.nodes, tetrahedra=m.tetrahedra, region=m.region, region_names=np.array(m.region_names))
    data = dict(_scene(mesh_scale=2.0), tissue=dict(SCENE["tissue"], mesh={"file": str(mesh)}))
    r = run_cli("validate", write_scene(tmp_path, data))
    assert r.returncode == 2 and "controller.mesh_scale" in r.stderr


def test_a_surrogate_learned_from_the_body_puts_every_lesion_on_its_needle_and_is_cached(tmp_path, monkeypatch):
    """controller.model surrogate: §15's interpolant of the body's lesions over the strokes, checked against
    held-out body solves; the loop on it ends on the (configured mesh's) needle line. Its samples are cached beside
    the run, read back without a solve, under a key that another model's body does not share."""
    from scissor_cli.experiments import body_surrogate
    from scissor_cli.experiments.run_cache import cache_dir

    data = _scene(model="surrogate", surrogate={"samples": 16})
    run = simulate_here(tmp_path, data)
    with h5py.File(run / "results.h5", "r") as f:
        attrs = f["trials"].attrs
        assert attrs["controller_model"] == "surrogate" and 0.0 <= attrs["surrogate_error_mm"] < 0.05
        error = float(attrs["surrogate_error_mm"])
        for t in ("T1", "T2"):
            direction = f[f"plan/{t}"].attrs["direction"]
            assert f[f"trials/{t}/manipulation_miss_mm"][0] <= 0.1
            assert _true_miss(f[f"trials/{t}/final_error"][()], direction).max() <= 0.1
    cache = cache_dir(run)
    assert len(list(cache.glob("controller-surrogate-*.npz"))) == 1
    cfg = parse_config(yaml.safe_dump(data), "<test>")
    _, _, tissue = body_model(cfg)

    def no_solves(*args, **kwargs):
        raise AssertionError("the cached samples were fitted again")

    monkeypatch.setattr(body_surrogate, "train", no_solves)
    cached = body_surrogate.body_surrogate_data(cfg, tissue, cache)
    assert cached.kind == "surrogate" and cached.validation_error_mm == error
    assert cached.samples.targets.shape[0] == 16
    other = cfg.model_copy(update={"controller": cfg.controller.model_copy(update={"mesh_scale": 2.0})})
    assert body_surrogate._key(other) != body_surrogate._key(cfg)  # another model's body: another file
    with pytest.raises(AssertionError, match="fitted again"):
        body_surrogate.body_surrogate_data(other, body_model(other, scale=2.0)[2], cache)


def test_a_surrogate_with_too_few_samples_for_its_cups_exits_2(tmp_path):
    r = run_cli("validate", write_scene(tmp_path, _scene(model="surrogate", surrogate={"samples": 8})))
    assert r.returncode == 2 and "controller.surrogate.samples" in r.stderr
