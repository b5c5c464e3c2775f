"""ADMM-PD on the tissue energy (Overby et al. 2017; MODEL.md §4): quasi-static or implicit Euler.

Problem and splitting
---------------------
Minimise Φ(x) = U(x) [+ 1/(2Δt²) ‖x − x̃‖²_M] over the free dofs, the
Dirichlet dofs placed by the strokes. With z = D x (one vec F per element,
`fem.reduction_matrix`) and W_e = w_e I₄ the scaled ADMM iteration is

    x ← (M/Δt² + D_fᵀW²D_f)⁻¹ (M/Δt² x̃_f + D_fᵀW² (z − u − D_d x_d))   global, prefactored
    z_e ← argmin_z  hA_e Ψ(z) + w_e²/2 ‖G_e x_e − z + u_e‖²             local, all elements at once
    u ← u + D x − z

(quasi-static: no M/Δt² terms; the fixed boundary keeps D_fᵀW²D_f positive
definite). Shapes: x (N, 2) mm, z and u (M, 4) dimensionless (vec F,
row-major), w_e² = k_e hA_e in µJ with k_e (M,) in kPa. Divided by hA_e the
local problem is  min Ψ(z) + k_e/2 ‖z − v_e‖²,  v = D x + u: scale-free,
and at a solution k_e u_e = P(z_e) — the element's first Piola stress (kPa).

Weights k_e (measured on configs/example.yaml, 2667 elements, tol 1e-4)
-----------------------------------------------------------------------
ADMM on a non-convex Ψ only converges when each local problem is convex
enough, i.e. k_e clearly above the most negative eigenvalue of the element
tangent C(z_e) = ∂²Ψ/∂F². At Newton's solutions min λ(C) = −1.09 κ for
push10 (κ = 33.3 kPa; the elements under the cup, J down to 0.29), −0.22 κ
for pull8 and −3.98 κ for a 20 mm push. Uniform weights k = β κ (adaptive
off), iterations push10 / pull8: β = 1 and 1.5 stall on push10 (a 2-cycle,
residual stuck at 7e-2 / 5e-2 after 1500 iterations), β = 2 / 3 / 4 need
187 / 280 / 373 (iterations grow ∝ β); the 20 mm push fails for all.
A uniform weight large enough for the worst element is slow everywhere
else, so the weights are per element and two-part:

* base: k0_e = weight_scale · sqrt(λ₂ λ₄) of the element's tangent at rest
  (λ₂ the smallest non-zero eigenvalue — the rotation mode is 0 — and λ₄ the
  largest): the geometric mean of its stiffness range, the optimal penalty
  of ADMM on a quadratic (Ghadimi et al. 2015). Here 23.6 kPa = 0.71 κ in
  the tissue, 67 kPa in the vessel (λ = 6.9 … 80.5 kPa with the fiber).
  Adaptive, iterations push10 / pull8 / push20 (Anderson 5 in brackets):
  weight_scale 0.5: 38 / 49 / 231 (31 / 30 / 94) but the final force
  residual is 4e-4 at tol 1e-4 (too small a weight: the primal test lags);
  0.7: 41 / 45 / 278 (28 / 30 / 224); 1.0: 63 / 63 / 308 (29 / 30 / 110);
  1.4: 91 / 91 / 346; 2.0: 131 / 131 / 224. The default 1.0 keeps the
  final force residual and the displacement error at ≈ tol.
* curvature boost (`adaptive=True`): after each local step, every element
  whose C(z_e) + (k_e/2) I is not positive definite (a row-wise 4×4
  Cholesky, cheap) at two consecutive iterations gets
  k_e = min(3 · (−λ_min(C(z_e))), 16 · k0_e) (eigenvalues of those few
  elements only), the scaled dual is rescaled to keep the stress k_e u_e,
  and the global matrix is refactored (same pattern: a CHOLMOD numeric
  refactorisation, ≈ 2 ms ≈ 1 iteration). The persistence and the cap matter: without them
  transient iterates with J → 0 drove k up 10⁵-fold (ν = 0.3, push10) and
  froze those elements. Weights only grow and persist in the solver, so a
  control loop that re-solves nearby strokes stops refactoring after its
  first solves. With `adaptive=False` the matrix is factored exactly once.

The 20 mm push (and configs/hard/compression40, stiff_fibers push10) has
several equilibria: ADMM may converge (force residual ≤ tol) to one with a
lower energy than the one Newton finds from its tangent predictor (20 mm:
24444 µJ vs 25317 µJ, 3.4 mm apart at the free surface beside the cup;
Newton started from the ADMM answer stays there, residual 2e-13).

Local step
----------
Safeguarded Newton on every element's 4-vector at once: H = C(z) + k I by a
row-wise Cholesky on (M,) component arrays (7x faster than batched
`np.linalg.solve` here); elements where H is not positive definite use the
PSD-projected C (eigen-decomposition of that subset only). A per-element
backtracking line search keeps det z > 0 (Ψ = +inf otherwise) and satisfies
Armijo on the local objective, evaluating only the elements still
backtracking. Warm start: the previous z, whose Ψ, P and C are carried from
the last line search, so one Newton step costs one order-2 material
evaluation. `local_steps` Newton steps per ADMM iteration (default 1: the
warm-started local problems converge together with ADMM; the local
optimality is part of the stopping test, so an inexact local solve can not
stop the iteration early).

Stopping rule (Boyd et al. 2011 §3.3, W-weighted, made relative)
-----------------------------------------------------------------
With r = D x − z (this iteration's x and z) and the change of z:

    primal  ‖W r‖                       ≤ tol · max(‖W (D x − I)‖, ‖W (z − I)‖)
    dual    ‖D_fᵀ W² (z_new − z_old)‖   ≤ tol · max(‖D_dᵀ W² u‖, f_floor)
    local   ‖W g/k‖                     ≤ tol · max(‖W (D x − I)‖, ‖W (z − I)‖)

where g_e = P(z_e) + k_e (z_e − v_e) is the local gradient (kPa). The primal
scale is Boyd's max(‖Ax‖, ‖Bz‖, ‖c‖) written for the displacement gradient
F − I, so a rigid motion or the rest state does not inflate it. The dual
residual is exactly the force residual (mN) on the free dofs at the
z-configuration when the local problems are solved (∇Φ_f = D_fᵀ W² u_new +
inertia = D_fᵀ W² (z_old − z_new)), and D_dᵀ W² u are the Dirichlet reactions
(mN) — the same relative measure as `solve.relative_residual`; f_floor is
that function's floor (1e-9·E·h·L); the primal scale likewise has the
floor 1e-9·‖W I‖ (so "relative" is defined at rest). `SolveResult.history` holds
max(primal, dual, local) relative per iteration; `SolveResult.residual` is
`relative_residual` of the final x, comparable with Newton's. On the example
tol = 1e-4 gives a displacement within 1.2e-4 (push10) / 8e-5 (pull8),
relative L2, of Newton's at 1e-10, and a final force residual ≈ 1e-4.

Anderson acceleration (Zhang et al. 2019)
-----------------------------------------
`anderson_memory = m > 0` treats one ADMM iteration as a fixed-point map
G(z, u) (x depends only on z and u) and extrapolates with type-II Anderson
over the last m differences, in the W-weighted norm. Safeguard: the
combined residual ‖W f‖² = ‖W (z' − z)‖² + ‖W (D x − z')‖² of an accelerated
point must be below that of the last accepted point, else the plain ADMM
iterate from that point is taken instead and the history is cleared (also
cleared when the weights change). An accelerated z may have det ≤ 0: the
local step always warm-starts from the last plain z (valid, cached).

Measured (benchmarks/bench_forward.py, example, 2 cores): Anderson with
m = 5 halves the iterations, push10 63 → 29, pull8 63 → 30, for ≈ 15 %
more time per iteration, so ≈ 1.7–2x less time; on configs/hard it helps
most where plain ADMM is slowest (stiff_obstacle push10 1064 → 56,
nearly_incompressible push10 381 → 213, stiff_fibers pull8 580 → 260).
A safeguard rejection is rare on these scenes (0 on push10).

Starts
------
Cold (no state): the linear-elastic response of the rest state to the
strokes (rest tangent K0 + M/Δt², factored once on first use — K0 does not
depend on the state, so this is no per-solve factorisation), then z = D x,
u = P(z)/k. Placing a 10 mm stroke with the interior at rest inverts the
elements under the cup and sends ADMM into a spurious 2-cycle; the
predictor inverts none there. Warm (a state): its z, u moved by one
linearised step from its x to the new strokes (same K0, the true gradient
at x), k u following P(z). From push10, re-solving 0.05 mm / 0.3 mm away
takes 17 / 30 iterations instead of 63 (Anderson: 12 / 18 instead of 29):
ADMM converges linearly, so a start closer by a factor c saves only
∝ log c iterations; an exact-tangent predictor (one factorisation per
solve) did not do much better (14 / 21). A state whose x is inverted is
dropped for a cold start; inverted z of a state are replaced by their
nearest rotations; the message says so.

Speed: one iteration (global solve, local Newton step, residuals) costs
≈ 0.7–0.9 µs per element on the example (2 ms at 2667 elements): the
order-2 material evaluation ≈ 20 %, the 4×4 Cholesky factorisations (Newton
direction and boost test) ≈ 18 %, sparse products and the Cholesky solve
≈ 16 %, the rest elementwise arithmetic on (M, 4) arrays. Newton needs 5–6 iterations (≈ 30 ms) to
1e-10 here; plain ADMM ≈ 110–130 ms to 1e-4, with Anderson ≈ 65 ms.

Failure modes: never NaN silently. Non-finite values raise SolverError; so
does a final x with an inverted element (with the partial SolveResult).
Not converging in max_iter returns converged=False with a message.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp

from scissor_cli.mechanics import fem
from scissor_cli.mechanics import materials
from scissor_cli.solvers.linear import Factorization
from scissor_cli.solvers.common import Inertia, SolveResult, SolverError, objective_gradient, relative_residual
from scissor_cli.mechanics.tissue import Tissue

__all__ = ["AdmmSolver", "AdmmState", "EulerStep", "implicit_euler", "rest_weights", "local_newton"]

IDENTITY = np.array([1.0, 0.0, 0.0, 1.0])  # vec(I), row-major
ARMIJO = 1e-4
BOOST_TRIGGER = 2.0  # boost when k_e < 2·(−λ_min(C(z_e)))
BOOST_FACTOR = 3.0  # … to k_e = 3·(−λ_min): headroom so the same element rarely triggers twice
BOOST_CAP = 16.0  # k_e <= BOOST_CAP · k0_e
BOOST_PERSIST = 2  # flagged at this many consecutive iterations
DIAG = ([0, 1, 2, 3], [0, 1, 2, 3])
STRAIN_FLOOR = 1e-9  # primal scale floor (strain): like relative_residual's force floor, it defines "relative" at rest


@dataclass
class AdmmState:
    """Where an ADMM solve ended, to warm-start the next one.

    x (N, 2) mm positions of the last global step; z (M, 4) the local
    deformation gradients (every det > 0); u (M, 4) the scaled dual, with
    k (M,) kPa the weights it is scaled by (k·u is the element stress).
    """

    x: np.ndarray
    z: np.ndarray
    u: np.ndarray
    k: np.ndarray


@dataclass
class _Cache:
    """z (M, 4) with Ψ (M,) kPa, P (M, 4) kPa and C (M, 4, 4) kPa evaluated there."""

    z: np.ndarray
    psi: np.ndarray
    P: np.ndarray
    C: np.ndarray


def _evaluate(z: np.ndarray, params: materials.MaterialParams) -> _Cache:
    psi, P, C = materials.evaluate(z.reshape(-1, 2, 2), params, order=2)
    return _Cache(z, psi, P.reshape(-1, 4), C)


def det4(z: np.ndarray) -> np.ndarray:
    """det of each vec F (M, 4) → (M,)."""
    return z[:, 0] * z[:, 3] - z[:, 1] * z[:, 2]


def closest_rotation(z: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to each vec F (M, 4): a valid guess where det F ≤ 0."""
    theta = np.arctan2(z[:, 2] - z[:, 1], z[:, 0] + z[:, 3])
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([c, -s, s, c], axis=1)


def rest_weights(params: materials.MaterialParams) -> np.ndarray:
    """Base stiffness k0 (M,) kPa: sqrt(λ₂ λ₄) of the tangent at F = I (geometric mean of its non-zero range)."""
    M = params.n_elements
    _, _, C = materials.evaluate(np.broadcast_to(np.eye(2), (M, 2, 2)), params, order=2)
    lam = np.linalg.eigvalsh(C)  # (M, 4) ascending; λ₁ = 0 is the rotation mode
    # the floor keeps D_fᵀW²D_f definite should a material have a zero mode besides rotation
    return np.sqrt(np.maximum(lam[:, 1], 1e-3 * lam[:, 3]) * lam[:, 3])


def _cholesky4(H: np.ndarray):
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


def _cholesky4_solve(L, b: np.ndarray) -> np.ndarray:
    """Solve L Lᵀ d = b for factor rows L (from `_cholesky4`) and b (M, 4)."""
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
    L, ok = _cholesky4(H)
    d = _cholesky4_solve(L, -g)
    if not ok.all():
        bad = np.flatnonzero(~ok)
        Hb = materials.project_psd(C[bad]) + k[bad, None, None] * np.eye(4)
        d[bad] = np.linalg.solve(Hb, -g[bad][..., None])[..., 0]
    return d


def _line_search(cache: _Cache, phi, d, slope, v, k, params) -> _Cache:
    """Per-element backtracking from cache.z along d (M, 4): det > 0 and Armijo on Ψ + k/2‖z − v‖².

    Elements that find no acceptable step in 40 halvings keep their z.
    """
    # Φ differences below round-off must not reject a (tiny) Newton step near the solution.
    noise = 1e-13 * (np.abs(phi) + 1.0)
    zt = cache.z + d
    trial = _evaluate(zt, params)
    dv = zt - v
    phit = trial.psi + 0.5 * k * np.einsum("ei,ei->e", dv, dv)
    good = np.isfinite(phit) & (phit <= phi + ARMIJO * slope + noise)
    if good.all():  # the usual case: no copies
        return trial
    out = _Cache(cache.z.copy(), cache.psi.copy(), cache.P.copy(), cache.C.copy())
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
        trial = _evaluate(zt, params.take(idx))
        dv = zt - v[idx]
        phit = trial.psi + 0.5 * k[idx] * np.einsum("ei,ei->e", dv, dv)
        good = np.isfinite(phit) & (phit <= phi[idx] + ARMIJO * alpha * slope[idx] + noise[idx])
    return out


def local_gradient(cache: _Cache, v: np.ndarray, k: np.ndarray) -> np.ndarray:
    """g (M, 4) kPa = P(z) + k (z − v): gradient of the local objective per unit volume."""
    return cache.P + k[:, None] * (cache.z - v)


def local_newton(cache: _Cache, v: np.ndarray, k: np.ndarray, params, steps: int = 1) -> tuple[_Cache, np.ndarray]:
    """`steps` safeguarded Newton steps on min_z Ψ(z) + k/2 ‖z − v‖², all elements at once.

    cache: the start z (M, 4) (every det > 0) with its Ψ, P, C; v (M, 4);
    k (M,) kPa. Returns the new cache and the local gradient g (M, 4) there.
    """
    for _ in range(steps):
        g = local_gradient(cache, v, k)
        d = _newton_direction(cache.C, k, g)
        diff = cache.z - v
        phi = cache.psi + 0.5 * k * np.einsum("ei,ei->e", diff, diff)
        slope = np.einsum("ei,ei->e", g, d)
        cache = _line_search(cache, phi, d, slope, v, k, params)
    return cache, local_gradient(cache, v, k)


class _Anderson:
    """Type-II Anderson acceleration of a fixed-point map s ↦ G(s) on flat vectors, weighted norm."""

    def __init__(self, memory: int):
        self.m = memory
        self.reset()

    def reset(self):
        self.dF, self.dG = [], []
        self.f_prev = self.g_prev = None

    def step(self, g: np.ndarray, f: np.ndarray) -> np.ndarray:
        """g = G(s) and the weighted residual f = W (G(s) − s) of an accepted point → the next s."""
        if self.f_prev is not None:
            self.dF.append(f - self.f_prev)
            self.dG.append(g - self.g_prev)
            if len(self.dF) > self.m:
                self.dF.pop(0)
                self.dG.pop(0)
        self.f_prev, self.g_prev = f, g
        if not self.dF:
            return g
        dF = np.stack(self.dF)  # (m, n)
        gram = dF @ dF.T
        # A tiny Tikhonov term keeps nearly dependent differences from blowing up γ.
        gram[np.diag_indices_from(gram)] += 1e-10 * np.trace(gram) + 1e-300
        gamma = np.linalg.solve(gram, dF @ f)
        return g - gamma @ np.stack(self.dG)


class AdmmSolver:
    """ADMM-PD for one tissue (and one Δt): weights and the global factorisation are built once.

    tissue: the discrete tissue; dt_s: implicit-Euler step (s) or None for
    quasi-static solves (then `inertia` must be None, else its dt_s must
    match); weight_scale: multiplies the base weights `rest_weights`;
    adaptive: curvature boosts of the weights (module docstring);
    anderson_memory: 0 = plain ADMM, m > 0 = Anderson with m differences;
    local_steps: Newton steps of the local problems per ADMM iteration.

    Attributes: k0 (M,) kPa base weights; k (M,) kPa current weights
    (w_e² = k_e hA_e, `w2`); n_factorizations — global factorisations so
    far (1 unless curvature boosts refactored).
    """

    def __init__(
        self,
        tissue: Tissue,
        dt_s: float | None = None,
        *,
        weight_scale: float = 1.0,
        adaptive: bool = True,
        anderson_memory: int = 0,
        local_steps: int = 1,
    ):
        if dt_s is not None and not dt_s > 0:
            raise ValueError(f"dt_s must be > 0 or None, got {dt_s}")
        if anderson_memory < 0 or local_steps < 1 or not weight_scale > 0:
            raise ValueError("need anderson_memory >= 0, local_steps >= 1, weight_scale > 0")
        self.tissue = tissue
        self.dt_s = dt_s
        self.adaptive = adaptive
        self.anderson_memory = int(anderson_memory)
        self.local_steps = int(local_steps)
        ops = tissue.ops
        self.k0 = weight_scale * rest_weights(tissue.params)  # (M,) kPa
        self.k = self.k0.copy()
        self._flagged = np.zeros(len(self.k), int)
        D = fem.reduction_matrix(ops)
        self.D_f = D[:, tissue.free_dofs].tocsr()
        self.D_fT = self.D_f.T.tocsr()
        self.D_d = D[:, tissue.dirichlet_dofs].tocsr()
        self.D_dT = self.D_d.T.tocsr()
        # G_eᵀ G_e packed (21, M) in 1/mm²: the element matrices of C = I, unscaled
        self._GtG = fem.element_matrices(ops, np.broadcast_to(np.eye(4), (len(ops.area), 4, 4)), scale=np.ones(len(ops.area)))
        self._mass_w = None if dt_s is None else tissue.mass[tissue.free_dofs] / dt_s**2
        self.n_factorizations = 0
        self._factor: Factorization | None = None
        self._factor_global()
        self._K0: Factorization | None = None  # rest tangent (+ M/Δt²) for the predictors, on first use
        self._Ke0: np.ndarray | None = None  # packed rest element Hessians (21, M), for K0 δ
        size = float(np.ptp(tissue.mesh.nodes, axis=0).max())
        self._force_floor = 1e-9 * float(tissue.element_E_kPa.max()) * ops.thickness_mm * size

    @property
    def w2(self) -> np.ndarray:
        """w_e² = k_e h A_e (M,) in µJ."""
        return self.k * self.tissue.ops.volume

    def _factor_global(self) -> None:
        A = self.tissue.pattern_free_upper.assemble(self._GtG * self.w2)
        if self._mass_w is not None:
            A = A + sp.diags(self._mass_w, format="csr")
        self._factor = Factorization(A, upper=True) if self._factor is None else self._factor.refactor(A)
        self.n_factorizations += 1

    # ------------------------------------------------------------------ starts

    def state_from_positions(self, x: np.ndarray) -> AdmmState:
        """A start (N, 2) → AdmmState with z = D x and u = P(z)/k (the stress x would have at equilibrium).

        Elements with det(D x) ≤ 0 get the nearest rotation instead, so every
        z is valid; x itself is kept as given.
        """
        x = np.asarray(x, float)
        z = fem.deformation_gradients(self.tissue.ops, x).reshape(-1, 4)
        bad = ~(det4(z) > 0)
        if bad.any():
            z[bad] = closest_rotation(z[bad])
        if not np.all(np.isfinite(z)):
            raise SolverError("start positions are not finite")
        cache = _evaluate(z, self.tissue.params)
        return AdmmState(x.copy(), z, cache.P / self.k[:, None], self.k.copy())

    def predictor(self, strokes: np.ndarray, inertia: Inertia | None = None, x: np.ndarray | None = None) -> np.ndarray:
        """One linearised step (N, 2) from x (default: rest) to the strokes, with the rest tangent.

        (K0 + M/Δt²) δx_f = −∇Φ_f(x) − K0_fd δx_d, K0 = ∇²U(rest) factored
        once on first use (the same for every solve, so no refactoring).
        From rest this is the linear-elastic response (the cold start); from
        a previous equilibrium it is a first-order guess of the new one.
        """
        tissue = self.tissue
        free = tissue.free_dofs
        rest = tissue.rest
        if self._K0 is None:
            # the tissue's own upper-triangle pattern: building a full (2N, 2N)
            # one here cost 73 ms per solver at 15.7k elements
            self._Ke0 = tissue.element_stiffness(rest)
            K_ff = tissue.stiffness_free(rest, Ke=self._Ke0, upper=True)
            if self._mass_w is not None:
                K_ff = K_ff + sp.diags(self._mass_w, format="csr")
            self._K0 = Factorization(K_ff, upper=True)
        x = rest if x is None else np.asarray(x, float)
        x_new = tissue.apply_strokes(x, strokes).ravel()
        delta = x_new - x.ravel()
        rhs = -tissue.stiffness_times(rest, delta, self._Ke0)[free]
        if x is not rest or inertia is not None:
            rhs -= objective_gradient(tissue, x, inertia)[1][free]
        x_new[free] += self._K0.solve(rhs)
        return x_new.reshape(-1, 2)

    def _sanitize(self, state: AdmmState) -> AdmmState:
        """A copy of a state with every det z > 0 (nearest rotations, zero dual there) and u scaled to self.k."""
        z = np.array(state.z, float)
        bad = ~(det4(z) > 0)
        z[bad] = closest_rotation(z[bad])
        u = np.array(state.u, float) * (np.asarray(state.k, float) / self.k)[:, None]
        u[bad] = 0.0
        return AdmmState(np.array(state.x, float), z, u, self.k.copy())

    def _warm_start(self, state: AdmmState, strokes: np.ndarray, inertia: Inertia | None):
        """z, u for a warm start: the state's, moved by the linearised response to the new strokes.

        z' = z + D δx and k u' = k u + P(z') − P(z) (the stress follows z); the
        step δx is halved until every det z' > 0 (dropped after two halvings).
        The caller guarantees that state.x has no inverted element.
        """
        tissue = self.tissue
        z, u = state.z, state.u
        step = (self.predictor(strokes, inertia, state.x) - state.x).ravel()
        if not np.all(np.isfinite(step)):
            return z, u
        dz = (self.D_f @ step[tissue.free_dofs] + self.D_d @ step[tissue.dirichlet_dofs]).reshape(z.shape)
        for alpha in (1.0, 0.5, 0.25):
            z_new = z + alpha * dz
            if det4(z_new).min() > 0:
                P_old = _evaluate(z, tissue.params).P
                P_new = _evaluate(z_new, tissue.params).P
                return z_new, u + (P_new - P_old) / self.k[:, None]
        return z, u

    # ------------------------------------------------------------------ solve

    def solve(
        self,
        strokes: np.ndarray,
        state: AdmmState | None = None,
        inertia: Inertia | None = None,
        tol: float = 1e-4,
        max_iter: int = 2000,
        callback: Callable[[int, dict], None] | None = None,
    ) -> tuple[SolveResult, AdmmState]:
        """Equilibrium (or one implicit-Euler step with `inertia`) for cup strokes (C,) mm.

        state: warm start (a previous solve's state); None starts from the
        linear-elastic predictor. tol: relative tolerance of the stopping
        rule (module docstring). callback(iteration, info) with info keys
        primal, dual, local (relative), accelerated (bool), boosted (int).
        Returns (SolveResult with solver="admm", AdmmState).
        """
        t0 = time.perf_counter()
        tissue = self.tissue
        self._check_inertia(inertia)
        if max_iter < 1 or not tol >= 0:
            raise ValueError(f"need max_iter >= 1 and tol >= 0, got {max_iter}, {tol}")
        strokes = np.atleast_1d(np.asarray(strokes, float))
        M = tissue.mesh.n_elements
        free, params = tissue.free_dofs, tissue.params
        note = ""
        if state is not None and not tissue.jacobians(state.x).min() > 0:
            n_bad = int(np.sum(~(tissue.jacobians(state.x) > 0)))
            note = f"warm start had {n_bad} inverted element(s) in x: cold start instead; "
            state = None
        if state is None:
            state = self.state_from_positions(self.predictor(strokes, inertia))
        else:
            n_bad = int(np.sum(~(det4(state.z) > 0)))
            if n_bad:
                note = f"warm start had {n_bad} inverted z: replaced by their nearest rotations; "
            state = self._sanitize(state)
            z, u = self._warm_start(state, strokes, inertia)
            state = AdmmState(state.x, z, u, self.k)
        z, u = state.z, state.u
        x = tissue.apply_strokes(state.x, strokes).ravel()  # Dirichlet dofs fixed for this solve
        Ddxd = (self.D_d @ x[tissue.dirichlet_dofs]).reshape(M, 4)
        rhs_inertia = 0.0 if inertia is None else inertia.weight[free] * inertia.x_tilde[free]

        cache = _evaluate(z, params)  # the local warm start, always valid
        anderson = _Anderson(self.anderson_memory) if self.anderson_memory else None
        accelerated = False
        best = np.inf  # combined residual of the last accepted point (Anderson safeguard)
        default_zu = default_cache = None  # plain iterate from the last accepted point, its local cache
        history: list[float] = []
        converged, message = False, ""
        x_f = x[free]
        it = 0
        for it in range(1, max_iter + 1):
            w2 = self.w2[:, None]
            sw = np.sqrt(w2)
            # global step
            x_f = self._factor.solve(self.D_fT @ (w2 * (z - u - Ddxd)).ravel() + rhs_inertia)
            if not np.all(np.isfinite(x_f)):
                message = "the global step became non-finite"
                break
            Dx = (self.D_f @ x_f).reshape(M, 4) + Ddxd
            v = Dx + u
            # local step (warm start: the last plain z, whose material values are cached)
            cache, g = local_newton(cache, v, self.k, params, self.local_steps)
            if not np.all(np.isfinite(cache.z)):
                message = "the local step became non-finite"
                break
            z_new = cache.z
            r = Dx - z_new
            u_new = u + r
            # residuals (module docstring)
            pri_scale = max(_norm(sw * (Dx - IDENTITY)), _norm(sw * (z_new - IDENTITY)), STRAIN_FLOOR * _norm(sw))
            primal = _norm(sw * r) / pri_scale
            local = _norm(sw * g / self.k[:, None]) / pri_scale
            reaction = _norm(self.D_dT @ (w2 * u_new).ravel())
            dual = _norm(self.D_fT @ (w2 * (z_new - z)).ravel()) / max(reaction, self._force_floor)
            history.append(max(primal, dual, local))
            combined = _norm(sw * (z_new - z)) ** 2 + _norm(sw * r) ** 2
            info = {"primal": primal, "dual": dual, "local": local, "accelerated": accelerated, "boosted": 0}
            if history[-1] <= tol:
                z, u = z_new, u_new
                converged = True
                if callback is not None:
                    callback(it, info)
                break
            if not np.isfinite(history[-1]):
                message = "a residual became non-finite"
                break
            boosted = self._boost(cache) if self.adaptive else None
            if boosted is not None:
                ratio = boosted[1]  # k_old / k_new on the boosted elements
                u_new[boosted[0]] *= ratio[:, None]
                info["boosted"] = len(boosted[0])
                if anderson is not None:
                    anderson.reset()
                    best, accelerated = np.inf, False
                z, u = z_new, u_new
            elif anderson is None:
                z, u = z_new, u_new
            elif accelerated and combined >= best:
                # safeguard: the accelerated point did worse than the plain iterate would have;
                # the plain iterate's local warm start goes with it
                (z, u), cache = default_zu, default_cache
                anderson.reset()
                accelerated = False
                info["rejected"] = True
            else:
                best = combined
                default_zu, default_cache = (z_new, u_new), cache
                s_new = anderson.step(
                    np.concatenate([z_new.ravel(), u_new.ravel()]),
                    np.concatenate([(sw * (z_new - z)).ravel(), (sw * r).ravel()]),
                )
                z, u = s_new[: 4 * M].reshape(M, 4), s_new[4 * M :].reshape(M, 4)
                accelerated = True
            if callback is not None:
                callback(it, info)

        if not converged and not message:
            z, u = z_new, u_new  # the last plain iterate: every det z > 0, unlike an extrapolated one
        x[free] = x_f
        xx = x.reshape(-1, 2)
        partial = SolveResult(xx, False, it, np.nan, time.perf_counter() - t0, "admm", "", history)
        if message:  # something became non-finite
            partial.message = note + message
            raise SolverError(partial.message, partial)
        J = tissue.jacobians(xx)
        if not J.min() > 0:
            partial.message = note + (
                f"{int(np.sum(~(J > 0)))} element(s) of x inverted after {it} iterations "
                f"(min J = {J.min():.3g}, last relative residual {history[-1]:.3g})"
            )
            raise SolverError(partial.message, partial)
        partial.residual = relative_residual(tissue, objective_gradient(tissue, xx, inertia)[1])
        if not np.isfinite(partial.residual):
            partial.message = note + "the final force residual is not finite"
            raise SolverError(partial.message, partial)
        if converged:
            message = f"converged in {it} iterations"
        else:
            message = f"not converged in {max_iter} iterations (relative ADMM residual {history[-1]:.3g} > {tol:g})"
        elapsed = time.perf_counter() - t0
        result = SolveResult(xx, converged, it, partial.residual, elapsed, "admm", note + message, history)
        return result, AdmmState(xx, z, u, self.k.copy())

    def _check_inertia(self, inertia: Inertia | None) -> None:
        if inertia is None and self.dt_s is not None:
            raise ValueError(f"this AdmmSolver was built for implicit Euler (dt_s = {self.dt_s}); pass inertia")
        if inertia is not None and (self.dt_s is None or not np.isclose(inertia.dt_s, self.dt_s, rtol=1e-12)):
            raise ValueError(
                f"inertia.dt_s = {inertia.dt_s} but this AdmmSolver was factored for dt_s = {self.dt_s}; "
                "build an AdmmSolver(tissue, dt_s=...) for that step"
            )

    def _boost(self, cache: _Cache):
        """Raise k_e where C(z_e) + k_e/BOOST_TRIGGER I is indefinite; refactor. None if nothing changed.

        Returns (elements, k_old/k_new) for rescaling the scaled dual.
        """
        H = cache.C.copy()
        H[:, DIAG[0], DIAG[1]] += (self.k / BOOST_TRIGGER)[:, None]
        _, ok = _cholesky4(H)
        self._flagged[ok] = 0
        if ok.all():
            return None
        self._flagged[~ok] += 1
        bad = np.flatnonzero(self._flagged >= BOOST_PERSIST)
        if len(bad) == 0:
            return None
        lam_min = np.linalg.eigvalsh(cache.C[bad])[:, 0]
        k_new = np.minimum(BOOST_FACTOR * np.maximum(-lam_min, 0.0), BOOST_CAP * self.k0[bad])
        grow = k_new > self.k[bad]
        if not grow.any():
            return None
        elems, k_new = bad[grow], k_new[grow]
        self._flagged[elems] = 0
        ratio = self.k[elems] / k_new
        self.k[elems] = k_new
        self._factor_global()
        return elems, ratio


def _norm(a: np.ndarray) -> float:
    return float(np.sqrt(np.vdot(a, a)))


# ---------------------------------------------------------------------- dynamics


@dataclass
class EulerStep:
    """One implicit-Euler step: time t_s (s), strokes (C,) mm, x (N, 2) mm, v (N, 2) mm/s, and how it was solved."""

    t_s: float
    strokes: np.ndarray
    x: np.ndarray
    v: np.ndarray
    result: SolveResult
    state: AdmmState


def implicit_euler(
    tissue: Tissue,
    solver: AdmmSolver,
    strokes_path: np.ndarray,
    dt_s: float,
    x0: np.ndarray,
    v0: np.ndarray,
    f_ext: np.ndarray | None = None,
    tol: float = 1e-4,
    max_iter: int = 2000,
) -> list[EulerStep]:
    """Step MODEL §4 with ADMM along strokes_path (S, C) mm: S steps of dt_s from x0, v0 (N, 2).

    x̃ = x_n + Δt v_n + Δt² M⁻¹ f_ext (f_ext (2N,) mN, default none);
    v_{n+1} = (x_{n+1} − x_n)/Δt. Each step warm-starts from the previous
    one. A step that does not converge raises SolverError (with its result).
    """
    if solver.tissue is not tissue:
        raise ValueError("the solver was built for another tissue")
    if solver.dt_s is None or not np.isclose(solver.dt_s, dt_s, rtol=1e-12):
        raise ValueError(f"the solver was built for dt_s = {solver.dt_s}, not {dt_s}")
    path = np.asarray(strokes_path, float).reshape(len(strokes_path), -1)
    x, v = np.array(x0, float), np.array(v0, float)
    state = solver.state_from_positions(x)
    steps = []
    for n, s in enumerate(path):
        x_tilde = (x + dt_s * v).ravel()
        if f_ext is not None:
            x_tilde = x_tilde + dt_s**2 * np.asarray(f_ext, float) / tissue.mass
        result, state = solver.solve(s, state, Inertia(dt_s, x_tilde, tissue.mass), tol=tol, max_iter=max_iter)
        if not result.converged:
            raise SolverError(f"implicit Euler step {n + 1}: {result.message}", result)
        v = (result.x - x) / dt_s
        x = result.x
        steps.append(EulerStep((n + 1) * dt_s, s.copy(), x, v, result, state))
    return steps
