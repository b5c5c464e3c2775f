"""Newton, the exact reference: accuracy, convergence rate, mesh convergence, hard cases."""

import numpy as np
import pytest

from scissor_cli.config import load_config
from scissor_cli.experiments.simulate import build_model
from scissor_cli.mesh.mesh import interpolate, locate
from scissor_cli.solvers import newton
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.newton import solve_newton

from helpers import EXAMPLE, rates_above_roundoff


@pytest.fixture(scope="module")
def example():
    return load_config(EXAMPLE)


@pytest.mark.parametrize("stroke", [10.0, -8.0])
def test_example_forward_cases_converge_quadratically(example, stroke):
    _, _, tissue = build_model(example)
    r = solve_newton(tissue, np.array([stroke]))
    assert r.converged and r.residual <= 1e-8
    assert len(r.history) <= 10
    # quadratic ending, read above round-off: the last steps square the residual (up to a constant)
    rates = rates_above_roundoff(r.history)
    assert rates[-1] < 1e-3 and rates[-2] < 1e-1, r.history
    assert tissue.jacobians(r.x).min() > 0


def test_linear_model_is_one_linear_solve(example):
    _, _, tissue = build_model(example, model="linear", mesh_scale=2.0)
    r = solve_newton(tissue, np.array([5.0]))
    assert r.converged and r.iterations <= 1
    # and it equals the solution of K_ff u_f = -K_fd u_d at rest
    from scissor_cli.solvers.linear import Factorization

    x_d = tissue.apply_strokes(tissue.rest, np.array([5.0]))
    u = (x_d - tissue.rest).ravel()
    rhs = -tissue.stiffness_times(tissue.rest, u)[tissue.free_dofs]
    u[tissue.free_dofs] = Factorization(tissue.stiffness_free(tissue.rest)).solve(rhs)
    assert np.allclose(r.x.ravel() - tissue.rest.ravel(), u, atol=1e-9)


def test_target_displacement_converges_under_refinement(example):
    """Refining h shrinks the targets' error against a much finer reference solve.

    Why these levels: every scale builds a new unstructured mesh, so each
    level's answer carries a mesh-to-mesh scatter of a few hundredths of a
    mm (one refinement decision more or less moves a node near a target;
    CPUs differ there). Successive differences between neighbouring levels
    (0.16, 0.07, 0.07 mm) are as small as that scatter at the fine end, so
    they cannot show an order. Errors against a reference 3x finer than the
    finest level tested (scale 0.35, ~14k triangles) are well above it:
    0.28, 0.12, 0.08 mm at scales 4, 2, 1, an order of about 0.9 over the
    range (P1 triangles at ν = 0.45 with the singular stress at the cup's
    edges: pre-asymptotic). The asserts leave room for the scatter.
    """
    positions = {}
    for scale in (4.0, 2.0, 1.0, 0.35):
        _, mesh, tissue = build_model(example, mesh_scale=scale)
        r = solve_newton(tissue, np.array([10.0]))
        tri, bary = locate(mesh, np.array([t.rest for t in tissue.scene.targets]))
        positions[scale] = interpolate(r.x, mesh.triangles, tri, bary)
    error = [np.linalg.norm(positions[s] - positions[0.35]) for s in (4.0, 2.0, 1.0)]
    assert error[0] > 1.5 * error[1], error
    order = np.log2(error[0] / error[2]) / 2
    assert order > 0.4, (error, order)


def scene_with(example, **material):
    return example.model_copy(update={"material": example.material.model_copy(update=material)})


@pytest.mark.parametrize(
    "name,update,stroke",
    [
        ("nearly incompressible", {"nu": 0.499}, 10.0),
        ("strong fibers", {"eta_kPa": 200.0}, 10.0),
        ("20 mm push", {}, 20.0),
    ],
)
def test_hard_cases_converge_or_fail_clearly(example, name, update, stroke):
    cfg = scene_with(example, **update)
    _, _, tissue = build_model(cfg, mesh_scale=2.0)
    try:
        r = solve_newton(tissue, np.array([stroke]))
    except SolverError as exc:  # allowed, but must say why and carry no NaN
        assert str(exc)
        assert exc.result is None or np.all(np.isfinite(exc.result.x))
        pytest.fail(f"{name}: {exc}")  # on these small meshes we expect convergence
    assert r.converged and np.all(np.isfinite(r.x)) and tissue.jacobians(r.x).min() > 0


def test_load_substeps_are_counted_and_settled_loosely_to_the_same_equilibrium(example, monkeypatch):
    """A push the tangent predictor cannot take in one step goes in load substeps (SolveResult.substeps, as
    its message says); settling them tighter than SUBSTEP_TOL gives the same equilibrium."""
    _, _, tissue = build_model(example, mesh_scale=2.0)
    r = solve_newton(tissue, np.array([20.0]))
    assert r.converged and r.substeps >= 1 and f"{r.substeps} load substeps" in r.message
    monkeypatch.setattr(newton, "SUBSTEP_TOL", 1e-8)
    tight = solve_newton(tissue, np.array([20.0]))
    assert tight.converged and np.max(np.abs(tight.x - r.x)) < 1e-6
    assert solve_newton(tissue, np.array([5.0])).substeps == 0


def test_inverted_start_guess_is_replaced(example):
    _, _, tissue = build_model(example, mesh_scale=2.0)
    bad = tissue.rest.copy()
    bad[:, 1] *= -1  # mirror: every element inverted
    r = solve_newton(tissue, np.array([5.0]), x0=bad, strokes0=np.array([0.0]))
    assert r.converged and "inverted" in r.message
    ref = solve_newton(tissue, np.array([5.0]))
    assert np.allclose(r.x, ref.x, atol=1e-8)


def test_warm_start_from_equilibrium(example):
    _, _, tissue = build_model(example, mesh_scale=2.0)
    a = solve_newton(tissue, np.array([6.0]))
    b = solve_newton(tissue, np.array([6.5]), x0=a.x, strokes0=np.array([6.0]))
    c = solve_newton(tissue, np.array([6.5]))
    assert b.iterations <= 3 and np.allclose(b.x, c.x, atol=1e-8)


def test_unconverged_newton_says_so(example):
    _, _, tissue = build_model(example, mesh_scale=2.0)
    with pytest.raises(SolverError, match="not converged in 1 iterations"):
        solve_newton(tissue, np.array([10.0]), max_iter=1)


def test_chord_option_reaches_the_same_solution_and_ends_quadratic(example):
    """newton_iterations(chord=True) reuses factorisations only far from the solution (its docstring)."""
    from scissor_cli.solvers.newton import newton_iterations, tangent_predictor

    _, _, tissue = build_model(example, mesh_scale=2.0)
    ref = solve_newton(tissue, np.array([5.0]))
    start = tangent_predictor(tissue, tissue.rest, np.array([5.0]))
    r = newton_iterations(tissue, start, chord=True)
    assert r.converged and np.abs(r.x - ref.x).max() < 1e-8
    assert rates_above_roundoff(r.history)[-1] < 1e-3, r.history  # the last step is a full Newton step


def test_2d_steps_precondition_with_a_factor_that_modelled_the_last_step_well(example, monkeypatch):
    """After a full step that shrank the residual by KRYLOV_CONTRACTION, a 2-D step first tries
    conjugate gradients on that step's factor: the same equilibrium, fewer factorisations,
    and a direct solve again once the factor's measured rate cannot reach the forcing term."""
    import scissor_cli.solvers.newton as newton

    _, _, tissue = build_model(example, mesh_scale=0.75)
    default = newton.KRYLOV_CONTRACTION
    cg = solve_newton(tissue, np.array([5.0]))
    factor = tissue.factor_cache["free"]
    cg_iterations = factor.cg_iterations
    monkeypatch.setattr(newton, "KRYLOV_CONTRACTION", 0.0)  # never: every step factors (the old path)
    direct = solve_newton(tissue, np.array([5.0]))
    assert cg.converged and direct.converged and cg.residual <= 1e-10
    assert np.abs(cg.x - direct.x).max() < 1e-8
    assert factor.cg_iterations == cg_iterations > 0  # the direct path ran no CG
    assert cg.factorizations < direct.factorizations == direct.iterations + 1  # + the predictor's
    # still superlinear at the end, read above round-off (a CG step may land anywhere on the floor)
    assert rates_above_roundoff(cg.history)[-1] < 1e-3, cg.history
    # the loose solve the solver benchmark times: one factorisation fewer, the same answer to its tolerance
    loose = {}
    for contraction in (0.0, default):
        monkeypatch.setattr(newton, "KRYLOV_CONTRACTION", contraction)
        loose[contraction] = solve_newton(tissue, np.array([5.0]), tol=0.1)
    a, b = loose.values()
    assert b.factorizations == a.factorizations - 1 and b.residual <= 0.1
    # as far from the equilibrium as the direct path's iterate (2.7e-3 vs 2.5e-3 mm of a 5 mm push)
    assert np.abs(b.x - direct.x).max() < 1.5 * np.abs(a.x - direct.x).max()


def test_2d_forcing_follows_the_contraction_squared():
    """Eisenstat–Walker's choice 2: η = 0.9 θ², capped; none when the factor's measured rate cannot reach it."""
    from types import SimpleNamespace

    from scissor_cli.solvers.newton import KRYLOV_FORCING_MAX_2D, KRYLOV_MAX_ITER_2D, _reuse_forcing

    fresh = {"free": SimpleNamespace(cg_iterations_for=lambda eta: 0.0)}  # no preconditioned solve yet
    assert _reuse_forcing(fresh, 0.3, 1.5) == pytest.approx(0.9 * 0.2**2)
    assert _reuse_forcing(fresh, 0.5, 1.0) == KRYLOV_FORCING_MAX_2D  # θ = 0.5: 0.225, capped
    assert _reuse_forcing(fresh, 1e-6, 1e-3) == pytest.approx(9e-7)  # quadratic end: ever tighter
    slow = {"free": SimpleNamespace(cg_iterations_for=lambda eta: KRYLOV_MAX_ITER_2D + 1.0)}
    assert _reuse_forcing(slow, 0.3, 1.5) is None and _reuse_forcing({}, 0.3, 1.5) is None


def test_full_steps_are_extrapolated_where_the_hessian_overrates_the_curvature(example, monkeypatch):
    """10 mm push on the 15.7k mesh: an element folds at the cup's grip end, the exact
    Hessian is indefinite there and its PD stand-in makes unit steps crawl (Φ falls by
    its full linear prediction). Doubling such steps crosses that stretch."""
    import scissor_cli.solvers.newton as newton

    _, _, tissue = build_model(example, mesh_scale=0.33)
    fast = solve_newton(tissue, np.array([10.0]))
    monkeypatch.setattr(newton, "EXTRAPOLATE_RATIO", 2.0)  # never: plain backtracking
    slow = solve_newton(tissue, np.array([10.0]))
    assert fast.converged and slow.converged
    assert fast.iterations <= 25 < 30 <= slow.iterations
    assert np.abs(fast.x - slow.x).max() < 1e-6
    assert rates_above_roundoff(fast.history)[-1] < 1e-3, fast.history  # still Newton's quadratic ending
