"""What the 2-D and 3-D material tests share: the model variants, finite differences, comparisons."""

from __future__ import annotations

import numpy as np

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
