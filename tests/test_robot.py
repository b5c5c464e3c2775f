"""Puncture-module kinematics: closed form vs the matrix product, IK round trip, registration."""

import types

import numpy as np
import pytest

from scissor_cli.robot.chain import RobotModel
from scissor_cli.robot.ik import ik, ik_batch, linear_interval
from scissor_cli.robot.registration import direction_layer_to_base, layer_to_base, plan_to_joints
from scissor_cli.robot.workspace import reachable_coverage, sample_joints

PAPER = RobotModel.paper()


def product_of_six(q):
    """The six modified-DH matrices of docs/model.md §11 multiplied one by one (no shared code with robot.fk)."""
    d1, d2, d3, t4, d5 = q
    rows = [(0, 0, 0, d1), (-np.pi / 2, 60, -np.pi / 2, d2), (-np.pi / 2, 0, -np.pi / 2, d3),
            (-np.pi / 2, 70, t4, 0), (-np.pi / 2, 0, -np.pi / 2, d5), (0, 80, 0, 80)]
    T = np.eye(4)
    for alpha, a, theta, d in rows:
        ca, sa, ct, st = np.cos(alpha), np.sin(alpha), np.cos(theta), np.sin(theta)
        T = T @ np.array([[ct, -st, 0, a], [st * ca, ct * ca, -sa, -d * sa], [st * sa, ct * sa, ca, d * ca],
                          [0, 0, 0, 1]])
    return T


def test_closed_form_equals_product_of_six_matrices():
    q = sample_joints(PAPER, 2000, seed=3)
    tip, axis = PAPER.tip_and_axis(q)
    for k in range(0, 2000, 50):
        T = product_of_six(q[k])
        assert np.abs(tip[k] - T[:3, 3]).max() < 1e-9
        assert np.abs(axis[k] - T[:3, 2]).max() < 1e-12
    d1, d2, d3, t4, d5 = q.T  # docs/model.md §11 as printed
    L = d5 + 80
    assert np.allclose(tip, np.column_stack([60 + d3 - L * np.cos(t4), 70 + d2 - L * np.sin(t4), d1 + 80]), atol=1e-9)
    assert np.allclose(axis, np.column_stack([-np.cos(t4), -np.sin(t4), np.zeros_like(t4)]), atol=1e-12)


def test_batched_fk_matches_single():
    q = sample_joints(PAPER, 5, seed=1)
    assert np.allclose(PAPER.fk(q)[2], PAPER.fk(q[2])[0])


def test_ik_round_trip_10000():
    q = sample_joints(PAPER, 10_000, seed=7)
    # IK prefers the shortest insertion: with d5 at its smallest feasible value the answer is unique
    tip, axis = PAPER.tip_and_axis(q)
    sol = ik_batch(tip, axis, PAPER)
    assert sol.reachable.all()
    tip2, axis2 = PAPER.tip_and_axis(sol.q)
    assert np.abs(tip2 - tip).max() < 1e-9 and np.abs(axis2 - axis).max() < 1e-12
    assert np.all(sol.q[:, 4] <= q[:, 4] + 1e-9)  # never a longer insertion than the input's
    q_min = q.copy()
    q_min[:, 4] = 0.0
    tip0, axis0 = PAPER.tip_and_axis(q_min)
    sol0 = ik_batch(tip0, axis0, PAPER)
    assert np.abs(sol0.q - q_min).max() < 1e-9  # at d5 = 0 the joint values come back exactly


def test_unreachable_names_the_joint_and_amount():
    r = ik(np.array([500.0, 100.0, 250.0]), np.array([-1.0, 0.0, 0.0]), PAPER)
    assert not r.reachable and "d3" in r.violations and r.violations["d3"] > 0 and "d3" in r.reason
    r = ik(np.array([100.0, 100.0, 250.0]), np.array([1.0, 0.0, 0.0]), PAPER)  # needs θ4 = 180°
    assert not r.reachable and "theta4" in r.violations and abs(abs(r.violations["theta4"]) - 45.0) < 1e-6
    with pytest.raises(ValueError):
        ik(np.array([100.0, 100.0, 250.0]), np.array([0.0, 0.6, 0.8]), PAPER)  # not horizontal


def test_registration_and_plan_to_joints():
    origin, yaw = np.array([120.0, 200.0, 250.0]), np.pi
    p = layer_to_base(np.array([[10.0, 5.0]]), origin, yaw)
    assert np.allclose(p, [[110.0, 195.0, 250.0]])
    assert np.allclose(direction_layer_to_base(np.array([[1.0, 0.0]]), yaw), [[-1.0, 0.0, 0.0]])
    r = plan_to_joints(PAPER, np.array([50.0, 40.0]), np.array([1.0, 0.0]), origin, yaw)
    assert r.reachable
    tip, axis = PAPER.tip_and_axis(r.q)
    assert np.allclose(tip[0], [70.0, 160.0, 250.0]) and np.allclose(axis[0], [-1.0, 0.0, 0.0])


def test_custom_dh_table_from_config():
    table = [(0, 0, 0, 0, "prismatic", (0, 300)), (-90, 50, -90, 0, "prismatic", (0, 100)),
             (-90, 0, -90, 0, "prismatic", (0, 100)), (-90, 70, 0, 0, "revolute", (-90, 90)),
             (-90, 0, -90, 0, "prismatic", (0, 50)), (0, 80, 0, 80, "fixed", None)]
    rows = [types.SimpleNamespace(alpha_deg=a, a_mm=length, theta_deg=t, d_mm=d, joint=j, limits=lim)
            for a, length, t, d, j, lim in table]
    robot = RobotModel.from_config(types.SimpleNamespace(dh=rows))
    assert robot.has_closed_form and robot.n_joints == 5
    q = sample_joints(robot, 200, seed=2)
    tip, _ = robot.tip_and_axis(q)
    assert np.allclose(tip, robot.fk(q)[:, :3, 3], atol=1e-9)
    assert np.all(q[:, 3] <= np.pi / 2 + 1e-12)
    # a table the closed form does not describe falls back to the product
    odd = RobotModel.from_config(types.SimpleNamespace(dh=rows[:4]))
    assert not odd.has_closed_form and odd.closed_form is None
    q = sample_joints(odd, 10, seed=0)
    assert np.allclose(odd.tip_and_axis(q)[0], odd.fk(q)[:, :3, 3])
    # IK and the sample-free coverage are closed-form only, and say so
    assert robot.require_closed_form() is robot.closed_form
    with pytest.raises(NotImplementedError, match="closed-form"):
        odd.require_closed_form()
    with pytest.raises(NotImplementedError):
        ik([100.0, 100.0, 100.0], [1.0, 0.0, 0.0], odd)
    with pytest.raises(NotImplementedError):
        reachable_coverage(odd, [0, 0, 0], [10, 10, 10])


def test_linear_interval():
    b = np.array([0.0, 0.0, 5.0, 15.0, 5.0])
    k = np.array([2.0, -2.0, 0.0, 0.0, 1.0])
    t_lo, t_hi = linear_interval(b, k, 1.0, 10.0)  # 1 <= b + k t <= 10
    np.testing.assert_allclose(t_lo, [0.5, -5.0, -np.inf, np.inf, -4.0])
    np.testing.assert_allclose(t_hi, [5.0, -0.5, np.inf, -np.inf, 5.0])
    # every t inside is feasible, and the ends are on the limits
    for i in (0, 1, 4):
        t = np.linspace(t_lo[i], t_hi[i], 7)
        assert np.all((b[i] + k[i] * t >= 1.0 - 1e-12) & (b[i] + k[i] * t <= 10.0 + 1e-12))


def test_ik_returns_the_shortest_insertion_of_the_one_parameter_family():
    # For a fixed tip and axis the solutions are q + t·(0, sin θ4, cos θ4, 0, 1) inside the limits;
    # IK must return the member with the smallest d5, so one millimetre less must break a limit.
    q = sample_joints(PAPER, 10_000, seed=11)
    tip, axis = PAPER.tip_and_axis(q)
    sol = ik_batch(tip, axis, PAPER)
    t = sol.q[:, 4] - q[:, 4]
    step = np.column_stack([np.zeros_like(t), np.sin(q[:, 3]), np.cos(q[:, 3]), np.zeros_like(t), np.ones_like(t)])
    assert np.abs(sol.q - (q + t[:, None] * step)).max() < 1e-9
    shorter = sol.q - 1e-3 * step
    assert not PAPER.within_limits(shorter, tol=0.0).any()


def test_ik_exact_when_a_limit_pins_the_insertion():
    # d3 on its lower limit with cos θ4 > 0 (or d2 on its upper limit with sin θ4 < 0): no shorter
    # insertion exists, so the full joint vector is unique and must come back.
    rng = np.random.default_rng(4)
    q = sample_joints(PAPER, 2000, seed=5)
    q[:, 3] = np.deg2rad(rng.uniform(-89.0, 45.0, len(q)))
    q[:1000, 2] = 0.0
    q[1000:, 3] = np.deg2rad(rng.uniform(-135.0, -1.0, 1000))
    q[1000:, 1] = 200.0
    sol = ik_batch(*PAPER.tip_and_axis(q), PAPER)
    assert sol.reachable.all() and np.abs(sol.q - q).max() < 1e-9
