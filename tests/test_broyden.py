"""Broyden's online Jacobian correction (control/broyden.py, controller.jacobian_update: broyden)."""

import numpy as np
import pytest

from scissor_cli import control as ct
from scissor_cli.control.actuator import Actuator
from scissor_cli.control.broyden import MAX_CHANGE, MIN_MOVE_MM, NOISE_FACTOR, BroydenCorrection, broyden_update
from scissor_cli.control.loop import run_loop
from scissor_cli.mesh.probe import probe_targets
from tests.test_control import scene_setup


def test_converges_to_the_true_jacobian_of_a_linear_plant():
    """Exciting both strokes: the error of J falls to round-off; the secant holds after every update."""
    rng = np.random.default_rng(0)
    A = np.array([[0.2, -0.6], [0.9, 0.3]])  # the plant's true J
    J = np.array([[0.5, -0.1], [0.4, 0.8]])  # a wrong model
    errors = []
    for _ in range(40):
        ds = rng.standard_normal(2)
        J = broyden_update(J, ds, A @ ds)
        np.testing.assert_allclose(J @ ds, A @ ds, atol=1e-12)
        errors.append(np.linalg.norm(J - A))
    assert errors[-1] < 1e-8 * errors[0]


def test_learns_only_the_excited_direction():
    """Moves along the first stroke only: J's first column becomes the plant's, the second stays the model's."""
    A = np.array([[0.2, -0.6], [0.9, 0.3]])
    J0 = np.array([[0.5, -0.1], [0.4, 0.8]])
    J = J0
    for a in (1.0, -0.5, 2.0):
        ds = np.array([a, 0.0])
        J = broyden_update(J, ds, A @ ds)
    np.testing.assert_allclose(J[:, 0], A[:, 0], atol=1e-12)
    np.testing.assert_array_equal(J[:, 1], J0[:, 1])


def test_on_a_body_the_rows_a_camera_sees_are_learnt_and_the_unseen_depth_row_is_kept():
    """J (3, C) with one camera above: the measured z is NaN; the x, y rows converge to the plant's, z stays."""
    rng = np.random.default_rng(1)
    A = np.array([[0.2, -0.6], [0.9, 0.3], [0.4, 0.1]])
    J0 = np.array([[0.5, -0.1], [0.4, 0.8], [-0.3, 0.2]])
    J = J0
    for _ in range(30):
        ds = rng.standard_normal(2)
        dy = A @ ds
        dy[2] = np.nan
        J = broyden_update(J, ds, dy)
        assert np.all(np.isfinite(J))
    np.testing.assert_allclose(J[:2], A[:2], atol=1e-8)
    np.testing.assert_array_equal(J[2], J0[2])
    c = BroydenCorrection()
    c.observe(J0, np.zeros(2), np.array([0.0, 0.0, np.nan]))
    c.observe(J0, np.array([1.0, 0.0]), np.array([0.2, 0.9, np.nan]))  # the move A's first column makes in x, y
    assert c.updates == 1 and np.all(np.isfinite(c.D)) and not np.any(c.D[2])


def test_guard_waits_for_motion_above_noise_and_bounds_the_correction():
    J_model = np.array([[0.1], [0.5]])
    c = BroydenCorrection(noise_mm=0.1)
    assert c.threshold_mm == pytest.approx(NOISE_FACTOR * 0.1) and c.threshold_mm > MIN_MOVE_MM
    c.observe(J_model, [0.0], [0.0, 0.0])
    c.observe(J_model, [0.5], [0.025, 0.125])  # 0.25 mm predicted, 0.125 seen: below 0.4 mm, wait
    assert (c.updates, c.skipped) == (0, 1) and c.D is None
    c.observe(J_model, [1.0], [0.05, 0.25])  # half the model's motion over both moves: the secant of both
    assert c.updates == 1
    np.testing.assert_allclose(c.jacobian(J_model), [[0.05], [0.25]], atol=1e-12)
    c.observe(J_model, [2.0], [5.0, -40.0])  # an absurd observation (a glitch): bounded
    assert np.linalg.norm(c.D) <= MAX_CHANGE * np.linalg.norm(J_model) * (1 + 1e-12)


def test_a_secant_cannot_cancel_the_models_response_or_turn_it_far():
    """A secant that says the target moves sideways (noise, a glitch): the corrected J keeps at least half the
    model's component along its own direction and turns by at most 30 degrees."""
    J_model = np.array([[0.1], [0.5]])
    c = BroydenCorrection(noise_mm=0.1)
    c.observe(J_model, [0.0], [0.0, 0.0])
    c.observe(J_model, [2.0], [1.0, 0.0])  # moved 1 mm in x and nothing in y
    J = c.jacobian(J_model)[:, 0]
    u = J_model[:, 0] / np.linalg.norm(J_model)
    assert J @ u >= (1 - MAX_CHANGE) * np.linalg.norm(J_model) - 1e-12
    assert np.degrees(np.arccos(J @ u / np.linalg.norm(J))) <= 30.0 + 1e-9


GAIN = 0.5


class HalfActuator(Actuator):
    """Drives reach half of what is commanded: the plant moves half as far as the model expects,
    as the slab does against the layer (docs/model.md §15)."""

    def apply(self, command):
        return super().apply(GAIN * np.asarray(command, float))


def _half_plant_loop(update: str):
    cfg, tissue, plans = scene_setup("example")
    target, plan = tissue.scene.targets[1], plans[1]  # T2: its plan (6.1 mm) doubled stays within the 15 mm stroke
    base = Actuator.from_scene(tissue.scene)
    fields = {f: getattr(base, f) for f in base.__dataclass_fields__}
    fields["speed_mm_per_s"] = np.full_like(base.speed_mm_per_s, 100.0)  # steps set by J, not by the drives' speed
    actuator = HalfActuator(**fields)
    probe = probe_targets(tissue.mesh, target.rest[None])
    plant = ct.Plant(tissue, actuator, probe)
    controller = ct.Controller(tissue, probe, base.lo, base.hi)
    controller_cfg = cfg.controller.model_copy(update={"jacobian_update": update, "max_iterations": 200})
    return run_loop(plant, controller, plan.desired, controller_cfg, target=target.name, direction=plan.direction)


def test_loop_learns_a_plant_that_gives_half():
    """Both reach the tolerance; with Broyden the learnt gain (half the model's) takes fewer iterations."""
    without, learnt = _half_plant_loop("none"), _half_plant_loop("broyden")
    assert without.stop_reason == "tolerance" and learnt.stop_reason == "tolerance"
    assert learnt.iterations < without.iterations
