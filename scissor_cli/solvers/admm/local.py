"""ADMM-PD's local step: min_z Ψ(z) + k_e/2 ‖z − v_e‖² on every element at once (docs/model.md §3, §4).

Shapes and units: z, v (M, 4) vec F (row-major, dimensionless); k (M,) kPa;
Ψ (M,) kPa (energy per unit volume), P (M, 4) kPa, C (M, 4, 4) kPa.

Safeguarded Newton on every element's 4-vector at once: H = C(z) + k I is
factored by a row-wise Cholesky on (M,) component arrays (`cholesky4`),
which beats a batched `np.linalg.solve` on so many 4×4 systems; elements
where H is not positive definite use the PSD-projected C (an
eigen-decomposition of that subset only). A per-element backtracking line
search keeps det z > 0 (Ψ = +inf otherwise) and satisfies Armijo on the
local objective, evaluating only the elements still backtracking.

Warm start: the previous z, whose Ψ, P and C are carried from the last line
search (`LocalCache`), so one Newton step costs one order-2 material
evaluation. The solver takes `local_steps` Newton steps per ADMM iteration
(default 1): the warm-started local problems converge together with ADMM,
and the local optimality is part of the stopping test, so an inexact local
solve cannot stop the iteration early.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scissor_cli.mechanics import materials

IDENTITY = np.array([1.0, 0.0, 0.0, 1.0])  # vec(I), row-major
ARMIJO = 1e-4
DIAG = ([0, 1, 2, 3], [0, 1, 2, 3])  # the diagonal of a stack of 4×4 matrices


@dataclass
class LocalCache:
    """z (M, 4) with Ψ (M,) kPa, P (M, 4) kPa and C (M, 4, 4) kPa evaluated there.

    The local step's warm start: the material values at z come with it, so
    they are evaluated once per accepted z.
    """

    z: np.ndarray
    psi: np.ndarray
    P: np.ndarray
    C: np.ndarray


def evaluate_local(z: np.ndarray, params: materials.MaterialParams) -> LocalCache:
    """The `LocalCache` of z (M, 4): Ψ, P and C of the elements' material (`params`, M elements) at z."""
    psi, P, C = materials.evaluate(z.reshape(-1, 2, 2), params, order=2)
    return LocalCache(z, psi, P.reshape(-1, 4), C)


def det4(z: np.ndarray) -> np.ndarray:
    """det of each vec F (M, 4) → (M,)."""
    return z[:, 0] * z[:, 3] - z[:, 1] * z[:, 2]


def closest_rotation(z: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to each vec F (M, 4): a valid guess where det F ≤ 0."""
    theta = np.arctan2(z[:, 2] - z[:, 1], z[:, 0] + z[:, 3])
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([c, -s, s, c], axis=1)


def cholesky4(H: np.ndarray):
    """Row-wise Cholesky of a stack of symmetric 4×4 H (M, 4, 4).

    Returns the 10 factor rows (l00, l10, l20, l30, l11, l21, l31, l22, l32, l33),
    each (M,), and ok (M,): False where H is not numerically positive definite
    (those rows hold garbage, never used).
    """
    h = H.reshape(-1, 16).T  # row 4i+j is H_ij for all elements
    with np.errstate(all="ignore"):
        ok = h[0] > 0
        l00 = np.sqrt(h[0])
        l10, l20, l30 = h[1] / l00, h[2] / l00, h[3] / l00
        r = h[5] - l10 * l10
        ok &= r > 1e-12 * h[5]
        l11 = np.sqrt(r)
        l21 = (h[6] - l20 * l10) / l11
        l31 = (h[7] - l30 * l10) / l11
        r = h[10] - l20 * l20 - l21 * l21
        ok &= r > 1e-12 * h[10]
        l22 = np.sqrt(r)
        l32 = (h[11] - l30 * l20 - l31 * l21) / l22
        r = h[15] - l30 * l30 - l31 * l31 - l32 * l32
        ok &= r > 1e-12 * h[15]
        l33 = np.sqrt(r)
    return (l00, l10, l20, l30, l11, l21, l31, l22, l32, l33), ok


def cholesky4_solve(L, b: np.ndarray) -> np.ndarray:
    """Solve L Lᵀ d = b for factor rows L (from `cholesky4`) and b (M, 4): d (M, 4)."""
    l00, l10, l20, l30, l11, l21, l31, l22, l32, l33 = L
    with np.errstate(all="ignore"):
        y0 = b[:, 0] / l00
        y1 = (b[:, 1] - l10 * y0) / l11
        y2 = (b[:, 2] - l20 * y0 - l21 * y1) / l22
        y3 = (b[:, 3] - l30 * y0 - l31 * y1 - l32 * y2) / l33
        d3 = y3 / l33
        d2 = (y2 - l32 * d3) / l22
        d1 = (y1 - l21 * d2 - l31 * d3) / l11
        d0 = (y0 - l10 * d1 - l20 * d2 - l30 * d3) / l00
    return np.stack([d0, d1, d2, d3], axis=1)


def _newton_direction(C: np.ndarray, k: np.ndarray, g: np.ndarray) -> np.ndarray:
    """d (M, 4) solving (C + k I) d = −g; PSD-projected C where C + k I is not positive definite."""
    H = C.copy()
    H[:, DIAG[0], DIAG[1]] += k[:, None]
    L, ok = cholesky4(H)
    d = cholesky4_solve(L, -g)
    if not ok.all():
        bad = np.flatnonzero(~ok)
        Hb = materials.project_psd(C[bad]) + k[bad, None, None] * np.eye(4)
        d[bad] = np.linalg.solve(Hb, -g[bad][..., None])[..., 0]
    return d


def _line_search(cache: LocalCache, phi, d, slope, v, k, params) -> LocalCache:
    """Per-element backtracking from cache.z along d (M, 4): det > 0 and Armijo on Ψ + k/2‖z − v‖².

    Elements that find no acceptable step in 40 halvings keep their z.
    """
    # Φ differences below round-off must not reject a (tiny) Newton step near the solution.
    noise = 1e-13 * (np.abs(phi) + 1.0)
    zt = cache.z + d
    trial = evaluate_local(zt, params)
    dv = zt - v
    phit = trial.psi + 0.5 * k * np.einsum("ei,ei->e", dv, dv)
    good = np.isfinite(phit) & (phit <= phi + ARMIJO * slope + noise)
    if good.all():  # the usual case: no copies
        return trial
    out = LocalCache(cache.z.copy(), cache.psi.copy(), cache.P.copy(), cache.C.copy())
    idx = np.arange(len(d))
    alpha = 1.0
    for _ in range(40):
        gi = idx[good]
        out.z[gi], out.psi[gi], out.P[gi], out.C[gi] = zt[good], trial.psi[good], trial.P[good], trial.C[good]
        idx = idx[~good]
        if len(idx) == 0:
            break
        alpha *= 0.5
        zt = cache.z[idx] + alpha * d[idx]
        trial = evaluate_local(zt, params.take(idx))
        dv = zt - v[idx]
        phit = trial.psi + 0.5 * k[idx] * np.einsum("ei,ei->e", dv, dv)
        good = np.isfinite(phit) & (phit <= phi[idx] + ARMIJO * alpha * slope[idx] + noise[idx])
    return out


def local_gradient(cache: LocalCache, v: np.ndarray, k: np.ndarray) -> np.ndarray:
    """g (M, 4) kPa = P(z) + k (z − v): gradient of the local objective per unit volume."""
    return cache.P + k[:, None] * (cache.z - v)


def local_newton(cache: LocalCache, v: np.ndarray, k: np.ndarray, params,
                 steps: int = 1) -> tuple[LocalCache, np.ndarray]:
    """`steps` safeguarded Newton steps on min_z Ψ(z) + k/2 ‖z − v‖², all elements at once.

    cache: the start z (M, 4) (every det > 0) with its Ψ, P, C; v (M, 4);
    k (M,) kPa; params: the elements' material. Returns the new cache and
    the local gradient g (M, 4) kPa there.
    """
    for _ in range(steps):
        g = local_gradient(cache, v, k)
        d = _newton_direction(cache.C, k, g)
        diff = cache.z - v
        phi = cache.psi + 0.5 * k * np.einsum("ei,ei->e", diff, diff)
        slope = np.einsum("ei,ei->e", g, d)
        cache = _line_search(cache, phi, d, slope, v, k, params)
    return cache, local_gradient(cache, v, k)
