"""ADMM-PD on the tissue energy, quasi-static or one implicit-Euler step (docs/model.md §4).

After Overby et al. 2017. The per-element weights are in `admm.weights`, the
local step in `admm.local`, the acceleration in `solvers.anderson`, and time
stepping over a stroke path in `admm.euler`.

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

Large strokes can have several equilibria: ADMM may converge (force
residual ≤ tol) to a different one from Newton's, of lower energy.

Stopping rule (Boyd et al. 2011 §3.3, W-weighted, made relative)
-----------------------------------------------------------------
With r = D x − z (this iteration's x and z) and the change of z:

    primal  ‖W r‖                       ≤ tol · max(‖W (D x − I)‖, ‖W (z − I)‖, 1e-9 ‖W I‖)
    dual    ‖D_fᵀ W² (z_new − z_old)‖   ≤ tol · max(‖D_dᵀ W² u‖, 1e-9 · E_max h L)
    local   ‖W g/k‖                     ≤ tol · max(‖W (D x − I)‖, ‖W (z − I)‖, 1e-9 ‖W I‖)

where g_e = P(z_e) + k_e (z_e − v_e) is the local gradient (kPa), E_max the
largest element modulus (kPa), h the thickness and L the mesh's largest
extent (mm). The primal scale is Boyd's max(‖Ax‖, ‖Bz‖, ‖c‖) written for the
displacement gradient F − I, so a rigid motion or the rest state does not
inflate it; its floor (`STRAIN_FLOOR`) defines "relative" at rest.

The dual test and `solvers.common.relative_residual` (the Newton solver's
and `SolveResult.residual`) share their numerator and their reference force,
not their floor:

* the same: the numerator is the force residual (mN) on the free dofs. When
  the local problems are solved, ∇Φ_f at the z-configuration is
  D_fᵀ W² u_new + inertia = D_fᵀ W² (z_old − z_new). The reference is the
  norm of the Dirichlet reactions (mN): here D_dᵀ W² u, the reactions of
  the stresses k u; there ∇Φ_d at x (`Tissue.force_scale`).
* different: the floor under the reference. Here 1e-9·E_max·h·L, there
  1e-3·E_max·h·L (about the reaction of a 0.1 mm stroke). For reactions
  above 1e-3·E_max·h·L the two divide by the same kind of force; below it
  the dual test is the stricter, by up to 10⁶. Also the dual residual is
  taken at z and u, not at x, and equals the force residual only when the
  local problems are solved (hence the local test).

`SolveResult.history` holds max(primal, dual, local) per iteration;
`SolveResult.residual` is `relative_residual` of the final x, with the
common floor, comparable with Newton's.

Starts
------
Cold (no state): the linear-elastic response of the rest state to the
strokes (rest tangent K0 + M/Δt², factored once on first use — K0 does not
depend on the state, so this is no per-solve factorisation), then z = D x,
u = P(z)/k. Placing a large stroke with the interior at rest inverts the
elements under the cup and sends ADMM into a spurious 2-cycle; the
predictor inverts none there. Warm (a state): its z, u moved by one
linearised step from its x to the new strokes (same K0, the true gradient
at x), k u following P(z). ADMM converges linearly, so a start closer by a
factor c saves only ∝ log c iterations: an exact-tangent predictor (one
factorisation per solve) did not earn its factorisation. A state whose x is
inverted is dropped for a cold start; inverted z of a state are replaced by
their nearest rotations; the message says so.

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
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.admm.local import IDENTITY, LocalCache, closest_rotation, det4, evaluate_local, local_newton
from scissor_cli.solvers.admm.weights import curvature_boost, rest_weights
from scissor_cli.solvers.anderson import Anderson
from scissor_cli.solvers.common import Inertia, SolverError, SolveResult, objective_gradient, relative_residual
from scissor_cli.solvers.linear import Factorization

STRAIN_FLOOR = 1e-9  # primal scale floor (strain), × ‖W I‖: defines "relative" at rest
FORCE_FLOOR = 1e-9  # dual reference floor, × E_max h L (kPa·mm² = mN); relative_residual has 1e-3 (module docstring)


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


class AdmmSolver:
    """ADMM-PD for one tissue (and one Δt): weights and the global factorisation are built once.

    tissue: the discrete tissue; dt_s: implicit-Euler step (s) or None for
    quasi-static solves (then `inertia` must be None, else its dt_s must
    match); weight_scale: multiplies the base weights `rest_weights`;
    adaptive: curvature boosts of the weights (`admm.weights`);
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
        self._GtG = fem.element_matrices(ops, np.broadcast_to(np.eye(4), (len(ops.area), 4, 4)),
                                         scale=np.ones(len(ops.area)))
        self._mass_w = None if dt_s is None else tissue.mass[tissue.free_dofs] / dt_s**2
        self.n_factorizations = 0
        self._factor: Factorization | None = None
        self._factor_global()
        self._K0: Factorization | None = None  # rest tangent (+ M/Δt²) for the predictors, on first use
        self._Ke0: np.ndarray | None = None  # packed rest element Hessians (21, M), for K0 δ
        size = float(np.ptp(tissue.mesh.nodes, axis=0).max())
        self._force_floor = FORCE_FLOOR * float(tissue.element_E_kPa.max()) * ops.thickness_mm * size

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
        cache = evaluate_local(z, self.tissue.params)
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
            # one here, per solver, was slow on fine meshes
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
                P_old = evaluate_local(z, tissue.params).P
                P_new = evaluate_local(z_new, tissue.params).P
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

        cache = evaluate_local(z, params)  # the local warm start, always valid
        anderson = Anderson(self.anderson_memory) if self.anderson_memory else None
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

    def _boost(self, cache: LocalCache):
        """Raise k_e where `curvature_boost` asks for it; refactor. None if nothing changed.

        Returns (elements, k_old/k_new) for rescaling the scaled dual.
        """
        boosted = curvature_boost(cache.C, self.k, self.k0, self._flagged)
        if boosted is None:
            return None
        elems, k_new = boosted
        ratio = self.k[elems] / k_new
        self.k[elems] = k_new
        self._factor_global()
        return elems, ratio


def _norm(a: np.ndarray) -> float:
    return float(np.sqrt(np.vdot(a, a)))
