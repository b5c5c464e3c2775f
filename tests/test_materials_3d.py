"""The 3-D-only tests of scissor_cli.mechanics.materials (the checks shared with 2-D are the
dim-parametrised tests of test_materials.py): 3-component fibers in the parameters, agreement
with the 2-D plane-strain kernels on F = diag(F2, 1), zero energy at rigid rotations, the
neo-Hookean closed form, and the eigenvalue-clamped projected tangent."""

import warnings

import numpy as np
import pytest

from scissor_cli.mechanics import materials as mat

from material_checks import (
    NONLINEAR,
    NONLINEAR_IDS,
    VARIANT_IDS,
    VARIANTS,
    assert_close_per_element,
    fiber_I4,
    invalid_F,
    kron_rotation,
    per_element_scale,
    project_and_compare,
    random_F,
    random_params,
    random_rotations,
    rotation,
    with_fiber,
    without_fiber,
)


def test_material_params_accepts_3d_fibers():
    p = mat.material_params("neo_hookean_fiber", [10.0, 20.0], 0.45, 5.0, [[0.0, 3.0, 4.0], [2.0, 0.0, 0.0]])
    assert p.fiber.shape == (2, 3)
    np.testing.assert_allclose(p.fiber, [[0.0, 0.6, 0.8], [1.0, 0.0, 0.0]], rtol=1e-15)
    shared = mat.material_params("neo_hookean_fiber", np.ones(4), 0.3, 1.0, [1.0, 2.0, 2.0])
    np.testing.assert_allclose(shared.fiber, np.tile([1 / 3, 2 / 3, 2 / 3], (4, 1)), rtol=1e-15)
    assert shared.take(np.array([3, 1])).fiber.shape == (2, 3)
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean_fiber", 10.0, 0.3, 1.0, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean_fiber", 10.0, 0.3, 1.0, [[1.0, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean_fiber", 10.0, 0.3, 1.0, [np.inf, 0.0, 0.0])
    with pytest.raises(ValueError):
        mat.MaterialParams("neo_hookean", np.ones(2), np.ones(2), np.ones(2), np.zeros(2), np.ones((2, 4)))
    with pytest.raises(ValueError):
        mat.MaterialParams("neo_hookean", np.ones(2), np.ones(2), np.ones(2), np.zeros(2), np.ones((3, 3)))
    # A 3-component fiber has no plane-strain meaning: the 2-D kernels refuse it.
    with pytest.raises(ValueError, match=r"\(M, 2\) fibers"):
        mat.evaluate(np.broadcast_to(np.eye(2), (2, 2, 2)), p)
    with pytest.raises(ValueError, match=r"\(M, 2\) fibers"):
        mat.evaluate_projected(np.broadcast_to(np.eye(2), (2, 2, 2)), p)


IN_PLANE = [0, 1, 3, 4]  # vec(F) indices of F00, F01, F10, F11 in 3-D


def test_fd_checks_see_the_fiber_term():
    """The 3-D fiber variants of test_materials.py's FD test are not vacuous: the fiber adds to Ψ, P and C."""
    rng = np.random.default_rng(103)
    M = 50
    params = random_params(3, "neo_hookean_fiber", M, rng)
    base = without_fiber(params)
    F = random_F(3, M, rng, "far")
    for a, b in zip(mat.evaluate(F, params), mat.evaluate(F, base)):
        assert np.all(np.abs(a - b).reshape(M, -1).max(axis=1) > 1e-6)


# --------------------------------------------------------------------------
# agreement with the 2-D plane-strain kernels
# --------------------------------------------------------------------------


@pytest.mark.parametrize("regime", ["near", "far"])
@pytest.mark.parametrize("model,tension_only", VARIANTS, ids=VARIANT_IDS)
def test_plane_strain_embedding_matches_2d_kernels(model, tension_only, regime):
    """F = diag(F2, 1) in 3-D gives the 2-D plane-strain Ψ, in-plane P block and 4x4 tangent block."""
    rng = np.random.default_rng(104)
    M = 200
    theta = rng.uniform(-np.pi, np.pi, M)
    p2 = random_params(3, model, M, rng, tension_only, fiber=np.c_[np.cos(theta), np.sin(theta)])
    p3 = with_fiber(p2, np.c_[p2.fiber, np.zeros(M)])
    if regime == "near":
        F2 = np.eye(2) + 0.05 * rng.standard_normal((M, 2, 2))
    else:
        lam = np.exp(rng.uniform(np.log(0.4), np.log(2.5), (M, 2)))
        R = rotation(theta)
        F2 = R @ (lam[:, :, None] * np.swapaxes(R[::-1], 1, 2))
    F3 = np.zeros((M, 3, 3))
    F3[:, :2, :2] = F2
    F3[:, 2, 2] = 1.0
    psi2, P2, C2 = mat.evaluate(F2, p2)
    psi3, P3, C3 = mat.evaluate(F3, p3)
    scale = p2.kappa.max()
    np.testing.assert_allclose(psi3, psi2, rtol=1e-12, atol=1e-13 * scale)
    assert_close_per_element(P3[:, :2, :2], P2, rtol=1e-12)
    # No out-of-plane shear stress for an in-plane state.
    assert np.abs(P3[:, :2, 2]).max() <= 1e-13 * scale and np.abs(P3[:, 2, :2]).max() <= 1e-13 * scale
    assert_close_per_element(C3[:, IN_PLANE][:, :, IN_PLANE], C2, rtol=1e-12)
    # A 2-component fiber in 3-D is the in-plane fiber (a0, 0), bit for bit.
    for a, b in zip(mat.evaluate(F3, p2), (psi3, P3, C3)):
        np.testing.assert_array_equal(a, b)


# --------------------------------------------------------------------------
# rigid rotations
# --------------------------------------------------------------------------


@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_rotations_have_zero_energy_and_stress(model, tension_only):
    rng = np.random.default_rng(106)
    M = 100
    params = random_params(3, model, M, rng, tension_only)
    psi, P, _ = mat.evaluate(random_rotations(3, M, rng), params, order=1)
    scale = params.kappa.max()
    assert np.all(np.abs(psi) <= 1e-12 * scale)
    assert np.all(np.abs(P) <= 1e-12 * scale)


def test_linear_model_is_not_rotation_invariant():
    """Small-strain theory: a finite rotation strains the linear model (the
    nonlinear models' zero energy at rotations is a real property)."""
    rng = np.random.default_rng(107)
    params = random_params(3, "linear", 50, rng)
    assert np.all(mat.energy_density(random_rotations(3, 50, rng), params) > 0.0)


# --------------------------------------------------------------------------
# closed forms of the individual models
# --------------------------------------------------------------------------


def test_neo_hookean_energy_closed_form():
    rng = np.random.default_rng(110)
    M = 60
    params = random_params(3, "neo_hookean_fiber", M, rng)
    F = random_F(3, M, rng, "far")
    J = np.linalg.det(F)
    I1 = np.einsum("eij,eij->e", F, F)
    I4 = fiber_I4(F, params)
    mu, kappa, eta = params.mu, params.kappa, params.eta
    expected = mu / 2 * (J ** (-2 / 3) * I1 - 3) + kappa / 2 * (J - 1) ** 2 + eta / 2 * (I4 - 1) ** 2
    np.testing.assert_allclose(mat.energy_density(F, params), expected, rtol=1e-11)
    np.testing.assert_allclose(mat.jacobian_det(F), J, rtol=1e-12)
    # E, ν → μ, κ as documented.
    E, nu = 12.0, 0.4
    p = mat.material_params("neo_hookean", E, nu, None, None)
    np.testing.assert_allclose([p.mu[0], p.kappa[0]], [E / (2 * (1 + nu)), E / (3 * (1 - 2 * nu))])


# --------------------------------------------------------------------------
# evaluate_projected
# --------------------------------------------------------------------------


@pytest.mark.parametrize("regime", ["near", "far"])
@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_projected_tangent_is_psd_and_exact_where_already_psd(model, tension_only, regime):
    rng = np.random.default_rng(116)
    M = 400
    params = random_params(3, model, M, rng, tension_only)
    F = random_F(3, M, rng, regime)
    if regime == "near":  # volumetric compression (twist modes < 0) and expansion
        F = F * rng.uniform(0.9, 1.1, M)[:, None, None]
    # PSD, and only negative parts are removed: Cp − C is PSD.
    C, Cp, scale = project_and_compare(F, params, psd_rtol=1e-10)
    assert Cp.shape == (M, 9, 9)
    w = np.linalg.eigvalsh(C)
    psd = w[:, 0] > 1e-9 * scale
    indefinite = w[:, 0] < -1e-9 * scale
    assert psd.any() and indefinite.any()
    # Unchanged (bit for bit) where C is already PSD ...
    np.testing.assert_array_equal(Cp[psd], C[psd])
    # ... elsewhere the eigenvalue-clamped C: same eigenvectors, max(λ, 0).
    assert_close_per_element(Cp[indefinite], mat.project_psd(C[indefinite]), rtol=1e-10)


def test_projected_tangent_clamps_small_negative_eigenvalues():
    """Slight volumetric compression: the twist modes are barely negative and must still be clamped."""
    rng = np.random.default_rng(123)
    M = 60
    params = random_params(3, "neo_hookean", M, rng)
    F = (1.0 - np.logspace(-9, -5, M))[:, None, None] * random_rotations(3, M, rng)
    C = mat.tangent(F, params)
    scale = per_element_scale(C)
    w = np.linalg.eigvalsh(C)[:, 0]
    assert np.all(w < -1e-11 * scale) and np.all(w > -1e-4 * scale)
    _, _, Cp = mat.evaluate_projected(F, params)
    assert np.all(np.linalg.eigvalsh(Cp)[:, 0] >= -1e-13 * scale)
    assert_close_per_element(Cp, mat.project_psd(C), rtol=1e-12)


def test_scaled_projection_of_huge_matrices_stays_finite():
    """The helper behind the 3-D evaluate_projected: entries near the float64
    limit are projected without overflow in eigh; a rebuilt matrix that
    overflows when scaled back becomes 0 (still PSD), never inf."""
    from scissor_cli.mechanics.materials.psd import _project_psd_scaled

    C = np.array([[[1.0, 1.0], [1.0, -1.0]], [[2.0, 1.0], [1.0, -3.0]], [[1.0, 0.0], [0.0, 2.0]]])
    C = C * np.array([1.7e308, 1e307, 1e300])[:, None, None]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with np.errstate(all="ignore"):
            Cp = _project_psd_scaled(C)
    assert np.all(np.isfinite(Cp))
    np.testing.assert_array_equal(Cp[0], 0.0)  # max entry ≈ 1.207 · 1.7e308 overflows
    w = np.linalg.eigvalsh(Cp[1] / 1e307)
    assert w[0] >= -1e-15 and w[1] > 2.0  # projected, eigenvalues (0, 2.19...)
    np.testing.assert_array_equal(Cp[2], C[2])  # already PSD: unchanged


def test_projected_tangent_at_rest_and_rotations():
    """PSD-singular tangents (rest, rigid rotations) stay the exact tangent up to round-off."""
    rng = np.random.default_rng(117)
    M = 50
    params = random_params(3, "neo_hookean_fiber", M, rng)
    F = np.concatenate([np.broadcast_to(np.eye(3), (M // 2, 3, 3)), random_rotations(3, M - M // 2, rng)])
    C = mat.tangent(F, params)
    _, _, Cp = mat.evaluate_projected(F, params)
    assert_close_per_element(Cp, C, rtol=1e-13)


def test_projected_frame_behaviour():
    """Like the exact tangent: C_proj(R F) = K C_proj(F) Kᵀ with K = R ⊗ I."""
    rng = np.random.default_rng(118)
    M = 200
    params = random_params(3, "neo_hookean_fiber", M, rng)
    F = random_F(3, M, rng, "far") * rng.uniform(0.85, 1.0, M)[:, None, None]
    R = random_rotations(3, M, rng)
    K = kron_rotation(R)
    _, _, Cp = mat.evaluate_projected(F, params)
    _, _, Cp_r = mat.evaluate_projected(R @ F, params)
    assert_close_per_element(Cp_r, K @ Cp @ np.swapaxes(K, 1, 2), rtol=1e-9)


@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_projected_invalid_rows_are_finite_psd(model, tension_only):
    rng = np.random.default_rng(120)
    F, bad = invalid_F(3)
    params = random_params(3, model, len(F), rng, tension_only)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        psi, _, Cp = mat.evaluate_projected(F, params)
    assert np.all(np.isposinf(psi[bad]))
    assert np.all(np.isfinite(Cp))
    scale = np.maximum(per_element_scale(Cp), 1e-300)
    assert np.all(np.linalg.eigvalsh(Cp / scale[:, None, None])[:, 0] >= -1e-10)
    _, _, Cg = mat.evaluate_projected(F[~bad], params.take(~bad))
    np.testing.assert_array_equal(Cp[~bad], Cg)


