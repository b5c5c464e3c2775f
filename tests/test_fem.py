"""FE operators and the assembled energy: checked against finite differences."""

import numpy as np
import pytest

from scissor_cli.config import parse_config
from scissor_cli.experiments.build import scene_of
from scissor_cli.mechanics import fem
from scissor_cli.mechanics.tissue import build_tissue
from scissor_cli.mesh.mesh import mesh_for_config

SCENE = """
tissue: {size_mm: [30, 20], mesh: {max_edge_mm: 5, min_edge_mm: 2.5}}
material: {model: %s, E_kPa: 10, nu: 0.4, eta_kPa: 4, fiber_angle_deg: 25}
cups: [{name: c, contact_mm: [15, 20], axis: [0, -1], radius_mm: 4}]
obstacles: [{name: v, circle: {center_mm: [10, 10], radius_mm: 2.5}, stiffness_factor: 3}]
"""


@pytest.fixture(scope="module", params=["linear", "neo_hookean", "neo_hookean_fiber"])
def tissue(request):
    cfg = parse_config(SCENE % request.param)
    scene = scene_of(cfg)
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
    fd = (tissue.energy_gradient(x + h * v.reshape(-1, 2))[1]
          - tissue.energy_gradient(x - h * v.reshape(-1, 2))[1]) / (2 * h)
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


def test_packed_element_matrices_are_the_matrix_products(tissue):
    """Ke = vol GᵀCG: the packed closed form against the batched products it stands for."""
    from scissor_cli.mechanics import materials

    x = deformed(tissue)
    C = materials.evaluate(fem.deformation_gradients(tissue.ops, x), tissue.params, 2)[2]
    G, vol = tissue.ops.G, tissue.ops.volume
    ref = np.matmul(np.matmul(G.transpose(0, 2, 1), C), G) * vol[:, None, None]
    packed = fem.element_matrices(tissue.ops, C)
    assert packed.shape == (21, len(vol))
    np.testing.assert_allclose(fem.unpack(packed), ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    # and K v element by element equals the assembled matrix times v
    v = np.random.default_rng(3).standard_normal(2 * tissue.mesh.n_nodes)
    full = fem.sparse_pattern(tissue.ops).assemble(packed)
    np.testing.assert_allclose(fem.packed_times(tissue.ops, packed, v), full @ v, rtol=1e-12, atol=1e-12)


def test_upper_pattern_is_the_upper_triangle_of_the_full_one(tissue):
    import scipy.sparse as sp

    from scissor_cli.solvers.linear import Factorization

    x = deformed(tissue, amp=0.1)
    K = tissue.stiffness_free(x, project=True)
    U = tissue.stiffness_free(x, project=True, upper=True)
    assert abs(sp.triu(K) - U).max() <= 1e-12 * abs(K).max()
    assert U.has_sorted_indices and sp.tril(U, -1).nnz == 0
    b = np.random.default_rng(4).standard_normal(K.shape[0])
    np.testing.assert_allclose(Factorization(U, upper=True).solve(b), Factorization(K).solve(b), rtol=1e-10)
    # the qdldl fallback reads the upper triangle too
    shift = 2 * abs(K).max()
    Ki, Ui = (K - shift * sp.eye(K.shape[0])).tocsr(), (U - shift * sp.eye(K.shape[0])).tocsr()
    f = Factorization(Ui, upper=True)
    assert f.method == "ldl"
    np.testing.assert_allclose(Ki @ f.solve(b), b, atol=1e-8 * np.abs(b).max())
    with pytest.raises(ValueError, match="upper-triangular"):
        Factorization(K, upper=True)
