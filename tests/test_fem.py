"""FE operators and the assembled energy: checked against finite differences."""

import numpy as np
import pytest

from scissor_cli import fem
from scissor_cli.config import parse_config
from scissor_cli.mesh import mesh_for_config
from scissor_cli.scene import scene_from_config
from scissor_cli.tissue import build_tissue

SCENE = """
tissue: {size_mm: [30, 20], mesh: {max_edge_mm: 5, min_edge_mm: 2.5}}
material: {model: %s, E_kPa: 10, nu: 0.4, eta_kPa: 4, fiber_angle_deg: 25}
cups: [{name: c, contact_mm: [15, 20], axis: [0, -1], radius_mm: 4}]
obstacles: [{name: v, circle: {center_mm: [10, 10], radius_mm: 2.5}, stiffness_factor: 3}]
"""


@pytest.fixture(scope="module", params=["linear", "neo_hookean", "neo_hookean_fiber"])
def tissue(request):
    cfg = parse_config(SCENE % request.param)
    scene = scene_from_config(cfg)
    return build_tissue(scene, mesh_for_config(scene, cfg.tissue.mesh))


def deformed(tissue, seed=0, amp=0.4):
    rng = np.random.default_rng(seed)
    return tissue.rest + amp * rng.standard_normal(tissue.rest.shape) + 0.05 * tissue.rest[:, ::-1]


def test_reduction_matrix_gives_deformation_gradients(tissue):
    x = deformed(tissue)
    D = fem.reduction_matrix(tissue.ops)
    F = fem.deformation_gradients(tissue.ops, x)
    assert np.allclose(D @ x.ravel(), F.reshape(-1))


def test_affine_motion_has_uniform_F(tissue):
    A = np.array([[1.2, 0.3], [-0.1, 0.8]])
    F = fem.deformation_gradients(tissue.ops, tissue.rest @ A.T + 5)
    assert np.allclose(F, A)


def test_gradient_matches_finite_differences(tissue):
    x = deformed(tissue)
    assert tissue.jacobians(x).min() > 0
    _, g = tissue.energy_gradient(x)
    rng = np.random.default_rng(1)
    for _ in range(3):
        v = rng.standard_normal(x.shape)
        h = 1e-6
        fd = (tissue.energy(x + h * v) - tissue.energy(x - h * v)) / (2 * h)
        assert np.isclose(fd, g @ v.ravel(), rtol=1e-6, atol=1e-9)


def test_hessian_matches_finite_differences(tissue):
    x = deformed(tissue)
    K = tissue.stiffness_free(x)
    free = tissue.free_dofs
    rng = np.random.default_rng(2)
    v = np.zeros(x.size)
    v[free] = rng.standard_normal(len(free))
    h = 1e-6
    fd = (tissue.energy_gradient(x + h * v.reshape(-1, 2))[1] - tissue.energy_gradient(x - h * v.reshape(-1, 2))[1]) / (2 * h)
    assert np.allclose(K @ v[free], fd[free], rtol=1e-5, atol=1e-7 * np.abs(fd).max())
    assert np.allclose(tissue.stiffness_times(x, v), fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())
    assert abs(K - K.T).max() < 1e-10 * abs(K).max()


def test_projected_hessian_is_psd(tissue):
    x = deformed(tissue, amp=0.8)
    K = tissue.stiffness_free(x, project=True).toarray()
    assert np.linalg.eigvalsh(K).min() > -1e-9 * np.abs(K).max()


def test_zero_force_at_rest_and_mass(tissue):
    _, g = tissue.energy_gradient(tissue.rest)
    assert np.abs(g).max() < 1e-11  # round-off of F = I from absolute positions
    area = tissue.ops.area.sum()
    assert np.isclose(tissue.mass.sum(), 2 * 1e-6 * tissue.ops.thickness_mm * area)
