"""Tests of the 3-D material kernels of scissor_cli.mechanics.materials:
closed forms against finite differences, agreement with the 2-D plane-strain
kernels on F = diag(F2, 1), rest state, frame invariance, inversion handling,
the projected tangent, and 3-component fibers in the parameters."""

import warnings

import numpy as np
import pytest

from scissor_cli.mechanics import materials as mat
from material_checks import VARIANTS, VARIANT_IDS, NONLINEAR, NONLINEAR_IDS, fiber_I4, away_from_fiber_kink, fd_gradient, assert_close_per_element, per_element_scale


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


def random_fiber3(M, rng):
    a = rng.standard_normal((M, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def random_params(model, M, rng, tension_only=False, fiber=None):
    return mat.material_params(
        model,
        E_kPa=rng.uniform(5.0, 50.0, M),
        nu=rng.uniform(0.2, 0.49, M),
        eta_kPa=rng.uniform(1.0, 20.0, M),
        fiber=random_fiber3(M, rng) if fiber is None else fiber,
        tension_only=tension_only,
    )


def with_fiber(params, fiber):
    return mat.MaterialParams(params.model, params.mu, params.kappa, params.lam, params.eta,
                              fiber, params.tension_only)


def rotations(M, rng):
    """M random proper rotations (M, 3, 3)."""
    Q, R = np.linalg.qr(rng.standard_normal((M, 3, 3)))
    Q = Q * np.sign(np.diagonal(R, axis1=1, axis2=2))[:, None, :]
    Q[np.linalg.det(Q) < 0, :, 0] *= -1.0
    return Q


def random_F(M, rng, regime):
    """Random F with J > 0: 'near' I (|F - I| ~ 0.05) or 'far' (R1 diag(λ) R2, λ in [0.4, 2.5])."""
    if regime == "near":
        F = np.eye(3) + 0.05 * rng.standard_normal((M, 3, 3))
    else:
        lam = np.exp(rng.uniform(np.log(0.4), np.log(2.5), (M, 3)))
        F = rotations(M, rng) @ (lam[:, :, None] * rotations(M, rng))
    assert np.all(mat.jacobian_det(F) > 0.05)
    return F


def kron_rotation(R):
    """K = R ⊗ I (M, 9, 9): vec(R G) = K vec(G) for row-major vec."""
    M = R.shape[0]
    return np.einsum("eij,kl->eikjl", R, np.eye(3)).reshape(M, 9, 9)


# --------------------------------------------------------------------------
# closed forms against finite differences
# --------------------------------------------------------------------------


@pytest.mark.parametrize("regime", ["near", "far"])
@pytest.mark.parametrize("model,tension_only", VARIANTS, ids=VARIANT_IDS)
def test_stress_matches_fd_of_energy(model, tension_only, regime):
    rng = np.random.default_rng(101)
    M = 150
    params = random_params(model, M, rng, tension_only)
    F = random_F(M, rng, regime)
    F, params = away_from_fiber_kink(F, params)
    P = mat.stress(F, params)
    assert P.shape == F.shape
    P_fd = fd_gradient(lambda G: mat.energy_density(G, params), F).reshape(F.shape)
    assert_close_per_element(P, P_fd)


@pytest.mark.parametrize("regime", ["near", "far"])
@pytest.mark.parametrize("model,tension_only", VARIANTS, ids=VARIANT_IDS)
def test_tangent_matches_fd_of_stress(model, tension_only, regime):
    rng = np.random.default_rng(102)
    M = 150
    params = random_params(model, M, rng, tension_only)
    F = random_F(M, rng, regime)
    F, params = away_from_fiber_kink(F, params)
    C = mat.tangent(F, params)
    assert C.shape == (F.shape[0], 9, 9) and C.flags.c_contiguous
    # fd_gradient stacks d vec(P) / d f_k in the last axis: C_fd[e, m, k].
    C_fd = fd_gradient(lambda G: mat.stress(G, params).reshape(-1, 9), F)
    assert_close_per_element(C, C_fd)
    np.testing.assert_array_equal(C, np.swapaxes(C, 1, 2))


def test_fd_checks_see_the_fiber_term():
    """The fiber variants' FD tests are not vacuous: the fiber adds to Ψ, P and C."""
    rng = np.random.default_rng(103)
    M = 50
    params = random_params("neo_hookean_fiber", M, rng)
    base = mat.MaterialParams("neo_hookean", params.mu, params.kappa, params.lam, np.zeros(M), params.fiber)
    F = random_F(M, rng, "far")
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
    p2 = random_params(model, M, rng, tension_only, fiber=np.c_[np.cos(theta), np.sin(theta)])
    p3 = with_fiber(p2, np.c_[p2.fiber, np.zeros(M)])
    if regime == "near":
        F2 = np.eye(2) + 0.05 * rng.standard_normal((M, 2, 2))
    else:
        lam = np.exp(rng.uniform(np.log(0.4), np.log(2.5), (M, 2)))
        c, s = np.cos(theta), np.sin(theta)
        R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
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
# rest state, rotations, frame invariance
# --------------------------------------------------------------------------


@pytest.mark.parametrize("model,tension_only", VARIANTS, ids=VARIANT_IDS)
def test_rest_state_has_zero_energy_and_stress(model, tension_only):
    rng = np.random.default_rng(105)
    M = 20
    params = random_params(model, M, rng, tension_only)
    F = np.broadcast_to(np.eye(3), (M, 3, 3))
    psi, P, C = mat.evaluate(F, params)
    scale = params.kappa.max()
    assert np.all(np.abs(psi) <= 1e-12 * scale)
    assert np.all(np.abs(P) <= 1e-12 * scale)
    # The rest tangent is PSD with exactly three null directions: the
    # infinitesimal rotations (skew-symmetric vec(F)).
    w = np.linalg.eigvalsh(C)
    assert np.all(np.abs(w[:, :3]) <= 1e-12 * scale)
    assert np.all(w[:, 3] > 1e-3 * params.mu.min())
    for i, j in ((0, 1), (0, 2), (1, 2)):
        skew = np.zeros((3, 3))
        skew[i, j], skew[j, i] = 1.0, -1.0
        assert np.all(np.abs(C @ skew.ravel()) <= 1e-12 * scale)


@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_rotations_have_zero_energy_and_stress(model, tension_only):
    rng = np.random.default_rng(106)
    M = 100
    params = random_params(model, M, rng, tension_only)
    psi, P, _ = mat.evaluate(rotations(M, rng), params, order=1)
    scale = params.kappa.max()
    assert np.all(np.abs(psi) <= 1e-12 * scale)
    assert np.all(np.abs(P) <= 1e-12 * scale)


def test_linear_model_is_not_rotation_invariant():
    """Small-strain theory: a finite rotation strains the linear model (the
    nonlinear models' zero energy at rotations is a real property)."""
    rng = np.random.default_rng(107)
    params = random_params("linear", 50, rng)
    assert np.all(mat.energy_density(rotations(50, rng), params) > 0.0)


@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_frame_invariance(model, tension_only):
    """Ψ(RF) = Ψ(F), P(RF) = R P(F), C(RF) = K C(F) Kᵀ with K = R ⊗ I."""
    rng = np.random.default_rng(108)
    M = 150
    params = random_params(model, M, rng, tension_only)
    F = random_F(M, rng, "far")
    R = rotations(M, rng)
    psi, P, C = mat.evaluate(F, params)
    psi_r, P_r, C_r = mat.evaluate(R @ F, params)
    np.testing.assert_allclose(psi_r, psi, rtol=1e-11, atol=1e-12 * params.kappa.max())
    assert_close_per_element(P_r, R @ P, rtol=1e-10)
    K = kron_rotation(R)
    assert_close_per_element(C_r, K @ C @ np.swapaxes(K, 1, 2), rtol=1e-10)


def test_fiber_energy_follows_rotated_material():
    """Rotating the fiber with the reference body: Ψ(F Rᵀ; R a0) = Ψ(F; a0)."""
    rng = np.random.default_rng(109)
    M = 100
    params = random_params("neo_hookean_fiber", M, rng)
    F = random_F(M, rng, "far")
    R = rotations(M, rng)
    rotated = with_fiber(params, np.einsum("eij,ej->ei", R, params.fiber))
    psi = mat.energy_density(F, params)
    psi_r = mat.energy_density(F @ np.swapaxes(R, 1, 2), rotated)
    np.testing.assert_allclose(psi_r, psi, rtol=1e-11)


# --------------------------------------------------------------------------
# closed forms of the individual models
# --------------------------------------------------------------------------


def test_neo_hookean_energy_closed_form():
    rng = np.random.default_rng(110)
    M = 60
    params = random_params("neo_hookean_fiber", M, rng)
    F = random_F(M, rng, "far")
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


def test_linear_model_closed_form():
    rng = np.random.default_rng(111)
    M = 40
    params = random_params("linear", M, rng)
    F = np.eye(3) + 0.3 * rng.standard_normal((M, 3, 3))
    eps = 0.5 * (F + np.swapaxes(F, 1, 2)) - np.eye(3)
    tr = np.trace(eps, axis1=1, axis2=2)
    mu, lam = params.mu, params.lam
    psi_ref = mu * np.sum(eps * eps, axis=(1, 2)) + 0.5 * lam * tr**2
    P_ref = 2 * mu[:, None, None] * eps + (lam * tr)[:, None, None] * np.eye(3)
    psi, P, C = mat.evaluate(F, params)
    np.testing.assert_allclose(psi, psi_ref, rtol=1e-12)
    np.testing.assert_allclose(P, P_ref, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(lam, params.kappa - 2 * params.mu / 3, rtol=1e-12)
    # Constant, PSD, with the three skew (rotation) directions as its null space.
    np.testing.assert_array_equal(mat.tangent(np.broadcast_to(np.eye(3), F.shape), params), C)
    w = np.linalg.eigvalsh(C)
    assert np.all(np.abs(w[:, :3]) <= 1e-12 * params.kappa.max()) and np.all(w[:, 3] > 0.0)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        skew = np.zeros((3, 3))
        skew[i, j], skew[j, i] = 1.0, -1.0
        np.testing.assert_array_equal(C @ skew.ravel(), 0.0)
    np.testing.assert_allclose(C[:, 0, 0], 2 * mu + lam, rtol=1e-15)
    np.testing.assert_allclose(C[:, 0, 4], lam, rtol=1e-15)
    np.testing.assert_allclose(C[:, 1, 3], mu, rtol=1e-15)


def test_neo_hookean_rest_tangent_equals_linear_tangent():
    rng = np.random.default_rng(112)
    M = 30
    E = rng.uniform(5.0, 50.0, M)
    nu = rng.uniform(0.0, 0.49, M)
    nh = mat.material_params("neo_hookean", E, nu, None, None)
    lin = mat.material_params("linear", E, nu, None, None)
    F = np.broadcast_to(np.eye(3), (M, 3, 3))
    np.testing.assert_allclose(mat.tangent(F, nh), mat.tangent(F, lin), rtol=1e-12, atol=1e-12 * nh.kappa.max())
    F = np.eye(3) + 1e-4 * rng.standard_normal((M, 3, 3))
    np.testing.assert_allclose(mat.energy_density(F, nh), mat.energy_density(F, lin), rtol=1e-3)


@pytest.mark.parametrize("tension_only", [False, True])
def test_tension_only_fiber_is_inactive_in_compression(tension_only):
    rng = np.random.default_rng(113)
    M = 50
    params = random_params("neo_hookean_fiber", M, rng, tension_only)
    base = mat.MaterialParams("neo_hookean", params.mu, params.kappa, params.lam, np.zeros(M), params.fiber)
    a = params.fiber
    F = np.eye(3) - 0.2 * a[:, :, None] * a[:, None, :]  # I4 = 0.64 < 1
    psi, P, C = mat.evaluate(F, params)
    psi0, P0, C0 = mat.evaluate(F, base)
    if tension_only:
        np.testing.assert_array_equal(psi, psi0)
        np.testing.assert_array_equal(P, P0)
        np.testing.assert_array_equal(C, C0)
    else:
        np.testing.assert_allclose(psi - psi0, 0.5 * params.eta * (0.64 - 1.0) ** 2, rtol=1e-12)


# --------------------------------------------------------------------------
# inverted and extreme elements
# --------------------------------------------------------------------------


def invalid_F():
    """Valid and invalid 3-D states; row flags: J <= 0."""
    F = np.broadcast_to(np.eye(3), (9, 3, 3)).copy()
    F[1] = np.diag([1.0, 1.0, -1.0])  # reflected
    F[2] = np.diag([-0.5, -0.5, 1.0])  # a half-turn, scaled: J = 0.25 > 0, valid
    F[3] = np.zeros((3, 3))  # collapsed, J = 0
    F[4] = [[1.0, 2.0, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 1.0]]  # J = 0 with shear
    F[5] = [[0.2, 1.0, 0.1], [1.0, 0.1, 0.0], [0.0, 0.3, 0.9]]  # J < 0
    F[6] = -np.eye(3)  # point reflection, J = -1
    F[7] = [[1.1, 0.1, 0.0], [0.0, 0.9, 0.2], [0.1, 0.0, 1.0]]  # valid
    F[8] = np.diag([0.5, 0.5, -1e-3])  # slightly inverted
    return F, np.array([False, True, False, True, True, True, True, False, True])


@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_inverted_element_energy_is_inf_without_warnings(model, tension_only):
    rng = np.random.default_rng(114)
    F, expected_bad = invalid_F()
    M = len(F)
    params = random_params(model, M, rng, tension_only)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        J = mat.jacobian_det(F)
        psi, P, C = mat.evaluate(F, params)
        psi0 = mat.energy_density(F, params)
    bad = J <= 0.0
    np.testing.assert_array_equal(bad, expected_bad)
    assert np.all(np.isposinf(psi[bad])) and np.all(np.isposinf(psi0[bad]))
    assert np.all(np.isfinite(psi[~bad]))
    assert np.all(np.isfinite(P)) and np.all(np.isfinite(C))
    # Valid rows are unaffected by invalid neighbours.
    for a, b in zip((psi, P, C), mat.evaluate(F[~bad], params.take(~bad))):
        np.testing.assert_array_equal(a[~bad], b)


@pytest.mark.parametrize("model", mat.MODELS)
def test_extreme_input_never_warns(model):
    rng = np.random.default_rng(115)
    I = np.eye(3)
    F = np.array([I * 1e200, I * 1e-200, I * 1e-7, np.diag([1e300, 1e300, -1e300]),
                  np.full((3, 3), np.nan), np.diag([np.inf, 1.0, 1.0]), np.diag([1e100, 1e-100, 1.0])])
    params = random_params(model, len(F), rng)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        psi, P, C = mat.evaluate(F, params)
        psi_p, P_p, Cp = mat.evaluate_projected(F, params)
        mat.jacobian_det(F)
    if model == "linear":
        assert np.all(np.isnan(psi[4])) and np.all(np.isfinite(Cp))  # NaN in, NaN out; C is constant
    else:
        assert not np.isnan(psi).any()
        assert np.all(np.isposinf(psi[[0, 3, 4, 5]]))  # overflow, J < 0, NaN, inf
        # The projected tangent is finite and PSD in every row, whatever the input.
        assert np.all(np.isfinite(Cp))
        np.testing.assert_array_equal(Cp, np.swapaxes(Cp, 1, 2))
        scale = np.maximum(np.abs(Cp).max(axis=(1, 2)), 1e-300)
        assert np.all(np.linalg.eigvalsh(Cp / scale[:, None, None])[:, 0] >= -1e-10)
    np.testing.assert_array_equal(psi_p, psi)
    np.testing.assert_array_equal(P_p, P)


# --------------------------------------------------------------------------
# evaluate_projected
# --------------------------------------------------------------------------


@pytest.mark.parametrize("regime", ["near", "far"])
@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_projected_tangent_is_psd_and_exact_where_already_psd(model, tension_only, regime):
    rng = np.random.default_rng(116)
    M = 400
    params = random_params(model, M, rng, tension_only)
    F = random_F(M, rng, regime)
    if regime == "near":  # volumetric compression (twist modes < 0) and expansion
        F = F * rng.uniform(0.9, 1.1, M)[:, None, None]
    psi0, P0, C = mat.evaluate(F, params)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        psi, P, Cp = mat.evaluate_projected(F, params)
    np.testing.assert_array_equal(psi, psi0)
    np.testing.assert_array_equal(P, P0)
    assert Cp.shape == (M, 9, 9) and Cp.flags.c_contiguous
    np.testing.assert_array_equal(Cp, np.swapaxes(Cp, 1, 2))
    scale = per_element_scale(C)
    w = np.linalg.eigvalsh(C)
    assert np.all(np.linalg.eigvalsh(Cp)[:, 0] >= -1e-10 * scale)
    psd = w[:, 0] > 1e-9 * scale
    indefinite = w[:, 0] < -1e-9 * scale
    assert psd.any() and indefinite.any()
    # Unchanged (bit for bit) where C is already PSD ...
    np.testing.assert_array_equal(Cp[psd], C[psd])
    # ... elsewhere the eigenvalue-clamped C: same eigenvectors, max(λ, 0).
    assert_close_per_element(Cp[indefinite], mat.project_psd(C[indefinite]), rtol=1e-10)
    # Only negative parts are removed: Cp − C is PSD.
    assert np.all(np.linalg.eigvalsh(Cp - C)[:, 0] >= -1e-10 * scale)


def test_projected_tangent_clamps_small_negative_eigenvalues():
    """Slight volumetric compression: the twist modes are barely negative and must still be clamped."""
    rng = np.random.default_rng(123)
    M = 60
    params = random_params("neo_hookean", M, rng)
    F = (1.0 - np.logspace(-9, -5, M))[:, None, None] * rotations(M, rng)
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
    params = random_params("neo_hookean_fiber", M, rng)
    F = np.concatenate([np.broadcast_to(np.eye(3), (M // 2, 3, 3)), rotations(M - M // 2, rng)])
    C = mat.tangent(F, params)
    _, _, Cp = mat.evaluate_projected(F, params)
    assert_close_per_element(Cp, C, rtol=1e-13)


def test_projected_frame_behaviour():
    """Like the exact tangent: C_proj(R F) = K C_proj(F) Kᵀ with K = R ⊗ I."""
    rng = np.random.default_rng(118)
    M = 200
    params = random_params("neo_hookean_fiber", M, rng)
    F = random_F(M, rng, "far") * rng.uniform(0.85, 1.0, M)[:, None, None]
    R = rotations(M, rng)
    K = kron_rotation(R)
    _, _, Cp = mat.evaluate_projected(F, params)
    _, _, Cp_r = mat.evaluate_projected(R @ F, params)
    assert_close_per_element(Cp_r, K @ Cp @ np.swapaxes(K, 1, 2), rtol=1e-9)


def test_projected_linear_model_is_evaluate():
    rng = np.random.default_rng(119)
    M = 50
    params = random_params("linear", M, rng)
    F = np.eye(3) + 0.3 * rng.standard_normal((M, 3, 3))
    for a, b in zip(mat.evaluate_projected(F, params), mat.evaluate(F, params)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_projected_invalid_rows_are_finite_psd(model, tension_only):
    rng = np.random.default_rng(120)
    F, bad = invalid_F()
    params = random_params(model, len(F), rng, tension_only)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        psi, _, Cp = mat.evaluate_projected(F, params)
    assert np.all(np.isposinf(psi[bad]))
    assert np.all(np.isfinite(Cp))
    scale = np.maximum(per_element_scale(Cp), 1e-300)
    assert np.all(np.linalg.eigvalsh(Cp / scale[:, None, None])[:, 0] >= -1e-10)
    _, _, Cg = mat.evaluate_projected(F[~bad], params.take(~bad))
    np.testing.assert_array_equal(Cp[~bad], Cg)


# --------------------------------------------------------------------------
# API: orders, shapes, validation
# --------------------------------------------------------------------------


def test_evaluate_orders_agree_with_single_functions():
    rng = np.random.default_rng(121)
    M = 64
    params = random_params("neo_hookean_fiber", M, rng, tension_only=True)
    F = random_F(M, rng, "far")
    psi0, P0, C0 = mat.evaluate(F, params, order=0)
    psi1, P1, C1 = mat.evaluate(F, params, order=1)
    psi2, P2, C2 = mat.evaluate(F, params, order=2)
    assert P0 is None and C0 is None and C1 is None
    np.testing.assert_array_equal(psi0, psi2)
    np.testing.assert_array_equal(psi1, psi2)
    np.testing.assert_array_equal(P1, P2)
    np.testing.assert_array_equal(mat.energy_density(F, params), psi2)
    np.testing.assert_array_equal(mat.stress(F, params), P2)
    np.testing.assert_array_equal(mat.tangent(F, params), C2)
    assert C2.flags.c_contiguous and P2.flags.c_contiguous
    # Non-contiguous input gives the same answer.
    Ft = np.ascontiguousarray(np.swapaxes(F, 1, 2))
    for a, b in zip(mat.evaluate(np.swapaxes(Ft, 1, 2), params), (psi2, P2, C2)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError):
        mat.evaluate(F, params, order=3)
    with pytest.raises(ValueError):
        mat.evaluate(F[:-1], params)
    with pytest.raises(ValueError):
        mat.evaluate_projected(F[:-1], params)
    with pytest.raises(ValueError, match=r"\(M, 2, 2\) or \(M, 3, 3\)"):
        mat.evaluate(np.zeros((M, 4, 4)), params)
    with pytest.raises(ValueError):
        mat.evaluate_projected(F.reshape(M, 9), params)


@pytest.mark.parametrize("model", mat.MODELS)
def test_empty_stack(model):
    params = mat.material_params(model, np.zeros(0) + 10.0, 0.3, 1.0, np.zeros((0, 3)))
    for psi, P, C in (mat.evaluate(np.zeros((0, 3, 3)), params),
                      mat.evaluate_projected(np.zeros((0, 3, 3)), params)):
        assert psi.shape == (0,) and P.shape == (0, 3, 3) and C.shape == (0, 9, 9)
    assert mat.jacobian_det(np.zeros((0, 3, 3))).shape == (0,)


def test_project_psd_on_9x9_stacks():
    rng = np.random.default_rng(122)
    A = rng.standard_normal((300, 9, 9))
    C = A + np.swapaxes(A, 1, 2)
    Cp = mat.project_psd(C)
    np.testing.assert_allclose(np.linalg.eigvalsh(Cp), np.sort(np.maximum(np.linalg.eigvalsh(C), 0.0), axis=1),
                               atol=1e-12)
    B = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(9)
    np.testing.assert_array_equal(mat.project_psd(B), B)
