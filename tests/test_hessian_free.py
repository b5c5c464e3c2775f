"""A 3-D Newton step without the assembled Hessian (docs/model.md §13, "Steps without the Hessian"): H v as a
difference of gradients against the assembled K_ff, with held, rotated and loaded dofs and inertia; Newton with it
reaches the equilibrium the assembled steps reach, and falls back to them when it cannot step."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import yaml

from scissor_cli.config.loading import parse_config
from scissor_cli.experiments.build import body_model
from scissor_cli.solvers import hessian_free, newton
from scissor_cli.solvers.common import NO_CONDITIONS, Conditions, Inertia, objective_gradient
from scissor_cli.solvers.equilibrium import solve_equilibrium
from scissor_cli.solvers.held import Held
from scissor_cli.solvers.linear import Factorization, factorize_free

from test_body_loop import SCENE


@pytest.fixture(scope="module")
def body():
    """The loop's coarse dome (`nodal`, the body's default) and an equilibrium with both cups pushed 3 mm."""
    tissue = body_model(parse_config(yaml.safe_dump(dict(SCENE, trials={"count": 0})), "<test>"))[2]
    return tissue, solve_equilibrium(tissue, np.full(tissue.n_cups, 3.0)).x


def _conditions(tissue) -> Conditions:
    """Loads on a few nodes, two held dofs and two nodes held across a direction, all away from the cups."""
    free_nodes = np.flatnonzero(np.all(tissue.free_index.reshape(-1, 3) >= 0, axis=1))
    nodes = free_nodes[[10, 20]]
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    t1 = np.cross(axis, [0.0, 0.0, 1.0])
    t1 /= np.linalg.norm(t1)
    along = np.stack([np.stack([t1, np.cross(axis, t1)])] * 2)  # (2, 2, 3): both directions across the axis
    loads = np.zeros(tissue.rest.size)
    loads[3 * free_nodes[30:40]] = 0.05
    return Conditions(loads=loads, held=3 * free_nodes[[50, 60]] + 1, along_nodes=nodes, along=along)


def _assembled(tissue, x, inertia, held):
    K = newton._system(tissue, x, False, inertia, held)
    diag = K.diagonal()
    return K, (lambda v: K @ v + K.T @ v - diag * v)


@pytest.mark.parametrize("with_conditions", [False, True])
@pytest.mark.parametrize("difference, bound", [("forward", 1e-5), ("central", 1e-7)])
def test_the_difference_operator_is_the_assembled_hessian(body, with_conditions, difference, bound):
    tissue, x = body
    conditions = _conditions(tissue) if with_conditions else NO_CONDITIONS
    inertia = Inertia(0.05, x.ravel() + 0.01, tissue.mass) if with_conditions else None
    held = Held(tissue, conditions)
    K, times = _assembled(tissue, x, inertia, held)
    grad = objective_gradient(tissue, x, inertia, conditions.loads)[1] if difference == "forward" else None
    op = hessian_free.hessian_times(tissue, x, grad, inertia, conditions.loads, held)
    rng = np.random.default_rng(0)
    rough = rng.standard_normal(tissue.free_dofs.size)
    smooth = factorize_free(tissue, K, {}).solve(rough)  # what conjugate gradients steps along
    for v in (rough, smooth):
        exact = times(v)
        assert np.linalg.norm(op(v) - exact) <= bound * np.linalg.norm(exact)
    if with_conditions:  # the held rows and columns are the identity's
        e = np.zeros(tissue.free_dofs.size)
        e[held.pos] = 1.0
        np.testing.assert_allclose(op(e), e, atol=1e-12)


def test_newton_without_the_assembled_hessian_reaches_the_same_equilibrium(body, monkeypatch):
    tissue, x = body
    target = np.array([5.0, -2.0])
    calls = []
    step = hessian_free.hessian_free_step

    def counted(*args, **kwargs):
        d = step(*args, **kwargs)
        calls.append(d is not None)
        return d

    monkeypatch.setattr(newton, "hessian_free_step", counted)
    runs = {}
    for on in (True, False):
        monkeypatch.setattr(newton, "HESSIAN_FREE", on)
        runs[on] = newton.solve_newton(tissue, target, x0=x, strokes0=np.full(2, 3.0), factors={})
    assert any(calls)  # steps were taken without assembling K
    on, off = runs[True], runs[False]
    assert on.converged and off.converged
    scale = np.max(np.abs(off.x - x))
    assert np.max(np.abs(on.x - off.x)) <= 1e-6 * scale
    assert on.factorizations <= off.factorizations


def test_no_usable_factor_or_a_failing_one_leaves_the_step_to_the_assembled_hessian(body):
    tissue, x = body
    held = Held(tissue, NO_CONDITIONS)
    K, exact = _assembled(tissue, x, None, held)
    grad = objective_gradient(tissue, x, None)[1]
    g = np.random.default_rng(1).standard_normal(tissue.free_dofs.size)
    args = (tissue, x, grad, g, None, None, held)
    assert hessian_free.hessian_free_step(*args, {}, 1e-2) is None  # no factor
    good = {"free": factorize_free(tissue, K, {})}
    for rtol in (1e-2, 1e-6):  # the forward difference, the central one
        d = hessian_free.hessian_free_step(*args, good, rtol)
        assert d is not None and np.dot(g, d) < 0
        assert np.linalg.norm(exact(d) + g) <= 2 * rtol * np.linalg.norm(g)
    assert hessian_free.hessian_free_step(*args, good, 0.1 * hessian_free.SMALLEST_FORCING) is None
    good["free"].stale = True
    assert hessian_free.hessian_free_step(*args, good, 1e-2) is None
    far = {"free": Factorization(sp.diags(K.diagonal()).tocsr(), definite=True, upper=True)}  # a poor preconditioner
    assert hessian_free.hessian_free_step(*args, far, 1e-6) is None
    assert far["free"].stale  # (not converged within the iterations) so the assembled step factors at once
