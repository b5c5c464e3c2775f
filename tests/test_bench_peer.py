"""The scikit-fem peer of benchmarks/bench_solvers.py solves the same problem as scissor.

The benchmark's ratio "peer time / scissor time" only means something if both
compute the same discrete solution: same mesh, energy, material parameters,
fiber, thickness and Dirichlet conditions. On the example's ~1000-element
mesh the peer's target positions must agree with scissor's Newton to 1e-6 mm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scissor_cli.config import load_config
from scissor_cli.experiments.simulate import build_model
from scissor_cli.mesh.probe import probe_targets, target_positions
from scissor_cli.solvers.newton import solve_newton

from helpers import benchmark_module

pytest.importorskip("skfem")  # the benchmark's peer (the bench and test extras)

ROOT = Path(__file__).resolve().parents[1]


def _bench_module():
    return benchmark_module("bench_solvers")


@pytest.fixture(scope="module")
def small_model():
    cfg = load_config(ROOT / "configs" / "example.yaml")
    scene, mesh, tissue = build_model(cfg, mesh_scale=2.0)
    assert 800 <= mesh.n_elements <= 1300
    return scene, mesh, tissue


def test_peer_solution_matches_scissor_newton(small_model):
    scene, mesh, tissue = small_model
    bench = _bench_module()
    strokes = bench.STROKE
    ref = solve_newton(tissue, strokes, tol=1e-10)
    assert ref.converged

    peer = bench.SkfemPeer(tissue)
    result = peer.solve(strokes, tol=1e-10)
    assert result.converged, result.history

    probe = probe_targets(mesh, np.array([t.rest for t in scene.targets]))
    p_ref = target_positions(probe, ref.x)
    p_peer = target_positions(probe, result.x)
    moved = np.linalg.norm(p_ref - target_positions(probe, mesh.nodes), axis=1)
    assert moved.min() > 0.1  # the comparison is not trivial: the targets move
    assert np.abs(p_peer - p_ref).max() <= 1e-6  # mm
    assert np.abs(result.x - ref.x).max() <= 1e-6  # every node, mm


def test_peer_forms_equal_scissor_energy_gradient_hessian(small_model):
    """At a deformed state the peer's Functional / LinearForm / BilinearForm are scissor's U, ∇U, K."""
    _, mesh, tissue = small_model
    bench = _bench_module()
    x = solve_newton(tissue, bench.STROKE, tol=1e-6).x
    peer = bench.SkfemPeer(tissue)
    uv = peer.basis.interpolate((x - mesh.nodes).ravel())
    energy = peer.energy.assemble(peer.basis, displacement=uv, **peer.fields)
    grad = peer.residual.assemble(peer.basis, displacement=uv, **peer.fields)
    K = peer.tangent.assemble(peer.basis, displacement=uv, **peer.fields)
    U, g = tissue.energy_gradient(x)
    free = tissue.free_dofs
    K_ref = tissue.stiffness_free(x).toarray()
    assert energy == pytest.approx(U, rel=1e-12)
    assert np.abs(grad - g).max() <= 1e-10 * np.abs(g).max()
    assert np.abs(K.toarray()[np.ix_(free, free)] - K_ref).max() <= 1e-10 * np.abs(K_ref).max()
