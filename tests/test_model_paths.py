"""The controller's model solved once per command sequence in a process (`control.plant.ModelPaths`): a loop that
takes over states an earlier loop solved answers exactly as if it had solved them (docs/model.md §19, "Trials")."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from scissor_cli import control
from scissor_cli.config.loading import parse_config
from scissor_cli.experiments.body_trials import BODY_MODEL_TOL, body_sensor_model
from scissor_cli.experiments.build import body_model
from scissor_cli.experiments.profiles import error_model
from scissor_cli.solvers.tracking import TrackedEquilibrium

from test_body_loop import SCENE


@pytest.fixture(scope="module")
def body():
    cfg = parse_config(yaml.safe_dump(dict(SCENE, trials={"count": 0})), "<test>")
    return cfg, body_model(cfg)[2]


@pytest.mark.parametrize("tol", [1e-10, BODY_MODEL_TOL])  # factoring at each move's start, and keeping a factor
def test_a_restored_tracker_moves_on_bit_for_bit(body, tol):
    _, tissue = body
    a = TrackedEquilibrium(tissue, tol)
    a.move_to(np.array([1.0, -0.5]), tangent=True)
    state = a.snapshot()
    for s in ([1.6, -0.2], [2.1, 0.4]):
        a.move_to(np.array(s), tangent=True)
    b = TrackedEquilibrium(tissue, tol)
    b.move_to(np.array([-2.0, 1.0]), tangent=True)  # its factorisation somewhere else entirely
    b.restore(state)
    for s in ([1.6, -0.2], [2.1, 0.4]):
        b.move_to(np.array(s), tangent=True)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.response, b.response)
    a.move_to(np.array([2.3, 0.5]), tangent=False)
    with pytest.raises(ValueError, match="tangent"):
        a.snapshot()  # without the exact tangent there is nothing to go on from exactly


@pytest.mark.parametrize("tol", [pytest.param(1e-10, marks=pytest.mark.slow), BODY_MODEL_TOL])
# (1e-10, a factor at each move's start: the restored tracker above moves on bit for bit there; runs settle their
# model to BODY_MODEL_TOL, the loops' default here)
def test_loops_sharing_the_models_paths_answer_as_loops_without(body, tol):
    cfg, tissue = body
    rest = tissue.scene.targets[0].rest
    desired = np.array(SCENE["targets"][0]["desired_mm"], float)
    centroids = tissue.mesh.nodes[tissue.mesh.tetrahedra].mean(axis=1)
    truths = [control.TruthPerturbation(E_scale=1.0 + 0.2 * np.sin(k + centroids[:, 0] / 9.0),
                                        fiber_offset_rad=0.1 * k) for k in range(2)]
    sensor = body_sensor_model(cfg, error_model(cfg.trials)).nominal(desired)  # the two cameras, exact
    paths = control.ModelPaths()
    shared, alone = [], []
    for truth in truths:
        for store, results in ((paths, shared), (None, alone)):
            run = control.TargetRun(truth=truth, sensor=sensor, direction=np.array([-1.0, 0.0, 0.0]),
                                    model_paths=store, tol=tol)
            results.append(control.run_target(tissue, rest, desired, cfg.controller, run))
    assert paths.hits > 0
    assert paths.get(()) is not None  # the rest state, where every loop's J starts, is shared too
    for a, b in zip(shared, alone):
        assert a.iterations == b.iterations > 1
        assert np.array_equal(a.final_error, b.final_error)
        assert np.array_equal(a.history_table()[1], b.history_table()[1], equal_nan=True)


def test_loops_on_released_factorisations_answer_as_loops_on_new_ones(body, monkeypatch):
    """A loop hands its trackers' factorisations back when it ends (`linear.release_free`): the next loop's new
    slots refactor them instead of analysing the pattern anew, and answer bit for bit as on new ones."""
    from scissor_cli.solvers import linear

    cfg, tissue = body
    rest = tissue.scene.targets[0].rest
    desired = np.array(SCENE["targets"][0]["desired_mm"], float)
    sensor = body_sensor_model(cfg, error_model(cfg.trials)).nominal(desired)
    taken = []
    released = linear._released
    monkeypatch.setattr(linear, "_released", lambda *a: taken.append(released(*a)) or taken[-1])

    def loop(k: int):
        truth = control.TruthPerturbation(fiber_offset_rad=0.1 * k)
        run = control.TargetRun(truth=truth, sensor=sensor, direction=np.array([-1.0, 0.0, 0.0]), tol=BODY_MODEL_TOL)
        return control.run_target(tissue, rest, desired, cfg.controller, run)

    tissue.factor_cache.pop("released", None)
    loop(0)
    assert tissue.factor_cache["released"]  # both trackers' slots, kept on the cache the truth shares
    taken.clear()
    on_released = loop(1)
    assert any(f is not None for f in taken) and tissue.factor_cache["released"]
    monkeypatch.setattr(linear, "REUSE_RELEASED", False)
    tissue.factor_cache.pop("released")
    on_new = loop(1)
    assert "released" not in tissue.factor_cache
    assert on_released.iterations == on_new.iterations > 1
    assert np.array_equal(on_released.final_error, on_new.final_error)
    assert np.array_equal(on_released.history_table()[1], on_new.history_table()[1], equal_nan=True)
