"""ADMM-PD's per-element weights k_e (kPa): base weights at rest and curvature boosts (docs/model.md §4).

Why per element, and why two parts: ADMM on a non-convex Ψ only converges
when each local problem is convex enough, i.e. k_e clearly above the most
negative eigenvalue of the element tangent C(z_e) = ∂²Ψ/∂F². That
eigenvalue is markedly negative only on the few compressed elements under a
cup. A uniform weight of the order of the tissue's stiffness stalls there
(the iteration falls into a 2-cycle), and the iteration count grows about in
proportion to the weight, so a uniform weight large enough for the worst
element is slow everywhere else.

* Base (`rest_weights`): k0_e = weight_scale · sqrt(λ₂ λ₄) of the element's
  tangent at rest (λ₂ the smallest non-zero eigenvalue — the rotation mode
  is 0 — and λ₄ the largest): the geometric mean of its stiffness range,
  the optimal penalty of ADMM on a quadratic (Ghadimi et al. 2015). The
  solver's default weight_scale 1.0 keeps the final force residual and the
  displacement error at about tol; a smaller scale takes fewer iterations
  but lets the primal test lag, so the final force residual ends above tol.
* Curvature boost (`curvature_boost`, the solver's `adaptive=True`): after
  each local step, every element whose C(z_e) + (k_e/BOOST_TRIGGER) I is not
  positive definite (a row-wise 4×4 Cholesky, cheap) at BOOST_PERSIST
  consecutive iterations gets k_e = min(BOOST_FACTOR · (−λ_min(C(z_e))),
  BOOST_CAP · k0_e) (eigenvalues of those few elements only). The solver
  then rescales the scaled dual to keep the stress k_e u_e, and refactors
  the global matrix (same pattern: a numeric refactorisation, about the
  cost of one iteration). The persistence and the cap matter: without them,
  transient iterates with J → 0 drove k up by orders of magnitude and froze
  those elements. Weights only grow and persist in the solver, so a control
  loop that re-solves nearby strokes stops refactoring after its first
  solves.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.mechanics import materials
from scissor_cli.solvers.admm.local import DIAG, cholesky4

BOOST_TRIGGER = 2.0  # boost when k_e < 2·(−λ_min(C(z_e)))
BOOST_FACTOR = 3.0  # … to k_e = 3·(−λ_min): headroom so the same element rarely triggers twice
BOOST_CAP = 16.0  # k_e <= BOOST_CAP · k0_e
BOOST_PERSIST = 2  # flagged at this many consecutive iterations


def rest_weights(params: materials.MaterialParams) -> np.ndarray:
    """Base stiffness k0 (M,) kPa: sqrt(λ₂ λ₄) of the tangent at F = I (geometric mean of its non-zero range)."""
    M = params.n_elements
    _, _, C = materials.evaluate(np.broadcast_to(np.eye(2), (M, 2, 2)), params, order=2)
    lam = np.linalg.eigvalsh(C)  # (M, 4) ascending; λ₁ = 0 is the rotation mode
    # the floor keeps D_fᵀW²D_f definite should a material have a zero mode besides rotation
    return np.sqrt(np.maximum(lam[:, 1], 1e-3 * lam[:, 3]) * lam[:, 3])


def curvature_boost(
    C: np.ndarray, k: np.ndarray, k0: np.ndarray, flagged: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """The elements whose weight must grow, and their new weights; None if none.

    C (M, 4, 4) kPa: the tangents at the current local z; k (M,) kPa the
    current weights, k0 (M,) kPa the base ones; flagged (M,) int: how many
    consecutive iterations each element has been flagged, updated in place.
    Returns (elements (B,), k_new (B,) kPa) with every k_new > k there. The
    caller sets the weights and rescales the scaled dual.
    """
    H = C.copy()
    H[:, DIAG[0], DIAG[1]] += (k / BOOST_TRIGGER)[:, None]
    _, ok = cholesky4(H)
    flagged[ok] = 0
    if ok.all():
        return None
    flagged[~ok] += 1
    bad = np.flatnonzero(flagged >= BOOST_PERSIST)
    if len(bad) == 0:
        return None
    lam_min = np.linalg.eigvalsh(C[bad])[:, 0]
    k_new = np.minimum(BOOST_FACTOR * np.maximum(-lam_min, 0.0), BOOST_CAP * k0[bad])
    grow = k_new > k[bad]
    if not grow.any():
        return None
    elems, k_new = bad[grow], k_new[grow]
    flagged[elems] = 0
    return elems, k_new
