"""Tests of the material kernels of scissor_cli.mechanics.materials: closed forms against finite
differences, rest state, frame invariance, small-strain consistency, inversion handling, the
projected tangent. A check that holds in both dimensions is one test parametrised by dim (2: the
plane-strain kernels, 3: the 3-D ones); the 2-D-only checks follow them here, the 3-D-only ones
(3-component fibers, the plane-strain embedding, the eigenvalue-clamped projection) are in
test_materials_3d.py. Both draw their states and parameters with material_checks.py."""

import warnings

import numpy as np
import pytest

from scissor_cli.mechanics import materials as mat
from scissor_cli.mechanics.materials import plane_strain_projection

from material_checks import (
    NONLINEAR,
    NONLINEAR_IDS,
    VARIANT_IDS,
    VARIANTS,
    assert_close_per_element,
    away_from_fiber_kink,
    extreme_F,
    fd_gradient,
    invalid_F,
    kron_rotation,
    per_element_scale,
    project_and_compare,
    random_F,
    random_params,
    random_rotations,
    rotation,
    skew_directions,
    with_fiber,
    without_fiber,
)

DIMS = pytest.mark.parametrize("dim", [2, 3], ids=["2d", "3d"])


# --------------------------------------------------------------------------
# both dimensions: closed forms against finite differences
# --------------------------------------------------------------------------


@DIMS
@pytest.mark.parametrize("regime", ["near", "far"])
@pytest.mark.parametrize("model,tension_only", VARIANTS, ids=VARIANT_IDS)
@pytest.mark.parametrize("order", [1, 2], ids=["stress", "tangent"])
def test_derivative_matches_fd(order, model, tension_only, regime, dim):
    """The stress P = ∂Ψ/∂F (order 1) and the tangent C = ∂vec(P)/∂vec(F) (order 2) against
    central differences of the order below."""
    rng = np.random.default_rng({(1, 2): 1, (2, 2): 2, (1, 3): 101, (2, 3): 102}[order, dim])
    M = {2: 200, 3: 150}[dim]
    params = random_params(dim, model, M, rng, tension_only)
    F = random_F(dim, M, rng, regime)
    if order == 2:  # the tension-only tangent jumps at I4 = 1 (Ψ and P are smooth enough there)
        F, params = away_from_fiber_kink(F, params)
    closed, below = {1: (mat.stress, mat.energy_density), 2: (mat.tangent, mat.stress)}[order]
    out = closed(F, params)
    assert out.shape == (len(F),) + ((dim, dim) if order == 1 else (dim * dim, dim * dim))
    assert out.flags.c_contiguous
    # fd_gradient stacks d(below) / d f_k in the last axis: C_fd[e, m, k] = d vec(P)_m / d f_k.
    fd = fd_gradient(lambda G: below(G, params).reshape(len(G), -1), F).reshape(out.shape)
    assert_close_per_element(out, fd)
    if order == 2:
        np.testing.assert_array_equal(out, np.swapaxes(out, 1, 2))


# --------------------------------------------------------------------------
# both dimensions: rest state, frame invariance, closed forms
# --------------------------------------------------------------------------


@DIMS
@pytest.mark.parametrize("tension_only", [False, True])
def test_tension_only_fiber_is_inactive_in_compression(tension_only, dim):
    rng = np.random.default_rng({2: 3, 3: 113}[dim])
    M = 50
    params = random_params(dim, "neo_hookean_fiber", M, rng, tension_only)
    base = without_fiber(params)
    # Compress along the fiber: F = I - 0.2 a aᵀ gives I4 = 0.64 < 1.
    a = params.fiber
    F = np.eye(dim) - 0.2 * a[:, :, None] * a[:, None, :]
    psi, P, C = mat.evaluate(F, params)
    psi0, P0, C0 = mat.evaluate(F, base)
    if tension_only:
        np.testing.assert_array_equal(psi, psi0)
        np.testing.assert_array_equal(P, P0)
        np.testing.assert_array_equal(C, C0)
    else:
        expected = 0.5 * params.eta * (0.64 - 1.0) ** 2
        np.testing.assert_allclose(psi - psi0, expected, rtol=1e-12)


@DIMS
@pytest.mark.parametrize("model,tension_only", VARIANTS, ids=VARIANT_IDS)
def test_rest_state_has_zero_energy_and_stress(model, tension_only, dim):
    rng = np.random.default_rng({2: 4, 3: 105}[dim])
    M = 20
    params = random_params(dim, model, M, rng, tension_only)
    F = np.broadcast_to(np.eye(dim), (M, dim, dim))
    psi, P, C = mat.evaluate(F, params)
    scale = params.kappa.max()
    assert np.all(np.abs(psi) <= 1e-12 * scale)
    assert np.all(np.abs(P) <= 1e-12 * scale)
    # The rest tangent is PSD and its null directions are exactly the infinitesimal
    # rotations (one in 2-D, three in 3-D).
    skews = skew_directions(dim)
    n_null = len(skews)
    w = np.linalg.eigvalsh(C)
    assert np.all(np.abs(w[:, :n_null]) <= 1e-12 * scale)
    assert np.all(w[:, n_null] > 1e-3 * params.mu.min())
    for skew in skews:
        assert np.all(np.abs(C @ skew) <= 1e-12 * scale)


@DIMS
@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_frame_invariance(model, tension_only, dim):
    """Ψ(RF) = Ψ(F), P(RF) = R P(F) (objectivity of the first Piola–Kirchhoff stress) and
    C(RF) = K C(F) Kᵀ with K = R ⊗ I."""
    rng = np.random.default_rng({2: 5, 3: 108}[dim])
    M = {2: 100, 3: 150}[dim]
    params = random_params(dim, model, M, rng, tension_only)
    F = random_F(dim, M, rng, "far")
    R = random_rotations(dim, M, rng)
    psi, P, C = mat.evaluate(F, params)
    psi_r, P_r, C_r = mat.evaluate(R @ F, params)
    np.testing.assert_allclose(psi_r, psi, rtol=1e-11, atol=1e-12 * params.kappa.max())
    # The stress both entrywise (relative to the largest stress) and per element.
    np.testing.assert_allclose(P_r, R @ P, rtol=1e-9, atol=1e-10 * np.abs(P).max())
    assert_close_per_element(P_r, R @ P, rtol=1e-10)
    K = kron_rotation(R)
    assert_close_per_element(C_r, K @ C @ np.swapaxes(K, 1, 2), rtol=1e-10)


@DIMS
def test_fiber_energy_follows_rotated_material(dim):
    """Rotating the fiber with the reference body: Ψ(F Rᵀ; R a0) = Ψ(F; a0)."""
    rng = np.random.default_rng({2: 6, 3: 109}[dim])
    M = 100
    params = random_params(dim, "neo_hookean_fiber", M, rng)
    F = random_F(dim, M, rng, "far")
    R = random_rotations(dim, M, rng)
    rotated = with_fiber(params, np.einsum("eij,ej->ei", R, params.fiber))
    psi = mat.energy_density(F, params)
    psi_r = mat.energy_density(F @ np.swapaxes(R, 1, 2), rotated)
    np.testing.assert_allclose(psi_r, psi, rtol=1e-11)


@DIMS
def test_neo_hookean_rest_tangent_equals_linear_tangent(dim):
    rng = np.random.default_rng({2: 7, 3: 112}[dim])
    M = 30
    E = rng.uniform(5.0, 50.0, M)
    nu = rng.uniform(0.0, 0.49, M)
    nh = mat.material_params("neo_hookean", E, nu, None, None)
    lin = mat.material_params("linear", E, nu, None, None)
    np.testing.assert_allclose(nh.lam, nh.kappa - 2.0 * nh.mu / 3.0, rtol=1e-12)
    F = np.broadcast_to(np.eye(dim), (M, dim, dim))
    C_nh = mat.tangent(F, nh)
    C_lin = mat.tangent(F, lin)
    np.testing.assert_allclose(C_nh, C_lin, rtol=1e-12, atol=1e-12 * nh.kappa.max())
    # ... and so the energies agree to second order in the strain.
    F = np.eye(dim) + 1e-4 * rng.standard_normal((M, dim, dim))
    psi_nh = mat.energy_density(F, nh)
    psi_lin = mat.energy_density(F, lin)
    np.testing.assert_allclose(psi_nh, psi_lin, rtol=1e-3)


@DIMS
def test_linear_model_closed_form(dim):
    rng = np.random.default_rng({2: 8, 3: 111}[dim])
    M = 40
    params = random_params(dim, "linear", M, rng)
    F = np.eye(dim) + 0.3 * rng.standard_normal((M, dim, dim))
    eps = 0.5 * (F + np.swapaxes(F, 1, 2)) - np.eye(dim)
    tr = np.trace(eps, axis1=1, axis2=2)
    mu, lam = params.mu, params.lam
    psi_ref = mu * np.sum(eps * eps, axis=(1, 2)) + 0.5 * lam * tr**2
    P_ref = 2 * mu[:, None, None] * eps + (lam * tr)[:, None, None] * np.eye(dim)
    psi, P, C = mat.evaluate(F, params)
    np.testing.assert_allclose(psi, psi_ref, rtol=1e-12)
    np.testing.assert_allclose(P, P_ref, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(lam, params.kappa - 2 * params.mu / 3, rtol=1e-12)
    # Constant, PSD, with the skew (rotation) directions as its null space.
    np.testing.assert_array_equal(mat.tangent(np.broadcast_to(np.eye(dim), F.shape), params), C)
    skews = skew_directions(dim)
    w = np.linalg.eigvalsh(C)
    assert np.all(np.abs(w[:, :len(skews)]) <= 1e-12 * params.kappa.max()) and np.all(w[:, len(skews)] > 0.0)
    for skew in skews:
        np.testing.assert_array_equal(C @ skew, 0.0)
    # vec(F) indices: F00 is 0, F01 is 1, F10 is dim, F11 is dim + 1.
    np.testing.assert_allclose(C[:, 0, 0], 2 * mu + lam, rtol=1e-15)
    np.testing.assert_allclose(C[:, 0, dim + 1], lam, rtol=1e-15)
    np.testing.assert_allclose(C[:, 1, dim], mu, rtol=1e-15)


# --------------------------------------------------------------------------
# both dimensions: inverted and extreme elements
# --------------------------------------------------------------------------


@DIMS
@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_inverted_element_energy_is_inf_without_warnings(model, tension_only, dim):
    rng = np.random.default_rng({2: 9, 3: 114}[dim])
    F, expected_bad = invalid_F(dim)
    params = random_params(dim, model, len(F), rng, tension_only)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        J = mat.jacobian_det(F)
        psi, P, C = mat.evaluate(F, params)
        psi0 = mat.energy_density(F, params)
    bad = J <= 0.0
    np.testing.assert_array_equal(bad, expected_bad)
    assert np.all(np.isposinf(psi[bad])) and np.all(np.isposinf(psi0[bad]))
    assert np.all(np.isfinite(psi[~bad]))
    assert not np.isnan(psi).any()
    assert np.all(np.isfinite(P)) and np.all(np.isfinite(C))
    # Valid rows are unaffected by invalid neighbours.
    for a, b in zip((psi, P, C), mat.evaluate(F[~bad], params.take(~bad))):
        np.testing.assert_array_equal(a[~bad], b)


@DIMS
@pytest.mark.parametrize("model", mat.MODELS)
def test_extreme_input_never_warns(model, dim):
    rng = np.random.default_rng({2: 13, 3: 115}[dim])
    F = extreme_F(dim)
    params = random_params(dim, model, len(F), rng)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        psi, P, C = mat.evaluate(F, params)
        psi_p, P_p, Cp = mat.evaluate_projected(F, params)
        # Known gaps, each checked where it holds: project_psd of a 9x9 stack near the float64
        # limit still warns (the 3-D evaluate_projected scales before eigh), and the 2-D
        # jacobian_det still overflows with a warning on the 1e200 rows.
        if dim == 2:
            mat.project_psd(np.nan_to_num(C))
        else:
            mat.jacobian_det(F)
    nan_in = np.isnan(F).any(axis=(1, 2))
    if model == "linear":
        # NaN in, NaN out; C is constant.
        assert np.all(np.isnan(psi[nan_in])) and not np.isnan(psi[~nan_in]).any()
        assert np.all(np.isfinite(Cp))
    else:
        assert not np.isnan(psi).any()
        # Overflow, J < 0, NaN and inf give an infinite energy.
        expected_inf = ~np.isfinite(F).all(axis=(1, 2))
        expected_inf[[0, 3]] = True
        assert np.all(np.isposinf(psi[expected_inf]))
        # The projected tangent is finite and PSD in every row, whatever the input.
        assert np.all(np.isfinite(Cp))
        np.testing.assert_array_equal(Cp, np.swapaxes(Cp, 1, 2))
        scale = np.maximum(np.abs(Cp).max(axis=(1, 2)), 1e-300)
        assert np.all(np.linalg.eigvalsh(Cp / scale[:, None, None])[:, 0] >= -1e-10)
    np.testing.assert_array_equal(psi_p, psi)
    np.testing.assert_array_equal(P_p, P)


# --------------------------------------------------------------------------
# both dimensions: API (orders, shapes, validation), project_psd
# --------------------------------------------------------------------------


@DIMS
def test_evaluate_orders_agree_with_single_functions(dim):
    rng = np.random.default_rng({2: 10, 3: 121}[dim])
    M = 64
    params = random_params(dim, "neo_hookean_fiber", M, rng, tension_only=True)
    F = random_F(dim, M, rng, "far")
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
        mat.evaluate_projected(F.reshape(M, dim * dim), params)


@DIMS
@pytest.mark.parametrize("model", mat.MODELS)
def test_empty_stack(model, dim):
    n = dim * dim
    params = mat.material_params(model, np.zeros(0) + 10.0, 0.3, 1.0, np.zeros((0, dim)))
    for psi, P, C in (mat.evaluate(np.zeros((0, dim, dim)), params),
                      mat.evaluate_projected(np.zeros((0, dim, dim)), params)):
        assert psi.shape == (0,) and P.shape == (0, dim, dim) and C.shape == (0, n, n)
    assert mat.project_psd(C).shape == (0, n, n)
    assert mat.jacobian_det(np.zeros((0, dim, dim))).shape == (0,)


@DIMS
def test_project_psd(dim):
    """On stacks of tangent-sized (d² x d²) symmetric matrices."""
    rng = np.random.default_rng({2: 12, 3: 122}[dim])
    M, n = {2: 500, 3: 300}[dim], dim * dim
    A = rng.standard_normal((M, n, n))
    C = A + np.swapaxes(A, 1, 2)
    Cp = mat.project_psd(C)
    np.testing.assert_allclose(Cp, np.swapaxes(Cp, 1, 2), atol=1e-12)
    w_in = np.linalg.eigvalsh(C)
    w_out = np.linalg.eigvalsh(Cp)
    assert w_out.min() > -1e-12
    np.testing.assert_allclose(w_out, np.sort(np.maximum(w_in, 0.0), axis=1), atol=1e-12)
    # Already PSD: returned unchanged (bit for bit), as a new array.
    B = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(n)
    Bp = mat.project_psd(B)
    np.testing.assert_array_equal(Bp, B)
    assert Bp is not B
    # A positive floor.
    Cf = mat.project_psd(C, floor=0.5)
    assert np.linalg.eigvalsh(Cf).min() > 0.5 - 1e-10
    # Projecting a tangent stack far from rest keeps the rest of the stack.
    params = random_params(dim, "neo_hookean_fiber", 100, rng)
    Ct = mat.tangent(random_F(dim, 100, rng, "far"), params)
    Ctp = mat.project_psd(Ct)
    assert np.linalg.eigvalsh(Ctp).min() > -1e-9 * np.abs(Ct).max()


@DIMS
def test_projected_linear_model_is_evaluate(dim):
    rng = np.random.default_rng({2: 25, 3: 119}[dim])
    M = 50
    params = random_params(dim, "linear", M, rng)
    F = np.eye(dim) + 0.3 * rng.standard_normal((M, dim, dim))
    for a, b in zip(mat.evaluate_projected(F, params), mat.evaluate(F, params)):
        np.testing.assert_array_equal(a, b)
    assert np.linalg.eigvalsh(mat.tangent(F, params)).min() > -1e-12


# --------------------------------------------------------------------------
# 2-D only: scratch reuse, parameter validation
# --------------------------------------------------------------------------


def test_outputs_do_not_alias_scratch_and_any_layout_works():
    rng = np.random.default_rng(11)
    params = random_params(2, "neo_hookean_fiber", 50, rng)
    F = random_F(2, 50, rng, "far")
    psi, P, C = mat.evaluate(F, params)
    saved = (psi.copy(), P.copy(), C.copy())
    # A larger and then a smaller call reuse (and grow) the scratch buffer.
    big = random_params(2, "neo_hookean", 300, rng)
    mat.evaluate(random_F(2, 300, rng, "near"), big)
    mat.evaluate(F[:7], params.take(slice(0, 7)))
    for a, b in zip((psi, P, C), saved):
        np.testing.assert_array_equal(a, b)
    # Non-contiguous input (a transposed view) gives the same answer.
    Ft = np.ascontiguousarray(np.swapaxes(F, 1, 2))
    psi_t, P_t, C_t = mat.evaluate(np.swapaxes(Ft, 1, 2), params)
    np.testing.assert_array_equal(psi_t, psi)
    np.testing.assert_array_equal(P_t, P)
    np.testing.assert_array_equal(C_t, C)
    mat.release_workspace()
    np.testing.assert_array_equal(mat.evaluate(F, params)[2], C)


def test_material_params_validation_and_values():
    with pytest.raises(ValueError, match="linear.*neo_hookean.*neo_hookean_fiber"):
        mat.material_params("mooney_rivlin", 10.0, 0.3, 0.0, [[1.0, 0.0]])
    with pytest.raises(ValueError):
        mat.MaterialParams("ogden", np.ones(1), np.ones(1), np.ones(1), np.zeros(1),
                           np.array([[1.0, 0.0]]))
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean", 10.0, 0.5, 0.0, [[1.0, 0.0]])
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean", -1.0, 0.3, 0.0, [[1.0, 0.0]])
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean_fiber", 10.0, 0.3, -1.0, [[1.0, 0.0]])
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean_fiber", 10.0, 0.3, 1.0, [[0.0, 0.0]])
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean", np.ones(3), 0.3, 0.0, np.ones((4, 2)))

    E = np.array([10.0, 20.0, 30.0])
    p = mat.material_params("neo_hookean_fiber", E, 0.45, 5.0, [3.0, 4.0], tension_only=True)
    assert p.n_elements == 3 and p.tension_only
    np.testing.assert_allclose(p.mu, E / 2.9)
    np.testing.assert_allclose(p.kappa, E / (3 * 0.1))
    np.testing.assert_allclose(p.lam, E * 0.45 / (1.45 * 0.1))
    np.testing.assert_allclose(p.eta, 5.0)
    np.testing.assert_allclose(p.fiber, [[0.6, 0.8]] * 3)
    with pytest.raises(ValueError):
        p.mu[0] = 1.0  # read-only
    q = mat.material_params("neo_hookean", E, 0.45, 5.0, [1.0, 0.0])
    np.testing.assert_array_equal(q.eta, 0.0)  # eta only for the fiber model
    sub = p.take(np.array([2, 0]))
    np.testing.assert_array_equal(sub.mu, p.mu[[2, 0]])
    assert sub.model == p.model and sub.tension_only


# --------------------------------------------------------------------------
# 2-D only: the analytic per-term PSD projection (evaluate_projected)
# --------------------------------------------------------------------------


def special_F(M, rng):
    """J > 0 states that stress the closed forms: identity, rotations (incl. a
    half-turn), equal and nearly equal singular values, strong compression,
    stretch, near-incompressible shear; each with random rotations."""
    sigmas = [
        (1.0, 1.0), (0.7, 0.7), (1.3, 1.3), (1.0, 1.0 + 1e-13), (0.8, 0.8 * (1 + 1e-8)),
        (1.1, 1.1 * (1 + 1e-4)), (0.5, 0.6), (0.2, 0.25), (0.3, 1.0), (1.8, 1.3),
        (2.5, 0.4), (1.2, 1.0 / 1.2), (3.0, 3.0), (0.05, 1.0),
    ]
    F = [np.eye(2), -np.eye(2), rotation(0.3), rotation(2.9)]
    while len(F) < M:
        s1, s2 = sigmas[len(F) % len(sigmas)]
        F.append(rotation(rng.uniform(-np.pi, np.pi)) @ np.diag([s1, s2])
                 @ rotation(rng.uniform(-np.pi, np.pi)))
    F = np.array(F[:M])
    # Exactly conformal and exactly diagonal entries too (R = 0, ρ undefined).
    F[4] = 0.8 * np.eye(2)
    F[5] = np.diag([0.6, 0.9])
    F[6] = 1.2 * rotation(1.0)
    assert np.all(mat.jacobian_det(F) > 0.0)
    return F


def state(regime, M, rng):
    return special_F(M, rng) if regime == "special" else random_F(2, M, rng, regime)


def outer_sum(lam, vec):
    """Σ_k lam[e, k] vec[e, k] vec[e, k]ᵀ."""
    return np.einsum("ek,eki,ekj->eij", lam, vec, vec)


REGIMES = ["near", "far", "special"]


@pytest.mark.parametrize("regime", REGIMES)
@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_analytic_eigensystem_reconstructs_tangent(model, tension_only, regime):
    rng = np.random.default_rng(20)
    M = 300
    params = random_params(2, model, M, rng, tension_only)
    F = state(regime, M, rng)
    C = mat.tangent(F, params)
    lam_i, vec_i, lam_f, vec_f = plane_strain_projection._eigensystem(F, params)
    # Orthonormal eigenvectors of each term.
    np.testing.assert_allclose(vec_i @ np.swapaxes(vec_i, 1, 2), np.broadcast_to(np.eye(4), (M, 4, 4)),
                               atol=1e-12)
    np.testing.assert_allclose(vec_f @ np.swapaxes(vec_f, 1, 2), np.broadcast_to(np.eye(2), (M, 2, 2)),
                               atol=1e-12)
    # Σ λ e eᵀ over both terms (unclamped) is the exact tangent.
    assert_close_per_element(outer_sum(lam_i, vec_i) + outer_sum(lam_f, vec_f), C, rtol=1e-10)
    # ... and each eigenpair is one of the isotropic term's tangent.
    iso = without_fiber(params)
    C_iso = mat.tangent(F, iso)
    resid = np.einsum("eij,ekj->eki", C_iso, vec_i) - lam_i[:, :, None] * vec_i
    assert np.abs(resid).max(axis=(1, 2)).max() / per_element_scale(C_iso).min() < 1e-10
    # Twist is ~0 at rest and negative in (volumetric) compression.
    at_rest = np.all(np.abs(F - np.eye(2)) < 1e-15, axis=(1, 2))
    if at_rest.any():
        assert np.abs(lam_i[at_rest, 2]).max() <= 1e-12 * params.kappa.max()


@pytest.mark.parametrize("regime", REGIMES)
@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_fast_path_decomposition_reconstructs_tangent(model, tension_only, regime):
    """The closed forms used by evaluate_projected (rotation/reflection
    parameterisation, invariants, negative parts with the clamp switched off)
    sum back to evaluate's tangent."""
    rng = np.random.default_rng(21)
    M = 300
    params = random_params(2, model, M, rng, tension_only)
    F = state(regime, M, rng)
    C = mat.tangent(F, params)
    _, _, residual = plane_strain_projection._evaluate_projected(F, params, clamp=False)
    assert np.abs(residual).max(axis=(1, 2)).max() <= 1e-10 * per_element_scale(C).min()


@pytest.mark.parametrize("regime", REGIMES)
@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_projected_tangent_is_per_term_psd_projection(model, tension_only, regime):
    rng = np.random.default_rng(22)
    M = 400
    params = random_params(2, model, M, rng, tension_only)
    F = state(regime, M, rng)
    if regime == "near":  # volumetric compression (twist < 0) and expansion
        F = F * rng.uniform(0.9, 1.1, M)[:, None, None]
    # PSD, and only negative parts are removed: Cp − C = −Σ min(λ, 0) e eᵀ is PSD.
    C, Cp, scale = project_and_compare(F, params, psd_rtol=1e-12)
    assert Cp.shape == (M, 4, 4)
    # Σ_k max(λ_k, 0) e_k e_kᵀ per term, from the reference eigensystem.
    lam_i, vec_i, lam_f, vec_f = plane_strain_projection._eigensystem(F, params)
    expected = outer_sum(np.maximum(lam_i, 0.0), vec_i) + outer_sum(np.maximum(lam_f, 0.0), vec_f)
    assert_close_per_element(Cp, expected, rtol=1e-10)
    # Unchanged (bit for bit) where every term is PSD; changed where one is not.
    tol = 1e-9 * scale[:, None]
    psd = np.all(lam_i >= tol, axis=1) & np.all((lam_f >= tol) | (lam_f == 0.0), axis=1)
    indefinite = np.any(lam_i < -tol, axis=1) | np.any(lam_f < -tol, axis=1)
    np.testing.assert_array_equal(Cp[psd], C[psd])
    assert np.all(np.any(Cp[indefinite] != C[indefinite], axis=(1, 2)))
    if regime != "special":
        assert psd.any() and indefinite.any()


@pytest.mark.parametrize("regime", REGIMES)
def test_projected_tangent_matches_project_psd_for_a_single_term(regime):
    """With one energy term (neo-Hookean; or the fiber model with tension_only
    in fiber compression) the per-term projection is project_psd of C."""
    rng = np.random.default_rng(23)
    M = 300
    F = state(regime, M, rng)
    params = random_params(2, "neo_hookean", M, rng)
    C = mat.tangent(F, params)
    _, _, Cp = mat.evaluate_projected(F, params)
    assert_close_per_element(Cp, mat.project_psd(C), rtol=1e-10)

    fib = random_params(2, "neo_hookean_fiber", M, rng, tension_only=True)
    a = fib.fiber
    Fc = (np.eye(2) - 0.3 * a[:, :, None] * a[:, None, :]) @ rotation(rng.uniform(-1, 1, M))
    Fc = rotation(rng.uniform(-np.pi, np.pi, M)) @ Fc @ np.swapaxes(rotation(rng.uniform(-1, 1, M)), 1, 2)
    _, _, Cp = mat.evaluate_projected(Fc, fib)
    assert_close_per_element(Cp, mat.project_psd(mat.tangent(Fc, fib)), rtol=1e-10)


@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_projected_tangent_frame_behaviour(model, tension_only):
    """Like the exact tangent: C(R F) = K C(F) Kᵀ with K = R ⊗ I (spatial
    rotation), and C(F Rᵀ; R a0) = L C(F; a0) Lᵀ with L = I ⊗ R (rotating the
    reference body together with its fiber)."""
    rng = np.random.default_rng(24)
    M = 200
    params = random_params(2, model, M, rng, tension_only)
    F = random_F(2, M, rng, "far")
    F[: M // 2] *= rng.uniform(0.85, 1.0, M // 2)[:, None, None]
    R = random_rotations(2, M, rng)
    K = kron_rotation(R)
    L = np.einsum("ij,ekl->eikjl", np.eye(2), R).reshape(M, 4, 4)
    Kt, Lt = np.swapaxes(K, 1, 2), np.swapaxes(L, 1, 2)
    rotated = with_fiber(params, np.einsum("eij,ej->ei", R, params.fiber))
    Rt = np.swapaxes(R, 1, 2)
    for evaluate in (mat.tangent, lambda G, p: mat.evaluate_projected(G, p)[2]):
        C = evaluate(F, params)
        assert_close_per_element(evaluate(R @ F, params), K @ C @ Kt, rtol=1e-10)
        if model == "neo_hookean_fiber":
            v = np.einsum("eij,ej->ei", F, params.fiber)
            keep = np.abs(np.sum(v * v, axis=1) - 1.0) > 1e-3  # away from the I4 = 1 kink
            assert_close_per_element(evaluate(F[keep] @ Rt[keep], rotated.take(keep)),
                                     L[keep] @ C[keep] @ Lt[keep], rtol=1e-10)


@pytest.mark.parametrize("model,tension_only", NONLINEAR, ids=NONLINEAR_IDS)
def test_projected_invalid_rows_are_finite_psd_without_warnings(model, tension_only):
    rng = np.random.default_rng(26)
    Fs = np.array([
        np.eye(2), np.diag([1.0, -1.0]), np.diag([-0.5, -0.5]), np.zeros((2, 2)),
        [[1.0, 2.0], [0.5, 1.0]], [[0.2, 1.0], [1.0, 0.1]],   # J = 0, J < 0
        np.eye(2) * 1e200, np.eye(2) * 1e-200, np.eye(2) * 1e-7, [[1e300, 0.0], [0.0, -1e300]],
        np.diag([1e100, 1e-100]), np.diag([1e40, 1e-40]), np.diag([1e-13, 1.0]),
        np.full((2, 2), np.nan), np.diag([np.inf, 1.0]), [[0.9, 0.1], [-0.2, 0.8]],
    ])
    M = len(Fs)
    params = random_params(2, model, M, rng, tension_only)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        psi, P, Cp = mat.evaluate_projected(Fs, params)
        psi0, P0, _ = mat.evaluate(Fs, params)
    np.testing.assert_array_equal(psi, psi0)
    np.testing.assert_array_equal(P, P0)
    assert np.all(np.isfinite(Cp))
    np.testing.assert_array_equal(Cp, np.swapaxes(Cp, 1, 2))
    scale = np.maximum(per_element_scale(Cp), 1e-300)
    assert np.all(np.linalg.eigvalsh(Cp / scale[:, None, None])[:, 0] >= -1e-12)
    # Valid rows are unaffected by invalid neighbours.
    with np.errstate(all="ignore"):
        good = np.isfinite(psi) & (mat.jacobian_det(Fs) > 1e-6)
    _, _, Cg = mat.evaluate_projected(Fs[good], params.take(good))
    np.testing.assert_array_equal(Cp[good], Cg)
    assert good.sum() >= 4


def _same(a, b):
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * float(np.max(np.abs(b), initial=0.0)))


def test_projected_scratch_reuse_and_validation():
    """Later calls never write into earlier results (an overwrite would change them by O(1), so they are
    compared to round-off: a reallocated scratch buffer may be aligned differently, and numpy's SIMD
    loops then round differently in the last bit)."""
    rng = np.random.default_rng(27)
    params = random_params(2, "neo_hookean_fiber", 60, rng)
    F = random_F(2, 60, rng, "far")
    before = mat.evaluate(F, params)
    out = mat.evaluate_projected(F, params)
    saved = [a.copy() for a in out]
    # evaluate is unaffected by the grown scratch buffer, and later calls do
    # not write into earlier results.
    for a, b in zip(mat.evaluate(F, params), before):
        _same(a, b)
    mat.evaluate_projected(random_F(2, 500, rng, "near"), random_params(2, "neo_hookean", 500, rng))
    mat.evaluate_projected(F[:5], params.take(slice(0, 5)))
    for a, b in zip(out, saved):
        _same(a, b)
    mat.release_workspace()
    _same(mat.evaluate_projected(F, params)[2], saved[2])
    # Non-contiguous input.
    Ft = np.ascontiguousarray(np.swapaxes(F, 1, 2))
    _same(mat.evaluate_projected(np.swapaxes(Ft, 1, 2), params)[2], saved[2])
    with pytest.raises(ValueError):
        mat.evaluate_projected(F[:-1], params)
    with pytest.raises(ValueError):
        mat.evaluate_projected(F.reshape(-1, 4), params)
    for model in mat.MODELS:
        empty = mat.material_params(model, np.zeros(0) + 10.0, 0.3, 1.0, np.zeros((0, 2)))
        psi, P, C = mat.evaluate_projected(np.zeros((0, 2, 2)), empty)
        assert psi.shape == (0,) and P.shape == (0, 2, 2) and C.shape == (0, 4, 4)
