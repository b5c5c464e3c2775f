"""The needle's equilibria on one kept factorisation (docs/model.md §12, "Speed").

An insertion step solves the tissue with the needle's hold many times: one
active-set pass after another, each with a few captured nodes switched
between stuck and slipping, and the next step barely moves the tissue. So
`ChordSolver` factors the plain K_ff (no needle hold) once and keeps it
across passes and steps; the hold enters as equality constraints on the
captured nodes,

    across the axis for every captured node:  t·(x_i − x̄_i) = 0,
    along it for a stuck one:                 n·(x_i − x̄_i) = ride_i,

(x̄ the last equilibrium), through a Schur complement on those few rows:
with K d₀ = −g, W = K⁻¹Cᵀ and S = C W,

    μ = S⁻¹ (C d₀ − r),   d = d₀ − W μ,

so C d = r exactly and K d + Cᵀμ = −g. The columns K⁻¹e of each captured
node's two dofs are solved once per factorisation and kept (a newly
captured node adds two), so switching a node between stuck and slipping
costs no factorisation at all. The step is a chord (modified Newton) step:
converged means the same relative residual as Newton's, of the same
gradient with the same held components removed (`residual`), so the
solution is the same equilibrium to the solver tolerance. A chord step that
does not shrink the residual by CONTRACTION refactors K at the current
iterate; a fresh factorisation that still fails raises `ChordFailed` and
the caller falls back to Newton.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.common import Conditions, SolverError, check_finite, objective_gradient
from scissor_cli.solvers.linear import factorize_free

#: a chord step is kept when it shrinks the relative residual at least this much
CONTRACTION = 0.5
#: a hold's constraint is met when it is this close (mm): round-off of positions ~100 mm
GAP_TOL = 1e-10
#: chord steps per solve before giving up (with the factorisation fresh)
MAX_CHORD = 40


class ChordFailed(Exception):
    """A chord solve did not converge even on a fresh factorisation: solve with Newton instead."""


class ChordSolver:
    """K_ff factored once and kept, with the needle's hold as Schur-complement constraints.

    factorizations counts the numeric factorisations made (the benchmark's
    evidence); `fresh` says the factor is the exact tangent at the last
    accepted iterate.
    """

    def __init__(self, tissue: Tissue):
        self.tissue = tissue
        self._factors: dict = {}  # its own slot: other solves refactor the tissue's shared one
        self._factor = None
        self.factorizations = 0
        self.fresh = False
        self._slot = np.full(tissue.mesh.n_nodes, -1, np.int64)
        self._W = np.zeros((tissue.free_dofs.size, 0))
        self._used = 0
        #: (factor key, g, K⁻¹g) of the last gradient solved on the kept factor (`_solve_gradient`)
        self._last_solve = None
        self._columns_memo = None

    # -- the factorisation and its columns ---------------------------------------------------------------

    def refactor(self, x: np.ndarray) -> None:
        """Factor K_ff at x (the exact tangent; the per-element PSD projection if that is not positive definite)."""
        factor = None
        for project in (False, True):
            K = self.tissue.stiffness_free(x, project=project, upper=True)
            self.factorizations += 1
            try:
                # simplicial: a kept factor is solved with about 200 times per factorisation here
                factor = factorize_free(self.tissue, K, self._factors, supernodal=False)
                break
            except SolverError:
                continue
        if factor is None:
            raise SolverError("the needle's chord solver found no positive definite stiffness")
        self._factor, self.fresh = factor, True
        self._slot[:] = -1
        self._used = 0

    def columns(self, nodes: np.ndarray) -> np.ndarray:
        """[K⁻¹e_x K⁻¹e_y] of each node's two free dofs, (Nf, 2P) in the nodes' order; solved once per factorisation.

        A view of the kept columns when the nodes are the ones kept, in their
        order (the captured nodes only grow at the end): no copy per step.
        """
        memo = self._columns_memo
        if memo is not None and memo[0] is nodes and memo[1] == (self._used, self.factorizations):
            return memo[2]  # asked again in the same pass (prediction, completion): nothing has changed
        missing = nodes[self._slot[nodes] < 0]
        if missing.size:
            fi, nf = self.tissue.free_index, self.tissue.free_dofs.size
            E = np.zeros((nf, 2 * missing.size))
            k = np.arange(missing.size)
            E[fi[2 * missing], 2 * k] = 1.0
            E[fi[2 * missing + 1], 2 * k + 1] = 1.0
            need = self._used + E.shape[1]
            if need > self._W.shape[1]:  # grow the kept columns by doubling
                grown = np.zeros((nf, max(2 * self._W.shape[1], need, 16)))
                grown[:, :self._used] = self._W[:, :self._used]
                self._W = grown
            self._W[:, self._used:need] = self._factor.solve(E).reshape(nf, -1)
            self._slot[missing] = self._used // 2 + k
            self._used = need
        s = self._slot[nodes]
        if s.size and s[0] == 0 and s.size * 2 == self._used and np.all(np.diff(s) == 1):
            W = self._W[:, :self._used]
        else:
            W = self._W[:, np.stack([2 * s, 2 * s + 1], axis=1).ravel()]
        self._columns_memo = (nodes, (self._used, self.factorizations), W)
        return W

    # -- one chord step ----------------------------------------------------------------------------------

    def predict(self, g: np.ndarray, hold: "Hold", gap: np.ndarray):
        """The chord step from a state with objective gradient g (2N,) and the hold's gap (m,), at the captured nodes.

        Returns (d0, μ, d_captured): d0 = −K⁻¹g (Nf,), the constraint forces
        μ (m,) (the needle supplies −Cᵀμ: −μ along each row's direction) and
        the step of the captured nodes (P, 2), which meets the hold's rows
        exactly. That is all an active-set decision reads; `complete` gives
        the whole step. With the node columns W (Nf, 2P) and each row's
        direction on its node's two dofs D (2P, m): C = DᵀEᵀ, S = Dᵀ (EᵀW) D,
        only (2P × 2P) dense work, the same for every step of a pass on one
        factorisation.
        """
        t = self.tissue
        nodes = hold.captured
        W = self.columns(nodes)
        key = (self._factor, self.factorizations)
        if nodes.size and (hold.schur is None or hold.schur[0] != key):
            fi = t.free_index
            idx = np.stack([fi[2 * nodes], fi[2 * nodes + 1]], axis=1).ravel()
            D = hold.directions()
            W_nodes = W[idx]
            S_inv = np.linalg.inv(D.T @ W_nodes @ D)  # m ≤ 2P: small, symmetric positive definite
            hold.schur = (key, idx, D, S_inv, W_nodes)
        d0 = -self._solve_gradient(g[t.free_dofs], key, W, hold.schur[1] if nodes.size else None)
        if not nodes.size:
            return d0, np.zeros(0), np.zeros((0, 2))
        _, idx, D, S_inv, W_nodes = hold.schur
        mu = S_inv @ (D.T @ d0[idx] - gap)
        return d0, mu, (d0[idx] - W_nodes @ (D @ mu)).reshape(-1, 2)

    def complete(self, d0: np.ndarray, mu: np.ndarray, hold: "Hold", shape: tuple) -> np.ndarray:
        """The whole chord step d (N, 2) of a prediction (`predict`): d0 − W D μ on the free dofs."""
        t = self.tissue
        d = np.zeros(t.mesh.nodes.size)
        d[t.free_dofs] = d0 if mu.size == 0 else d0 - self.columns(hold.captured) @ (hold.schur[2] @ mu)
        check_finite(d, "the needle's chord step")
        return d.reshape(shape)

    def step(self, g: np.ndarray, hold: "Hold", x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The whole chord step d (N, 2) from x (N, 2) with objective gradient g (2N,) under the hold, and μ (m,)."""
        d0, mu, _ = self.predict(g, hold, hold.gap(x))
        return self.complete(d0, mu, hold, x.shape), mu

    def _solve_gradient(self, g_free: np.ndarray, key, W: np.ndarray, idx: np.ndarray | None) -> np.ndarray:
        """K⁻¹ g (Nf,) on the kept factor; g_free is kept (the caller's own copy, not changed afterwards).

        A new active-set pass starts where the last one stopped, with only
        the friction loads of the switched nodes changed: when g differs from
        the last solved gradient only on the captured nodes' dofs idx, K⁻¹g
        is that solve plus their kept columns (no triangular solve).
        """
        last = self._last_solve
        if idx is not None and last is not None and last[0] == key and last[1].shape == g_free.shape:
            delta = g_free - last[1]
            on_nodes = delta[idx]
            delta[idx] = 0.0
            if not delta.any():
                solved = last[2] + W @ on_nodes
                self._last_solve = (key, g_free, solved)
                return solved
        solved = self._factor.solve(g_free)
        self._last_solve = (key, g_free, solved)
        return solved

    def converge(self, x: np.ndarray, g: np.ndarray, hold: "Hold", tol: float, loads: np.ndarray, decide=None):
        """Chord steps from x (N, 2) (gradient g) until the hold's relative residual is ≤ tol.

        Returns (x, g, iterations, verdict). decide(x, d_captured, μ, res),
        asked before each step with that step's prediction at the captured
        nodes (`predict`) and the residual at x, may end the solve early:
        whatever it returns (not None) is the verdict, x is left as it is.
        Refactors when a step does not contract; raises ChordFailed when a
        fresh factorisation does not help either (an inverted trial, no
        contraction, or MAX_CHORD steps).
        """
        res = hold.residual(self.tissue, g)
        gap = hold.gap(x)
        its = 0
        while res > tol or np.any(np.abs(gap) > GAP_TOL):
            if its >= MAX_CHORD:
                raise ChordFailed(f"{MAX_CHORD} chord steps left the residual at {res:.3g}")
            if self._factor is None:
                self.refactor(x)
            closing = bool(np.any(np.abs(gap) > GAP_TOL))  # a step that meets the rows: no residual to compare
            d0, mu, d_captured = self.predict(g, hold, gap)
            # A closing step's prediction errs by what the rows move, not by the residual: no decision on it.
            if decide is not None and not closing:
                verdict = decide(x, d_captured, mu, res)
                if verdict is not None:
                    return x, g, its, verdict
            trial = x + self.complete(d0, mu, hold, x.shape)
            _, g_t = objective_gradient(self.tissue, trial, None, loads, require_positive_J=True)
            res_t = np.inf if g_t is None else hold.residual(self.tissue, g_t)
            if not (res_t <= CONTRACTION * res or res_t <= tol or (closing and g_t is not None)):
                if self.fresh:
                    raise ChordFailed(f"a chord step on a fresh factorisation went from {res:.3g} to {res_t:.3g}")
                self.refactor(x)
                continue
            x, g, res = trial, g_t, res_t
            gap = hold.gap(x)
            self.fresh = False
            its += 1
        return x, g, its, None


class Hold:
    """The needle's hold in one pass: captured nodes (P,) at x̄ (P, 2), stuck (P,), ride (P,) mm, axis n, t."""

    def __init__(self, captured, base, stuck, ride, n, t):
        self.captured, self.base, self.stuck, self.ride = captured, base, stuck, ride
        self.n, self.t = n, t
        #: ((factor, its count), E's rows, D, S⁻¹, W's rows there) of the last chord step: the same while the factorisation is
        self.schur = None

    def directions(self) -> np.ndarray:
        """D (2P, m): each constraint row's unit direction on its node's (x, y) dofs; t rows for every captured node, then n rows for the stuck."""
        p = self.captured.size
        stuck = np.flatnonzero(self.stuck)
        D = np.zeros((2 * p, p + stuck.size))
        k = np.arange(p)
        D[2 * k, k], D[2 * k + 1, k] = self.t
        j = p + np.arange(stuck.size)
        D[2 * stuck, j], D[2 * stuck + 1, j] = self.n
        return D

    def gap(self, x: np.ndarray) -> np.ndarray:
        """r (m,): how far each constraint is from being met at x (its target minus its value)."""
        rel = x[self.captured] - self.base
        return np.concatenate([-(rel @ self.t), self.ride[self.stuck] - rel[self.stuck] @ self.n])

    def residual(self, tissue: Tissue, g: np.ndarray) -> float:
        """Newton's relative residual under this hold (`newton._Held.residual`): held components left out."""
        G = g.reshape(-1, 2).copy()
        gc = G[self.captured]
        gc -= (gc @ self.t)[:, None] * self.t
        gc[self.stuck] = 0.0
        G[self.captured] = gc
        return float(np.linalg.norm(G.ravel()[tissue.free_dofs])) / tissue.force_scale(g)

    def conditions(self, loads: np.ndarray) -> Conditions:
        """The same hold as Newton's `Conditions`: stuck nodes held, slipping ones held across the axis."""
        stuck, slip = self.captured[self.stuck], self.captured[~self.stuck]
        return Conditions(loads=loads, held=np.concatenate([2 * stuck, 2 * stuck + 1]),
                          along_nodes=slip, along=np.tile(self.t, (slip.size, 1)))

    def place(self, x: np.ndarray) -> np.ndarray:
        """x (N, 2) with the captured nodes moved onto the hold (stuck: ridden along; all: back across the axis)."""
        x = x.copy()
        along = np.where(self.stuck, self.ride, (x[self.captured] - self.base) @ self.n)
        x[self.captured] = self.base + along[:, None] * self.n
        return x
