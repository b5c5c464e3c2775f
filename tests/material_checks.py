"""What the 2-D and 3-D material tests share: the model variants, finite differences, comparisons, and the
states and parameters they draw in either dimension."""

from __future__ import annotations

import itertools
import warnings

import numpy as np

from scissor_cli.mechanics import materials as mat

FD_STEP = 1e-6
RTOL = 1e-6

# (model, tension_only)
VARIANTS = [
    ("linear", False),
    ("neo_hookean", False),
    ("neo_hookean_fiber", False),
    ("neo_hookean_fiber", True),
]
VARIANT_IDS = [f"{m}{'-tension_only' if t else ''}" for m, t in VARIANTS]
NONLINEAR = [v for v in VARIANTS if v[0] != "linear"]
NONLINEAR_IDS = [i for i, v in zip(VARIANT_IDS, VARIANTS) if v[0] != "linear"]


def fiber_I4(F, params):
    """Squared fiber stretch (M,) for F (M, d, d); a 2-component fiber is the in-plane one in 3-D."""
    d = F.shape[1]
    a = params.fiber if params.fiber.shape[1] == d else np.c_[params.fiber, np.zeros(len(params.fiber))]
    v = np.einsum("eij,ej->ei", F, a)
    return np.sum(v * v, axis=1)


def away_from_fiber_kink(F, params):
    """Drop elements with I4 within 1e-3 of 1 (the tension-only tangent jumps there)."""
    keep = np.abs(fiber_I4(F, params) - 1.0) > 1e-3
    return F[keep], params.take(keep)


def fd_gradient(fun, F, h=FD_STEP):
    """Central differences of fun (M, ...) with respect to each entry of vec(F) (row-major), F (M, d, d)."""
    d = F.shape[1]
    cols = []
    for k in range(d * d):
        i, j = divmod(k, d)
        Fp = F.copy()
        Fm = F.copy()
        Fp[:, i, j] += h
        Fm[:, i, j] -= h
        cols.append((fun(Fp) - fun(Fm)) / (2.0 * h))
    return np.stack(cols, axis=-1)


def assert_close_per_element(actual, expected, rtol=RTOL):
    """Relative comparison scaled by each element's largest entry."""
    M = actual.shape[0]
    a = actual.reshape(M, -1)
    e = expected.reshape(M, -1)
    scale = np.maximum(np.abs(e).max(axis=1, keepdims=True), 1e-12)
    err = np.abs(a - e) / scale
    assert err.max() < rtol, f"max relative error {err.max():.3e}"


def per_element_scale(C):
    return np.abs(C).max(axis=(1, 2))


# -- states and parameters, in either dimension (dim 2: plane strain, 3: the 3-D kernels) --


def rotation(theta):
    """2-D rotations by the angles theta."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def random_rotations(dim, M, rng):
    """M random proper rotations (M, dim, dim)."""
    if dim == 2:
        return rotation(rng.uniform(-np.pi, np.pi, M))
    Q, R = np.linalg.qr(rng.standard_normal((M, 3, 3)))
    Q = Q * np.sign(np.diagonal(R, axis1=1, axis2=2))[:, None, :]
    Q[np.linalg.det(Q) < 0, :, 0] *= -1.0
    return Q


def random_fiber(dim, M, rng):
    if dim == 2:
        theta = rng.uniform(-np.pi, np.pi, M)
        return np.c_[np.cos(theta), np.sin(theta)]
    a = rng.standard_normal((M, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def random_params(dim, model, M, rng, tension_only=False, fiber=None):
    # A 2-D fiber is drawn before the moduli and a 3-D one after them, so that each
    # dimension's seeds keep giving the states its tests were written against.
    if fiber is None and dim == 2:
        fiber = random_fiber(2, M, rng)
    E = rng.uniform(5.0, 50.0, M)
    nu = rng.uniform(0.2, 0.49, M)
    eta = rng.uniform(1.0, 20.0, M)
    if fiber is None:
        fiber = random_fiber(dim, M, rng)
    return mat.material_params(model, E_kPa=E, nu=nu, eta_kPa=eta, fiber=fiber, tension_only=tension_only)


def with_fiber(params, fiber):
    return mat.MaterialParams(params.model, params.mu, params.kappa, params.lam, params.eta,
                              fiber, params.tension_only)


def without_fiber(params):
    """The same material without its fiber term."""
    return mat.MaterialParams("neo_hookean", params.mu, params.kappa, params.lam,
                              np.zeros(params.n_elements), params.fiber)


def random_F(dim, M, rng, regime):
    """Random F with J > 0: 'near' I (|F - I| ~ 0.05) or 'far' (R1 diag(λ) R2: stretches λ in
    [0.4, 2.5], arbitrary rotations; large stretch, shear, rotation, compression)."""
    if regime == "near":
        F = np.eye(dim) + 0.05 * rng.standard_normal((M, dim, dim))
    else:
        lam = np.exp(rng.uniform(np.log(0.4), np.log(2.5), (M, dim)))
        F = random_rotations(dim, M, rng) @ (lam[:, :, None] * random_rotations(dim, M, rng))
    assert np.all(mat.jacobian_det(F) > {2: 0.1, 3: 0.05}[dim])
    return F


def kron_rotation(R):
    """K = R ⊗ I (M, d², d²): vec(R G) = K vec(G) for row-major vec."""
    M, d = R.shape[:2]
    return np.einsum("eij,kl->eikjl", R, np.eye(d)).reshape(M, d * d, d * d)


def skew_directions(dim):
    """vec(W) of the infinitesimal rotations W (skew-symmetric), one per coordinate plane."""
    out = []
    for i, j in itertools.combinations(range(dim), 2):
        W = np.zeros((dim, dim))
        W[i, j], W[j, i] = 1.0, -1.0
        out.append(W.ravel())
    return out


def invalid_F(dim):
    """Valid and invalid states; row flags: J <= 0."""
    if dim == 2:
        F = np.broadcast_to(np.eye(2), (6, 2, 2)).copy()
        F[1] = np.diag([1.0, -1.0])  # reflected
        F[2] = np.diag([-0.5, -0.5])  # a half-turn with J = 0.25 > 0: valid
        F[3] = np.zeros((2, 2))  # collapsed, J = 0
        F[4] = [[1.0, 2.0], [0.5, 1.0]]  # J = 0 with shear
        F[5] = [[0.2, 1.0], [1.0, 0.1]]  # J < 0
        return F, np.array([False, True, False, True, True, True])
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


def extreme_F(dim):
    """Overflowing, underflowing and tiny stretches and a huge inverted state; in 3-D also NaN,
    inf and a badly conditioned state (2-D meets those in the projected invalid-rows test)."""
    eye = np.eye(dim)
    F = [eye * 1e200, eye * 1e-200, eye * 1e-7, np.diag([1e300] * (dim - 1) + [-1e300])]
    if dim == 3:
        F += [np.full((3, 3), np.nan), np.diag([np.inf, 1.0, 1.0]), np.diag([1e100, 1e-100, 1.0])]
    return np.array(F)


def project_and_compare(F, params, psd_rtol):
    """evaluate_projected against evaluate: no warnings, the same Ψ and P bit for bit, and a
    symmetric, C-contiguous tangent stack that is PSD and differs from the exact tangent only by
    removed negative parts (Cp − C PSD), both to psd_rtol of each element's scale. Returns
    (C, Cp, scale) for the checks of how each dimension projects."""
    psi0, P0, C = mat.evaluate(F, params)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        psi, P, Cp = mat.evaluate_projected(F, params)
    np.testing.assert_array_equal(psi, psi0)
    np.testing.assert_array_equal(P, P0)
    assert Cp.shape == C.shape and Cp.flags.c_contiguous
    np.testing.assert_array_equal(Cp, np.swapaxes(Cp, 1, 2))
    scale = per_element_scale(C)
    assert np.all(np.linalg.eigvalsh(Cp)[:, 0] >= -psd_rtol * scale)
    assert np.all(np.linalg.eigvalsh(Cp - C)[:, 0] >= -psd_rtol * scale)
    return C, Cp, scale
