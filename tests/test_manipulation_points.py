"""Manipulation-point planning (docs/model.md §7): candidates on the accessible sides, the adjoint
responses against finite differences of full solves, the ranking, the verified choice."""

from functools import lru_cache

import numpy as np
import pytest

from scissor_cli.config import ManipulationPointsConfig, load_config
from scissor_cli.experiments.build import build_model, with_grips
from scissor_cli.mesh.probe import probe_targets, target_positions
from scissor_cli.planning import manipulation_points as mp
from scissor_cli.solvers.common import Conditions
from scissor_cli.solvers.equilibrium import solve_equilibrium

from helpers import ROOT


@lru_cache(maxsize=None)
def example():
    cfg = load_config(ROOT / "configs" / "example.yaml")
    points = ManipulationPointsConfig(sides=["top", "right"], spacing_mm=4.0)
    cfg = cfg.model_copy(update={"manipulation_points": points})
    scene, _, tissue = build_model(cfg, mesh_scale=2.0)
    return cfg, scene, tissue


def test_candidates_lie_on_the_accessible_sides_at_the_spacing():
    cfg, scene, _ = example()
    c = mp.grip_candidates(scene, ["top", "right"], 4.0, 5.0)
    assert set(c.sides) == {"top", "right"}
    top = c.points[np.array(c.sides) == "top"]
    np.testing.assert_allclose(top[:, 1], 60.0)
    np.testing.assert_allclose(np.diff(np.sort(top[:, 0])), 4.0)
    np.testing.assert_allclose(c.normals[np.array(c.sides) == "top"], [[0.0, -1.0]] * len(top), atol=1e-12)
    right = c.points[np.array(c.sides) == "right"]
    np.testing.assert_allclose(right[:, 0], 100.0)
    assert right[:, 1].min() > 5.0  # a cup there would grip the fixed bottom


def test_adjoint_responses_equal_finite_differences_of_full_solves():
    _, scene, tissue = example()
    free = mp.released(tissue)
    assert free.n_cups == 0
    cands = mp.grip_candidates(scene, ["top", "right"], 4.0, 5.0)
    F = mp.force_vectors(free.mesh, cands, 5.0)
    targets = np.array([t.rest for t in scene.targets])
    probe = probe_targets(free.mesh, targets)
    R, u, _ = mp.adjoint_responses(free, free.rest, probe, F)
    assert R.shape == (len(targets), len(cands), 2) and np.all(u > 0)
    eps = 0.1  # mN: small enough to stay linear
    for c in (0, len(cands) // 2, len(cands) - 1):
        plus = solve_equilibrium(free, np.zeros(0), conditions=Conditions(loads=eps * F[:, c]), tol=1e-9).x
        minus = solve_equilibrium(free, np.zeros(0), conditions=Conditions(loads=-eps * F[:, c]), tol=1e-9).x
        fd = (target_positions(probe, plus) - target_positions(probe, minus)) / (2 * eps)
        np.testing.assert_allclose(R[:, c], fd, rtol=1e-4, atol=1e-9 * np.abs(R).max())
        # the compliance: the patch's own motion along the force per unit force
        assert (F[:, c] @ (plus - minus).ravel()) / (2 * eps) == pytest.approx(u[c], rel=1e-4)


def test_plan_grips_ranks_verifies_and_replaces_the_first_cups():
    cfg, scene, tissue = example()
    plan = mp.plan_grips(cfg.manipulation_points, cfg.needle, tissue,
                         lambda contacts, axes: build_model(with_grips(cfg, contacts, axes), mesh_scale=2.0)[2])
    assert plan.contacts.shape == (1, 2) and plan.axes.shape == (1, 2)
    c = plan.chosen[0]
    np.testing.assert_allclose(plan.contacts[0], plan.candidates.points[c])
    np.testing.assert_allclose(plan.axes[0], plan.candidates.normals[c])
    for tr in plan.targets:
        assert tr.score.shape == (len(plan.candidates),)
        np.testing.assert_allclose(np.abs(tr.miss_direction @ tr.axis), 0.0, atol=1e-12)
        # linear prediction and the verifying nonlinear solve agree in direction
        assert np.all(np.isfinite(tr.verified)) and tr.predicted @ tr.verified > 0
    # the grip that the ranking prefers moves the targets across their needles at least as well as the configured one
    new = with_grips(cfg, plan.contacts, plan.axes)
    assert new.cups[0].contact_mm == plan.contacts[0].tolist() and new.cups[0].radius_mm == cfg.cups[0].radius_mm
    assert new.cups[0].stroke_mm == cfg.cups[0].stroke_mm
