"""ADMM-PD (scissor_cli.solvers.admm) against the Newton reference, and its safeguards."""

from __future__ import annotations

import numpy as np
import pytest

from scissor_cli.config import load_config
from scissor_cli.experiments.build import scene_of
from scissor_cli.mechanics.tissue import build_tissue
from scissor_cli.mesh.mesh import mesh_for_config
from scissor_cli.solvers.admm import local
from scissor_cli.solvers.admm import solver as admm_solver
from scissor_cli.solvers.admm.euler import implicit_euler
from scissor_cli.solvers.admm.solver import AdmmSolver, AdmmState
from scissor_cli.solvers.admm.weights import curvature_boost, rest_weights
from scissor_cli.solvers.anderson import Anderson
from scissor_cli.solvers.common import Inertia, SolverError
from scissor_cli.solvers.newton import solve_newton

CONFIG = "configs/example.yaml"


@pytest.fixture(scope="module")
def scene_cfg():
    import os

    cfg = load_config(os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), CONFIG))
    return scene_of(cfg), cfg


@pytest.fixture(scope="module")
def tissue(scene_cfg):
    """The example scene as shipped (2597 elements)."""
    scene, cfg = scene_cfg
    return build_tissue(scene, mesh_for_config(scene, cfg.tissue.mesh))


@pytest.fixture(scope="module")
def coarse(scene_cfg):
    """The example scene on a coarser mesh (~1000 elements) for the slower checks."""
    scene, cfg = scene_cfg
    return build_tissue(scene, mesh_for_config(scene, cfg.tissue.mesh, scale=2.0))


@pytest.fixture(scope="module")
def newton_refs(tissue):
    return {s: solve_newton(tissue, np.array([s]), tol=1e-10) for s in (10.0, -8.0)}


@pytest.fixture(scope="module")
def plain_solver(tissue):
    return AdmmSolver(tissue)


def rel_error(x, ref, rest):
    return float(np.linalg.norm(x - ref) / np.linalg.norm(ref - rest))


def assert_sane(tissue, result):
    assert np.all(np.isfinite(result.x))
    assert tissue.jacobians(result.x).min() > 0
    assert result.solver == "admm"
    assert len(result.history) == result.iterations


# ---------------------------------------------------------------- local pieces


def test_cholesky4_solves_and_flags_indefinite():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((50, 4, 4))
    H = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(4)
    H[:5] -= 20 * np.eye(4)  # indefinite
    b = rng.standard_normal((50, 4))
    L, ok = local.cholesky4(H)
    assert not ok[:5].any() and ok[5:].all()
    d = local.cholesky4_solve(L, b)
    np.testing.assert_allclose(d[5:], np.linalg.solve(H[5:], b[5:][..., None])[..., 0], rtol=1e-9, atol=1e-9)


def test_local_newton_converges_and_keeps_det_positive(tissue):
    """The vectorised local step solves min Ψ(z) + k/2‖z − v‖², also with inverted targets v."""
    M = tissue.mesh.n_elements
    rng = np.random.default_rng(1)
    v = np.tile(local.IDENTITY, (M, 1)) + 0.3 * rng.standard_normal((M, 4))
    v[:50, :2] *= -1  # flip the first row: det v < 0
    assert (local.det4(v[:50]) < 0).sum() > 30
    k = rest_weights(tissue.params)
    cache = local.evaluate_local(np.tile(local.IDENTITY, (M, 1)), tissue.params)
    scale = np.linalg.norm(v - local.IDENTITY, axis=1).max()
    for _ in range(30):
        cache, g = local.local_newton(cache, v, k, tissue.params)
        assert local.det4(cache.z).min() > 0
        if (np.linalg.norm(g, axis=1) / k).max() < 1e-10 * scale:
            break
    assert (np.linalg.norm(g, axis=1) / k).max() < 1e-10 * scale
    # a minimum, not just a stationary point: the PSD test of the local Hessian
    H = cache.C + k[:, None, None] * np.eye(4)
    assert np.linalg.eigvalsh(H)[:, 0].min() > -1e-8 * k.max()


def test_curvature_boost_needs_persistence_caps_and_only_grows():
    """Boost k_e to 3·(−λ_min) after two consecutive indefinite local Hessians, at most 16·k0, never down."""
    C = np.tile(10.0 * np.eye(4), (4, 1, 1))
    C[1] -= 30.0 * np.eye(4)  # λ_min = −20: C + k/2 I indefinite for k = 10
    C[2] -= 1000.0 * np.eye(4)  # λ_min = −990: the cap decides
    k = np.full(4, 10.0)
    flagged = np.zeros(4, int)
    assert curvature_boost(C, k, k, flagged) is None  # flagged once: no boost yet
    assert flagged.tolist() == [0, 1, 1, 0]
    elems, k_new = curvature_boost(C, k, k, flagged)
    assert elems.tolist() == [1, 2]
    np.testing.assert_allclose(k_new, [3 * 20.0, 16 * 10.0])
    assert flagged.tolist() == [0, 0, 0, 0]
    # already above what a boost would give: element 1 is now convex enough, element 2 stays at its larger k
    flagged[:] = [0, 1, 1, 0]
    assert curvature_boost(C, np.array([10.0, 100.0, 200.0, 10.0]), k, flagged) is None
    assert flagged.tolist() == [0, 0, 2, 0]


def test_anderson_accelerates_a_linear_fixed_point():
    rng = np.random.default_rng(2)
    n = 40
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A = Q @ np.diag(np.linspace(0.0, 0.97, n)) @ Q.T
    b = rng.standard_normal(n)
    s_star = np.linalg.solve(np.eye(n) - A, b)

    def iterations(memory):
        aa = Anderson(memory)
        s = np.zeros(n)
        for it in range(1, 2000):
            g = A @ s + b
            if np.linalg.norm(g - s) < 1e-10:
                return it, s
            s = aa.step(g, g - s) if memory else g
        return it, s

    n_plain, s_plain = iterations(0)
    n_aa, s_aa = iterations(8)
    np.testing.assert_allclose(s_aa, s_star, atol=1e-8)
    assert n_aa < n_plain / 5


# ---------------------------------------------------------------- acceptance: Newton


@pytest.mark.parametrize("stroke", [10.0, -8.0], ids=["push10", "pull8"])
def test_default_tolerance_matches_newton(tissue, newton_refs, plain_solver, stroke):
    """At its default tol (1e-4) plain ADMM is within 1e-3 (relative L2 displacement) of Newton at 1e-10."""
    result, state = plain_solver.solve(np.array([stroke]))
    assert result.converged, result.message
    assert_sane(tissue, result)
    assert rel_error(result.x, newton_refs[stroke].x, tissue.rest) < 1e-3
    assert result.history[-1] <= 1e-4
    assert result.residual < 1e-3  # the common force residual, comparable with Newton's
    assert result.iterations < 200
    assert local.det4(state.z).min() > 0


def test_anderson_matches_newton_and_needs_fewer_iterations(tissue, newton_refs, plain_solver):
    plain, _ = plain_solver.solve(np.array([10.0]))
    fast = AdmmSolver(tissue, anderson_memory=5)
    result, _ = fast.solve(np.array([10.0]))
    assert result.converged, result.message
    assert_sane(tissue, result)
    assert rel_error(result.x, newton_refs[10.0].x, tissue.rest) < 1e-3
    assert result.iterations < plain.iterations


def test_anderson_safeguard_rejects_bad_extrapolation(coarse, monkeypatch):
    """Extrapolations that make the combined residual grow are rejected: plain ADMM steps, right answer."""
    ref = solve_newton(coarse, np.array([10.0]))
    rng = np.random.default_rng(3)

    class Wild(Anderson):
        def step(self, g, f):
            good = super().step(g, f)
            return good + 0.05 * rng.standard_normal(good.shape)  # garbage on top of every extrapolation

    monkeypatch.setattr(admm_solver, "Anderson", Wild)
    rejected = []
    solver = AdmmSolver(coarse, anderson_memory=5)
    result, _ = solver.solve(np.array([10.0]), callback=lambda it, info: rejected.append(info.get("rejected", False)))
    assert result.converged, result.message
    assert rel_error(result.x, ref.x, coarse.rest) < 1e-3
    assert sum(rejected) >= 3


def test_weights_only_grow_and_fixed_weights_factor_once(coarse):
    solver = AdmmSolver(coarse, adaptive=False)
    solver.solve(np.array([-8.0]))
    solver.solve(np.array([-7.5]))
    assert solver.n_factorizations == 1
    adaptive = AdmmSolver(coarse)
    k0 = adaptive.k.copy()
    adaptive.solve(np.array([10.0]))
    assert np.all(adaptive.k >= k0)
    n = adaptive.n_factorizations
    _, state = adaptive.solve(np.array([10.0]))
    assert adaptive.n_factorizations <= n + 2  # learned weights: (almost) no refactoring on a re-solve
    assert np.all(state.k == adaptive.k)


def test_state_is_rescaled_to_new_weights(coarse):
    """k·u (the element stress) survives a change of weights between solves."""
    solver = AdmmSolver(coarse)
    result, state = solver.solve(np.array([6.0]))
    other = AdmmSolver(coarse, weight_scale=2.0)
    again, _ = other.solve(np.array([6.0]), state)
    assert again.converged and again.iterations <= 5


# ---------------------------------------------------------------- warm start


def test_warm_start_needs_far_fewer_iterations(tissue, newton_refs):
    """A control-loop re-solve: a small stroke correction from the previous state vs from scratch."""
    solver = AdmmSolver(tissue)
    _, state = solver.solve(np.array([10.0]))
    for ds, factor in ((0.05, 3.0), (0.3, 1.8)):
        stroke = np.array([10.0 + ds])
        cold, _ = solver.solve(stroke)  # same (learned) weights: a fair comparison
        warm, _ = solver.solve(stroke, state)
        assert cold.converged and warm.converged
        assert warm.iterations <= cold.iterations / factor, (ds, warm.iterations, cold.iterations)
    ref = solve_newton(tissue, stroke, x0=newton_refs[10.0].x, strokes0=np.array([10.0]))
    assert rel_error(warm.x, ref.x, tissue.rest) < 1e-3


# ---------------------------------------------------------------- dynamics


def test_implicit_euler_step_matches_newton(coarse):
    dt = 2e-3  # s: M/Δt² is comparable to the stiffness here, so inertia really matters
    solver = AdmmSolver(coarse, dt_s=dt)
    x0 = coarse.rest
    v0 = np.zeros_like(x0)
    x_tilde = (x0 + dt * v0).ravel()
    inertia = Inertia(dt, x_tilde, coarse.mass)
    stroke = np.array([3.0])
    ref = solve_newton(coarse, stroke, inertia=inertia)
    static = solve_newton(coarse, stroke)
    assert rel_error(ref.x, static.x, coarse.rest) > 0.05  # the step is not the static answer
    result, _ = solver.solve(stroke, solver.state_from_positions(x0), inertia=inertia)
    assert result.converged, result.message
    assert_sane(coarse, result)
    assert rel_error(result.x, ref.x, coarse.rest) < 1e-3


def test_implicit_euler_helper_steps_positions_and_velocities(coarse):
    dt = 2e-3
    solver = AdmmSolver(coarse, dt_s=dt)
    path = np.array([[1.0], [2.0], [2.5]])
    steps = implicit_euler(coarse, solver, path, dt, coarse.rest, np.zeros_like(coarse.rest))
    assert len(steps) == 3
    x, v = coarse.rest, np.zeros_like(coarse.rest)  # the Newton trajectory
    x_admm = coarse.rest
    for n, step in enumerate(steps):
        inertia = Inertia(dt, (x + dt * v).ravel(), coarse.mass)
        ref = solve_newton(coarse, path[n], x0=x if n else None, strokes0=path[n - 1] if n else None, inertia=inertia)
        assert rel_error(step.x, ref.x, coarse.rest) < 2e-3  # errors of 1e-4 per step accumulate a little
        np.testing.assert_allclose(step.v, (step.x - x_admm) / dt)
        assert step.t_s == pytest.approx((n + 1) * dt)
        x, v = ref.x, (ref.x - x) / dt
        x_admm = step.x
    with pytest.raises(ValueError):
        solver.solve(np.array([1.0]))  # built for dynamics: inertia is required
    with pytest.raises(ValueError):
        AdmmSolver(coarse).solve(np.array([1.0]), inertia=Inertia(dt, coarse.rest.ravel(), coarse.mass))


# ---------------------------------------------------------------- hard cases


def test_push20_converges_or_raises_never_nan(tissue):
    solver = AdmmSolver(tissue, anderson_memory=5)
    try:
        result, state = solver.solve(np.array([20.0]))
    except SolverError as exc:
        assert str(exc)
        assert exc.result is not None
        return
    assert np.all(np.isfinite(result.x)) and np.isfinite(result.residual)
    assert tissue.jacobians(result.x).min() > 0
    if result.converged:
        assert result.residual < 1e-3  # an equilibrium (not necessarily Newton's: this push has several)
    else:
        assert "not converged" in result.message


def test_inverted_start_converges_or_raises(coarse):
    """Warm starts with inverted elements: never NaN; solved (or a clear SolverError)."""
    ref = solve_newton(coarse, np.array([10.0]))
    solver = AdmmSolver(coarse)
    # (a) x inverted: one vertex reflected across the opposite edge → a cold start, and the message says so
    x_bad = coarse.rest.copy()
    tri = coarse.mesh.triangles[coarse.ops.area.argmax()]
    x_bad[tri[0]] = x_bad[tri[1]] + x_bad[tri[2]] - x_bad[tri[0]]
    assert coarse.jacobians(x_bad).min() < 0
    state = solver.state_from_positions(x_bad)
    assert local.det4(state.z).min() > 0  # z is always valid
    # (b) x fine but z inverted (first rows flipped) → those z replaced by their nearest rotations
    _, good = solver.solve(np.array([9.0]))
    z_flipped = good.z.copy()
    z_flipped[:20, :2] *= -1
    for start, words in ((state, "cold start"), (AdmmState(good.x, z_flipped, good.u, good.k), "inverted z")):
        try:
            result, _ = solver.solve(np.array([10.0]), start)
        except SolverError as exc:
            assert str(exc) and exc.result is not None
            continue
        assert result.converged, result.message
        assert words in result.message
        assert_sane(coarse, result)
        assert rel_error(result.x, ref.x, coarse.rest) < 1e-3


def test_not_converged_returns_flag_or_raises_with_reason(tissue):
    solver = AdmmSolver(tissue)
    try:
        result, _ = solver.solve(np.array([20.0]), max_iter=3)
    except SolverError as exc:
        assert "inverted" in str(exc) and exc.result is not None and exc.result.iterations == 3
        return
    assert not result.converged and "not converged" in result.message
    assert np.all(np.isfinite(result.x))


def test_rest_is_solved_at_once(coarse):
    """Zero strokes: "relative" has a floor, so the rest state converges instead of chasing round-off."""
    result, _ = AdmmSolver(coarse).solve(np.zeros(1))
    assert result.converged and result.iterations <= 2
    assert np.abs(result.x - coarse.rest).max() < 1e-9


def test_non_finite_raises(coarse):
    solver = AdmmSolver(coarse)
    state = solver.state_from_positions(coarse.rest)
    state.u[0, 0] = np.nan
    with pytest.raises(SolverError):
        solver.solve(np.array([1.0]), state)


# ---------------------------------------------------------------- speed


def test_warm_resolves_do_not_refactor(tissue):
    """Once the weights have settled, re-solving nearby strokes reuses the global factorisation.

    (The cost per element and iteration is a benchmark: benchmarks/bench_forward.py.)
    """
    solver = AdmmSolver(tissue)
    _, state = solver.solve(np.array([10.0]))
    # settles the weights: no refactoring below (on the default scene's mesh since T1 moved to (50, 27.5),
    # the first move to 10.5 still boosts a few elements once)
    solver.solve(np.array([10.5]), state, tol=1e-14, max_iter=20)
    n_fact = solver.n_factorizations
    for _ in range(3):
        result, _ = solver.solve(np.array([10.5]), state, tol=1e-14, max_iter=20)
        assert result.iterations == 20
    assert solver.n_factorizations == n_fact
