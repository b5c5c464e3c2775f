"""The one equilibrium entry point: methods, warm starts, and loads and held dofs as inputs."""

import numpy as np
import pytest

from scissor_cli.config import load_config
from scissor_cli.experiments.build import build_model
from scissor_cli.solvers.common import Conditions, SolverError, relative_residual
from scissor_cli.solvers.equilibrium import EquilibriumSolver, solve_equilibrium
from scissor_cli.solvers.linear import Factorization

from helpers import EXAMPLE


@pytest.fixture(scope="module")
def tissue():
    cfg = load_config(EXAMPLE)
    cfg = cfg.model_copy(update={"tissue": cfg.tissue.model_copy(
        update={"mesh": cfg.tissue.mesh.model_copy(update={"scale": 2.0})})})
    return build_model(cfg)[2]


def _interior_nodes(tissue, k, seed=0):
    """k free nodes away from the boundary."""
    free_nodes = np.flatnonzero(tissue.free_index[0::2] >= 0)
    nodes = tissue.rest
    lo, hi = nodes.min(0) + 15.0, nodes.max(0) - 15.0
    inside = free_nodes[np.all((nodes[free_nodes] > lo) & (nodes[free_nodes] < hi), axis=1)]
    return np.random.default_rng(seed).choice(inside, k, replace=False)


def test_nothing_pushes_nothing_moves(tissue):
    r = solve_equilibrium(tissue, np.zeros(tissue.n_cups), conditions=Conditions(loads=np.zeros(tissue.rest.size)))
    np.testing.assert_allclose(r.x, tissue.rest, rtol=0, atol=1e-12)  # round-off of the rest gradient


def test_held_dofs_stay_and_the_rest_is_in_equilibrium(tissue):
    nodes = _interior_nodes(tissue, 6)
    held = np.concatenate([2 * nodes, 2 * nodes + 1])
    strokes = np.full(tissue.n_cups, 5.0)
    free_run = solve_equilibrium(tissue, strokes)
    r = solve_equilibrium(tissue, strokes, conditions=Conditions(held=held))
    np.testing.assert_array_equal(r.x[nodes], tissue.rest[nodes])
    assert np.abs(free_run.x[nodes] - tissue.rest[nodes]).max() > 0.1  # holding them made a difference
    _, grad = tissue.energy_gradient(r.x)
    assert relative_residual(tissue, grad, Conditions(held=held).held_free(tissue)) <= 1e-10
    assert np.linalg.norm(grad[held]) > 1.0  # the held nodes carry reactions (mN)


def test_small_loads_give_the_linear_response(tissue):
    nodes = _interior_nodes(tissue, 3, seed=1)
    f = np.zeros(tissue.rest.size)
    f[2 * nodes] = 0.02  # mN
    f[2 * nodes + 1] = -0.01
    r = solve_equilibrium(tissue, np.zeros(tissue.n_cups), conditions=Conditions(loads=f))
    K = tissue.stiffness_free(tissue.rest)
    u_lin = Factorization(K).solve(f[tissue.free_dofs])
    u = (r.x - tissue.rest).ravel()[tissue.free_dofs]
    assert np.abs(u).max() > 1e-4
    np.testing.assert_allclose(u, u_lin, atol=1e-3 * np.abs(u_lin).max())


@pytest.mark.parametrize("stroke", [0.0, 4.0])
def test_loads_balance_the_reactions(tissue, stroke):
    """Σ reactions at the fixed side, the cups and the held nodes + Σ loads = 0, per axis."""
    nodes = _interior_nodes(tissue, 4, seed=2)
    f = np.zeros(tissue.rest.size)
    f[2 * nodes] = [5.0, -2.0, 3.0, 1.0]  # mN: large enough to deform visibly
    f[2 * nodes + 1] = [-4.0, 2.5, 0.0, 6.0]
    held_nodes = _interior_nodes(tissue, 2, seed=3)
    held_nodes = held_nodes[~np.isin(held_nodes, nodes)]
    held = np.concatenate([2 * held_nodes, 2 * held_nodes + 1])
    r = solve_equilibrium(tissue, np.full(tissue.n_cups, stroke), conditions=Conditions(loads=f, held=held))
    _, grad = tissue.energy_gradient(r.x)  # at a support, ∇U is the force the support exerts on the tissue
    supports = np.concatenate([tissue.dirichlet_dofs, held])
    reaction = np.zeros(2)
    np.add.at(reaction, supports % 2, grad[supports])
    total = reaction + np.array([f[0::2].sum(), f[1::2].sum()])
    scale = np.abs(grad[supports]).sum()
    assert np.abs(total).max() <= 1e-9 * scale


def test_held_dofs_must_be_free(tissue):
    with pytest.raises(ValueError, match="Dirichlet"):
        solve_equilibrium(tissue, np.zeros(tissue.n_cups), conditions=Conditions(held=tissue.dirichlet_dofs[:2]))


def test_admm_refuses_conditions_it_cannot_honour(tissue):
    with pytest.raises(ValueError, match="newton"):
        solve_equilibrium(tissue, np.zeros(tissue.n_cups), method="admm",
                          conditions=Conditions(loads=np.ones(tissue.rest.size)))


def test_changing_held_sets_reuse_one_symbolic_factorisation(tissue):
    """Held dofs are identity rows: the pattern, and so the factor object, stays the same."""
    for k, seed in ((3, 4), (5, 5)):
        nodes = _interior_nodes(tissue, k, seed)
        solve_equilibrium(tissue, np.full(tissue.n_cups, 2.0),
                          conditions=Conditions(held=np.concatenate([2 * nodes, 2 * nodes + 1])))
    first = tissue.factor_cache["free"]
    nodes = _interior_nodes(tissue, 7, 6)
    solve_equilibrium(tissue, np.full(tissue.n_cups, 2.0), conditions=Conditions(held=2 * nodes))
    assert tissue.factor_cache["free"] is first


def test_newton_and_admm_through_the_entry_point_agree(tissue):
    strokes = np.full(tissue.n_cups, 6.0)
    newton = solve_equilibrium(tissue, strokes)
    admm = solve_equilibrium(tissue, strokes, method="admm", tol=1e-6, max_iter=5000)
    scale = np.abs(newton.x - tissue.rest).max()
    assert np.abs(admm.x - newton.x).max() <= 1e-3 * scale


def test_admm_continues_its_own_iteration(tissue):
    strokes = np.full(tissue.n_cups, 6.0)
    solver = EquilibriumSolver(tissue, "admm", tol=1e-3)
    coarse = solver.solve(strokes)
    solver.tol = 1e-5
    finer = solver.solve(strokes, continue_previous=True)
    cold = EquilibriumSolver(tissue, "admm", tol=1e-5).solve(strokes)
    assert finer.iterations < cold.iterations
    assert finer.residual <= 1e-5 and coarse.residual > finer.residual


def test_unknown_method_and_failure_are_clear(tissue):
    with pytest.raises(ValueError, match="method"):
        EquilibriumSolver(tissue, "cg")
    with pytest.raises(SolverError) as err:
        solve_equilibrium(tissue, np.full(tissue.n_cups, 8.0), max_iter=1)
    assert err.value.result is not None and "not converged" in str(err.value)


@pytest.mark.parametrize("angle_deg", [0.0, 90.0, 37.0])
def test_nodes_held_along_a_direction_keep_that_component_only(tissue, angle_deg):
    """Conditions.along_nodes: the component along u stays, the one across is in equilibrium.

    At 0° and 90° it is the same as holding the x or the y dof (the existing
    held dofs); at any angle the force the hold carries is along u only.
    """
    nodes = _interior_nodes(tissue, 5, seed=4)
    a = np.deg2rad(angle_deg)
    u = np.array([np.cos(a), np.sin(a)])
    strokes = np.full(tissue.n_cups, 5.0)
    cond = Conditions(along_nodes=nodes, along=np.tile(u, (nodes.size, 1)))
    r = solve_equilibrium(tissue, strokes, conditions=cond)
    np.testing.assert_allclose((r.x[nodes] - tissue.rest[nodes]) @ u, 0.0, atol=1e-12)
    _, grad = tissue.energy_gradient(r.x)
    g = grad.reshape(-1, 2)[nodes]
    across = np.array([-u[1], u[0]])
    scale = tissue.force_scale(grad)
    assert np.abs(g @ across).max() <= 1e-8 * scale  # free across: no reaction
    assert np.abs(g @ u).max() > 1e-3  # held along u: a reaction
    if angle_deg in (0.0, 90.0):
        k = 0 if angle_deg == 0.0 else 1
        ref = solve_equilibrium(tissue, strokes, conditions=Conditions(held=2 * nodes + k))
        np.testing.assert_allclose(r.x, ref.x, atol=1e-8)


def test_along_holds_reuse_the_symbolic_factorisation(tissue):
    nodes = _interior_nodes(tissue, 4, seed=5)
    u = np.tile([0.6, 0.8], (nodes.size, 1))
    solve_equilibrium(tissue, np.full(tissue.n_cups, 2.0), conditions=Conditions(held=2 * nodes))
    factor = tissue.factor_cache["free"]
    solve_equilibrium(tissue, np.full(tissue.n_cups, 2.0), conditions=Conditions(along_nodes=nodes, along=u))
    assert tissue.factor_cache["free"] is factor


def test_along_holds_reject_dirichlet_nodes(tissue):
    node = int(tissue.dirichlet_dofs[0] // 2)
    with pytest.raises(ValueError):
        solve_equilibrium(tissue, np.zeros(tissue.n_cups),
                          conditions=Conditions(along_nodes=np.array([node]), along=np.array([[1.0, 0.0]])))
