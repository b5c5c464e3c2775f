"""The stroke step of docs/model.md §6 (control.allocation): the miss, the bounds, the speed limit,
the uncorrectable part, spare cups and zero cups."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from scissor_cli.control.allocation import REGULARISATION, along_mm, miss_mm, projector, stroke_step

X = np.array([1.0, 0.0])  # a needle along +x: the miss is the y error


def test_projector_and_parts():
    P = projector(X)
    np.testing.assert_allclose(P, [[0.0, 0.0], [0.0, 1.0]])
    assert projector(X, "position") is None and projector(np.full(2, np.nan)) is None
    assert miss_mm([0.3, -0.4], X) == pytest.approx(0.4) and along_mm([0.3, -0.4], X) == pytest.approx(0.3)
    assert miss_mm([0.3, -0.4], None) == pytest.approx(0.5) and along_mm([0.3, -0.4], None) == 0.0
    with pytest.raises(ValueError):
        projector(X, "across")


def test_one_cup_cancels_the_miss_exactly_and_leaves_the_along_part():
    J = np.array([[0.5], [-0.25]])
    e = np.array([0.7, 0.5])  # y_d - y
    step = stroke_step(J, e, [0.0], [-15.0], [15.0], None, X)
    assert step.ds[0] == pytest.approx(-2.0, rel=1e-4)  # -0.25 * -2 = 0.5: the miss
    np.testing.assert_allclose(step.uncorrectable, 0.0, atol=1e-5)
    assert step.along_mm == pytest.approx(0.7) and not step.at_limit and not step.limited
    # the paper's full error: one cup cannot remove both components
    pos = stroke_step(J, e, [0.0], [-15.0], [15.0], None, X, "position")
    assert np.linalg.norm(pos.uncorrectable) > 0.5 and pos.along_mm == 0.0


def test_speed_and_stroke_limits_bound_the_step():
    J = np.array([[0.0], [0.5]])
    e = np.array([0.0, 4.0])  # needs 8 mm
    step = stroke_step(J, e, [0.0], [-15.0], [15.0], [0.5], X)
    assert step.limited and step.ds[0] == pytest.approx(0.5)
    np.testing.assert_allclose(step.uncorrectable, 0.0, atol=1e-4)  # reachable within the stroke limits (λ bias)
    near = stroke_step(J, e, [13.0], [-15.0], [15.0], [0.5], X)
    assert near.at_limit and near.ds[0] == pytest.approx(0.5)
    assert np.linalg.norm(near.uncorrectable) == pytest.approx(4.0 - 0.5 * 2.0, rel=1e-4)  # 2 mm of room left
    at = stroke_step(J, e, [15.0], [-15.0], [15.0], [0.5], X)
    assert at.ds[0] == 0.0 and at.at_limit


def test_two_cups_bounded_least_squares_matches_lsq_linear_and_uses_the_spare_cup():
    from scipy.optimize import lsq_linear

    J = np.array([[0.4, -0.3], [0.6, 0.2]])
    e = np.array([1.0, 2.0])
    step = stroke_step(J, e, [0.0, 0.0], [-15.0, -15.0], [15.0, 15.0], [0.5, 0.5], X)
    # the miss row plus the along row with weight mu: with two cups both are reachable
    full = stroke_step(J, e, [0.0, 0.0], [-15.0, -15.0], [15.0, 15.0], None, X)
    np.testing.assert_allclose(J @ full.ds, e, atol=1e-4)  # miss and along part both cancelled
    assert np.all(np.abs(step.ds) <= 0.5 + 1e-12) and step.limited
    # the bounded problem is what lsq_linear solves
    from scissor_cli.control.allocation import ALONG_WEIGHT
    A = np.vstack([[0.0, 0.0], J[1], np.sqrt(ALONG_WEIGHT) * J[0], np.sqrt(REGULARISATION) * np.eye(2)])
    b = np.array([0.0, e[1], np.sqrt(ALONG_WEIGHT) * e[0], 0.0, 0.0])
    ref = lsq_linear(A, b, bounds=([-0.5, -0.5], [0.5, 0.5])).x
    np.testing.assert_allclose(step.ds, ref, atol=1e-6)


def test_zero_cups_have_nothing_to_correct():
    step = stroke_step(np.zeros((2, 0)), np.array([0.2, 0.3]), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), X)
    assert step.ds.shape == (0,)
    np.testing.assert_allclose(step.uncorrectable, [0.0, 0.3])
    assert step.along_mm == pytest.approx(0.2)


def test_zero_cup_loop_stops_at_once_and_says_so():
    from dataclasses import replace

    from scissor_cli import control as ct
    from scissor_cli.config import load_config
    from scissor_cli.experiments.build import build_model
    from scissor_cli.mechanics.tissue import build_tissue

    from helpers import ROOT

    cfg = load_config(ROOT / "configs" / "example.yaml")
    scene, _, tissue = build_model(cfg, mesh_scale=2.0)
    bare = build_tissue(replace(scene, cups=()), tissue.mesh)
    target = scene.targets[1]
    r = ct.run_target(bare, target.rest, target.desired, cfg.controller, ct.TargetRun(direction=X, target="T2"))
    assert r.iterations == 0 and "no cups: nothing to correct" in r.message
    assert r.miss_mm == pytest.approx(abs(target.desired[1] - target.rest[1]))


@settings(max_examples=300, deadline=None)
@example(C=4, rows=4, lam=REGULARISATION, seed=7770)  # BVLS stopped at scipy's default max_iter short of the optimum
@given(
    C=st.integers(1, 4),
    rows=st.integers(1, 4),
    lam=st.sampled_from([REGULARISATION, 1e-3, 1.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_bounded_step_matches_lsq_linear_and_its_optimality_conditions(C, rows, lam, seed):
    """The closed-form / face-wise bounded solve against scipy's BVLS on random boxes around 0 (C ≤ 3 by faces,
    C = 4 by BVLS itself), and the KKT conditions of the box problem checked directly."""
    from scipy.optimize import lsq_linear

    from scissor_cli.control.allocation import FACES_MAX_CUPS, _bounded

    rng = np.random.default_rng(seed)
    A = rng.normal(size=(rows, C)) * rng.choice([0.05, 1.0, 3.0], size=C)
    b = rng.normal(size=rows) * rng.choice([0.1, 1.0, 10.0])
    lb = -rng.uniform(0.0, 1.0, C) * rng.choice([0.0, 1.0], C, p=[0.1, 0.9])
    ub = rng.uniform(0.0, 1.0, C) * rng.choice([0.0, 1.0], C, p=[0.1, 0.9])
    x, inside = _bounded(A, b, lb, ub, lam)
    assert x.shape == (C,) and np.all(np.isfinite(x))
    slack = 0.0 if C <= FACES_MAX_CUPS else 1e-12  # the faces land on the bounds exactly, BVLS within round-off
    assert np.all(x >= lb - slack) and np.all(x <= ub + slack)
    Aa, ba = np.vstack([A, np.sqrt(lam) * np.eye(C)]), np.concatenate([b, np.zeros(C)])

    def f(y):
        return float(np.sum((Aa @ y - ba) ** 2))

    fixed = lb == ub
    if np.all(fixed):
        ref = lb.copy()
    else:
        ref = np.array(lb, float)
        sub = lsq_linear(Aa[:, ~fixed], ba - Aa[:, fixed] @ lb[fixed], bounds=(lb[~fixed], ub[~fixed]),
                         method="bvls", tol=1e-14, max_iter=1000)  # (its default, C iterations, can stop short)
        ref[~fixed] = sub.x
    scale = 1.0 + f(np.zeros(C))
    assert f(x) <= f(ref) + 1e-12 * scale
    # strictly convex (λ > 0): the minimiser is unique, and ‖x − x*‖² ≤ (f(x) − f*)/λ_min
    np.testing.assert_allclose(x, ref, atol=1e-7 * np.sqrt(scale / lam))
    # KKT: zero gradient on free strokes, pointing out of the box on strokes at a bound
    g = 2 * Aa.T @ (Aa @ x - ba)
    tol = 1e-9 * scale
    at_lb, at_ub = (x <= lb + 1e-12) & ~fixed, (x >= ub - 1e-12) & ~fixed
    interior = ~(at_lb | at_ub | fixed)
    assert np.all(np.abs(g[interior]) <= tol)
    assert np.all(g[at_lb] >= -tol) and np.all(g[at_ub] <= tol)
    if inside:
        assert np.all(np.abs(g) <= tol)
