"""The needle's equilibria on one kept factorisation (docs/model.md §12, "The chord step's arithmetic").

An insertion step solves the tissue with the needle's hold many times: one
active-set pass after another, each with a few captured nodes switched
between stuck and slipping, and the next step barely moves the tissue. So
`ChordSolver` factors the plain K_ff (no needle hold) once and keeps it
across passes and steps; the hold enters as equality constraints on the
captured nodes,

    across the axis for every captured node:  t_j·(x_i − x̄_i) = 0,  j = 1 … d − 1,
    along it for a stuck one:                 n·(x_i − x̄_i) = ride_i,

(x̄ the last equilibrium), through a Schur complement on those few rows:
with K d₀ = −g, W = K⁻¹Cᵀ and S = C W,

    μ = S⁻¹ (C d₀ − r),   d = d₀ − W μ,

so C d = r exactly and K d + Cᵀμ = −g. The responses K⁻¹e of each
captured node's d dofs (d = tissue.dim) are solved once per factorisation
and kept, so switching a node between stuck and slipping costs no
factorisation. In the captured nodes' (t₁ … t_{d−1}, n) frame every row is
one coordinate: S is a submatrix of one kept compliance, Cholesky-factored
once per pass. A step's arithmetic around its solve and gradient runs in
compiled loops (`insertion.kernels`). Converged means Newton's relative
residual with the held components removed (`residual`): the same
equilibrium to the solver tolerance. A step that does not shrink the
residual by CONTRACTION refactors K at the iterate; on a fresh factor
(Newton's step) it is damped on the energy as Newton's line search damps
it (`_damped`), and when that fails too raises `ChordFailed`: Newton next.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

from scissor_cli.insertion import kernels
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.anderson import Anderson
from scissor_cli.solvers.common import Conditions, SolverError, check_finite
from scissor_cli.solvers.linear import factorize_free
from scissor_cli.solvers.newton import ARMIJO

#: a chord step is kept when it shrinks the relative residual at least this much
CONTRACTION = 0.5
#: in 3-D a refactorisation costs dozens of triangular solves and then 3 per captured node for the kept
#: responses (benchmarks/bench_insertion3d.py): a step on the kept factor is kept while it contracts at all
#: appreciably (Anderson-accelerated, `ANDERSON_3D`)
CONTRACTION_3D = 0.9
#: a hold's constraint is met when it is this close (mm): round-off of positions ~100 mm
GAP_TOL = 1e-10
#: chord steps per solve before giving up (the factor fresh); in 3-D more: they contract more slowly there
MAX_CHORD = 40
MAX_CHORD_3D = 80
#: A step on a fresh factorisation (Newton's) that does not contract is damped as Newton damps it: halved
#: up to this many times until Φ falls by Newton's ARMIJO share of its slope (nearly incompressible tissue,
#: where Newton's residual grows on the way), before the solve goes to Newton
DAMPING_HALVINGS = 4
#: In 3-D the chord steps are Anderson-accelerated (type II, this many past steps): on a kept factor of an older
#: state they contract slowly, each a triangular solve (benchmarks/bench_insertion3d.py). It reuses the steps
#: taken (vector work only); the rows stay met (every past step meets them, so Σγ-combinations do). 0 turns it
#: off. The layer keeps the plain steps (a solve there costs about a gradient).
ANDERSON_3D = 5


class ChordFailed(Exception):
    """A chord solve did not converge even on a fresh factorisation: solve with Newton instead."""


class ChordSolver:
    """K_ff factored once and kept, with the needle's hold as Schur-complement constraints.

    factorizations counts the numeric factorisations made (the benchmark's
    evidence); `fresh` says the factor is the exact tangent at the last
    accepted iterate.
    """

    def __init__(self, tissue: Tissue, single_precision: bool | None = None):
        self.tissue = tissue
        #: solve on a float32 copy of the factor (`solvers.supernodal`); None: in 3-D
        self.single_precision = tissue.dim == 3 if single_precision is None else single_precision
        self._factors: dict = {}  # its own slot: other solves refactor the tissue's shared one
        self._factor = None
        self.factorizations = 0
        self.fresh = False
        #: the positions (N, d) the kept factor is the tangent at
        self._factored_at: np.ndarray | None = None
        #: dofs per node
        self.d = tissue.dim
        self._slot = np.full(tissue.mesh.n_nodes, -1, np.int64)
        # K⁻¹e of the kept nodes' dofs as rows (K is symmetric): a row block is contiguous, so a
        # combination of them (a chord step's K⁻¹Cᵀμ, a new pass's K⁻¹g) reads it without a copy
        self._responses = np.zeros((0, tissue.free_dofs.size))
        self._used = 0
        #: (factor key, g, K⁻¹g) of the last gradient solved on the kept factor (`_solve_gradient`)
        self._last_solve = None
        self._responses_memo = None
        self._compliance_memo = None

    # -- the factorisation and its responses -------------------------------------------------------------

    def refactor(self, x: np.ndarray) -> None:
        """Factor K_ff at x (the exact tangent; the per-element PSD projection if that is not positive definite)."""
        factor = None
        for project in (False, True):
            K = self.tissue.stiffness_free(x, project=project, upper=True)
            self.factorizations += 1
            try:
                factor = self._factored(K)
                break
            except SolverError:
                continue
        if factor is None:
            raise SolverError("the needle's chord solver found no positive definite stiffness")
        self._factor, self.fresh = factor, True
        self._factored_at = np.array(x, dtype=float)
        self._slot[:] = -1
        self._used = 0

    def _factored(self, K):
        """K's factor to step on (SolverError: K not positive definite), solved in compiled loops (through cvxopt
        where CHOLMOD's cannot be read in place); in float32, factored in float32 on the first CHOLMOD factor's
        layout (`Factorization.refactor`'s `single`) unless float32 breaks down on K."""
        # simplicial in 2-D: solved about 200 times per factorisation (in 3-D the fill makes supernodal faster)
        factor = factorize_free(self.tissue, K, self._factors, supernodal=self.d == 3 or self.single_precision,
                                single=self.single_precision)
        if self.single_precision:
            return factor.single() or factor
        return (factor.double() or factor) if self.d == 3 else factor  # (float32's floor met: `converge`)

    @property
    def factored(self) -> bool:
        """Whether there is a kept factorisation to step on."""
        return self._factor is not None

    @property
    def _key(self) -> tuple:
        """What the kept factor's derived data (Schur complements, solves) is valid for."""
        return self._factor, self.factorizations

    def responses(self, nodes: np.ndarray) -> np.ndarray:
        """K⁻¹e of each node's d free dofs as rows, (dP, Nf) in the nodes' order; solved once per factorisation.

        A view of the kept rows when the nodes are the ones kept, in their
        order (the captured nodes only grow at the end): no copy per step.
        """
        memo = self._responses_memo
        if memo is not None and memo[0] is nodes and memo[1] == (self._used, self.factorizations):
            return memo[2]  # asked again in the same pass (prediction, completion): nothing has changed
        d = self.d
        missing = nodes[self._slot[nodes] < 0]
        if missing.size:
            fi, nf = self.tissue.free_index, self.tissue.free_dofs.size
            E = np.zeros((nf, d * missing.size))
            k = np.arange(missing.size)
            for c in range(d):  # (d components, not a loop over nodes)
                E[fi[d * missing + c], d * k + c] = 1.0
            need = self._used + E.shape[1]
            if need > self._responses.shape[0]:  # grow the kept rows by doubling
                grown = np.zeros((max(2 * self._responses.shape[0], need, 16), nf))
                grown[:self._used] = self._responses[:self._used]
                self._responses = grown
            self._responses[self._used:need] = self._factor.solve(E).reshape(nf, -1).T
            self._slot[missing] = self._used // d + k
            self._used = need
        s = self._slot[nodes]
        if s.size and s[0] == 0 and s.size * d == self._used and np.all(np.diff(s) == 1):
            R = self._responses[:self._used]
        else:
            R = self._responses[(d * s[:, None] + np.arange(d)).ravel()]
        self._responses_memo = (nodes, (self._used, self.factorizations), R)
        return R

    def compliance(self, nodes: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(idx, A): the nodes' free dofs idx (dP,) as [x₀ y₀ (z₀) x₁ …], and their compliance A (dP, dP) in the frame.

        frame (d, d) has the unit vectors (t₁ … t_{d−1}, n) as columns;
        A = Qᵀ (K⁻¹)[idx, idx] Q with Q = I ⊗ frame, so (2-D) A[2i, 2j+1] is
        node i's t-displacement under a unit n-force on node j. Every constraint row of a hold is one such
        coordinate, so each pass's Schur complement is a submatrix of A.
        """
        memo = self._compliance_memo
        key = (nodes, self._key, self._used, frame.tobytes())
        if memo is not None and memo[0][0] is nodes and memo[0][1:] == key[1:]:
            return memo[1], memo[2]
        fi = self.tissue.free_index
        idx = fi[self.d * nodes[:, None] + np.arange(self.d)].ravel()
        # (K⁻¹)[idx, idx], symmetric (rows or columns alike), turned into the frame; made exactly
        # symmetric, so each Schur complement is
        A = kernels.frame_compliance(self.responses(nodes)[:, idx], frame)
        self._compliance_memo = (key, idx, A)
        return idx, A

    # -- one chord step ----------------------------------------------------------------------------------

    def predict(self, g_free: np.ndarray, hold: "Hold", gap: np.ndarray, shifted: bool = True):
        """The chord step from a state with objective gradient g_free (Nf,) on the free dofs and the hold's gap (m,).

        Returns (d0, μ, d_captured): d0 = −K⁻¹g (Nf,), the constraint forces
        μ (m,) (the needle supplies −Cᵀμ: −μ along each row's direction) and
        the step of the captured nodes (P, d), which meets the hold's rows
        exactly. That is all an active-set decision reads; `complete` gives
        the whole step. In the captured nodes' (t, n) frame every row is one
        coordinate, so with the compliance A there (`compliance`) and the
        rows' coordinates r: S = A[r, r], μ = S⁻¹ (d0[r] − gap) and the
        captured step d0 − A[:, r] μ: only (dP × m) dense work, S factored
        once per pass on one factorisation. `shifted`: g may differ from the
        last solved gradient only on the captured dofs (a new pass), so that
        solve may be reused (`_solve_gradient`).
        """
        if not hold.captured.size:
            return -self._solve_gradient(g_free, None, None), np.zeros(0), np.zeros((0, self.d))
        schur = hold.schur_on(self)
        d0 = -self._solve_gradient(g_free, schur.idx if shifted else None, self.responses(hold.captured))
        mu, d_captured = np.empty(schur.rows.size), np.empty((hold.captured.size, self.d))
        kernels.captured_step(d0, schur.idx, hold.frame, schur.rows, schur.S_upper, schur.A_rows, gap, mu, d_captured)
        return d0, mu, d_captured

    def complete(self, d0: np.ndarray, mu: np.ndarray, d_captured: np.ndarray, hold: "Hold") -> np.ndarray:
        """The whole chord step on the free dofs (Nf,) of a prediction (`predict`): d0 − K⁻¹Cᵀμ.

        The captured nodes take the prediction's own step d_captured (P, d),
        which meets the hold's rows to round-off: d0 − K⁻¹Cᵀμ meets them only
        as well as the kept factor's solves agree with its compliance (float32
        in the slab, `solvers.supernodal`), and a hold must close exactly.
        """
        if mu.size == 0:
            return d0
        d = kernels.chord_direction(d0, hold.rows, mu, hold.frame, self.responses(hold.captured))
        d[hold.schur_on(self).idx] = d_captured.ravel()
        return d

    def step(self, g: np.ndarray, hold: "Hold", x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The whole chord step d (N, d) from x (N, d) with objective gradient g (dN,) under the hold, and μ (m,)."""
        free = self.tissue.free_dofs
        gap = np.empty(hold.rows.size)
        hold.gap_into(x, gap)
        d0, mu, d_captured = self.predict(g[free], hold, gap)
        d = np.zeros(x.size)
        d[free] = self.complete(d0, mu, d_captured, hold)
        check_finite(d, "the needle's chord step")
        return d.reshape(x.shape), mu

    def _solve_gradient(self, g_free: np.ndarray, idx: np.ndarray | None, responses: np.ndarray | None) -> np.ndarray:
        """K⁻¹ g (Nf,) on the kept factor; g_free is kept (the caller's own copy, not changed afterwards).

        A new active-set pass starts where the last one stopped, with only
        the friction loads of the switched nodes changed: when g differs from
        the last solved gradient only on the captured nodes' dofs idx (dP,),
        K⁻¹g is that solve plus their `responses` (dP, Nf), in idx's order.
        """
        last, key = self._last_solve, self._key
        if idx is not None and last is not None and last[0] == key and last[1].shape == g_free.shape:
            delta = g_free - last[1]
            on_nodes = delta[idx]
            delta[idx] = 0.0
            if not delta.any():
                solved = last[2] + on_nodes @ responses
                self._last_solve = (key, g_free, solved)
                return solved
        solved = self._factor.solve(g_free)
        self._last_solve = (key, g_free, solved)
        return solved

    def converge(self, x: np.ndarray, g: np.ndarray, hold: "Hold", tol: float, loads: np.ndarray, decide=None,
                 refactor: bool = True):
        """Chord steps from x (N, d) (gradient g) until the hold's relative residual is ≤ tol.

        Returns (x, g, iterations, verdict). decide(x, d_captured, μ, res),
        asked before each step with that step's prediction at the captured
        nodes (`predict`) and the residual at x, may end the solve early:
        whatever it returns (not None) is the verdict, x is left as it is.
        Refactors when a step does not contract (with `refactor` False it
        raises ChordFailed instead: the caller knows a better state to factor
        at than this iterate); raises ChordFailed when a fresh factorisation
        does not help either (an inverted trial, no contraction, or MAX_CHORD
        steps).
        """
        t = self.tissue
        free = t.free_dofs
        if self._factor is None:
            self.refactor(x)
        elif self.fresh and not np.array_equal(x, self._factored_at):
            # fresh elsewhere (a solve there went to Newton, a start moved): a step that fails here is its age
            self.fresh = False
        g_free = g[free]
        res = hold.held_residual(self, g)
        gap = np.empty(hold.rows.size)
        closing = hold.gap_into(x, gap) > GAP_TOL  # a step that meets the rows: no residual to compare
        its = 0
        accelerate = Anderson(ANDERSON_3D) if self.d == 3 and ANDERSON_3D else None
        while res > tol or closing:
            if its >= (MAX_CHORD if self.d == 2 else MAX_CHORD_3D):
                raise ChordFailed(f"{its} chord steps left the residual at {res:.3g}")
            d0, mu, d_captured = self.predict(g_free, hold, gap, shifted=its == 0)
            # A closing step's prediction errs by what the rows move, not by the residual: no decision on it.
            if decide is not None and not closing:
                verdict = decide(x, d_captured, mu, res)
                if verdict is not None:
                    return x, g, its, verdict
            step = self.complete(d0, mu, d_captured, hold)
            contraction = CONTRACTION if self.d == 2 else CONTRACTION_3D
            trial, g_t, res_t = None, None, np.inf
            if not closing and accelerate is not None:
                x_free = x.reshape(-1)[free]
                accelerated = accelerate.step(x_free + step, step) - x_free
                if accelerate.extrapolating:  # kept if it contracts as a chord step must; else the plain step
                    trial, g_t, res_t = self._trial(x, accelerated, hold, loads)
                    if not (res_t <= contraction * res or res_t <= tol):
                        trial = None
            if trial is None:
                trial, g_t, res_t = self._trial(x, step, hold, loads)
            damped = None
            if not (res_t <= contraction * res or res_t <= tol or (closing and g_t is not None)):
                if self.fresh and self.single_precision and g_t is not None:
                    # float32's floor, not the tangent's: the rest of this solver's solves in float64
                    self.single_precision = False
                elif self.fresh:
                    damped = None if closing else self._damped(x, g_free, step, hold, loads)
                    if damped is None:
                        raise ChordFailed(f"a chord step on a fresh factorisation went from {res:.3g} to {res_t:.3g}")
                elif not refactor:
                    raise ChordFailed(f"a chord step on the kept factorisation went from {res:.3g} to {res_t:.3g}")
                if accelerate is not None:  # its steps were on the old factor, or the last one undamped
                    accelerate.reset()
                if damped is None:
                    self.refactor(x)
                    continue
                trial, g_t, res_t = damped
            x, g, g_free, res = trial, g_t, g_t[free], res_t
            closing = hold.gap_into(x, gap) > GAP_TOL
            self.fresh = False
            its += 1
        return x, g, its, None

    def _damped(self, x: np.ndarray, g_free: np.ndarray, step: np.ndarray, hold: "Hold", loads: np.ndarray):
        """Newton's backtracking along a fresh factorisation's step (Nf,) from x on the hold's rows: the first of
        the whole step, ½, ¼, … (DAMPING_HALVINGS) whose Φ = U − loads·x falls by ARMIJO of its slope, as
        (trial, gradient, residual); None when none does or the step is no descent."""
        slope = float(g_free @ step)
        if not slope < 0.0:
            return None
        phi0 = self.tissue.energy_gradient(x)[0] - float(loads @ x.reshape(-1))
        alpha = 1.0
        for _ in range(DAMPING_HALVINGS + 1):
            trial, finite = kernels.moved(x, self.tissue.free_dofs, alpha * step)
            U_t, g_t = self.tissue.energy_gradient(trial, require_positive_J=True) if finite else (np.inf, None)
            if g_t is not None and U_t - float(loads @ trial.reshape(-1)) <= phi0 + ARMIJO * alpha * slope:
                g_t -= loads
                return trial, g_t, hold.held_residual(self, g_t)
            alpha *= 0.5
        return None

    def _trial(self, x: np.ndarray, step: np.ndarray, hold: "Hold", loads: np.ndarray):
        """x moved by step (Nf,) on the free dofs, its objective gradient (dN,) and held residual (inf, None if
        inverted)."""
        trial, finite = kernels.moved(x, self.tissue.free_dofs, step)
        if not finite:
            raise SolverError("the needle's chord step became non-finite (NaN or inf)")
        _, g_t = self.tissue.energy_gradient(trial, require_positive_J=True)
        if g_t is None:
            return trial, None, np.inf
        g_t -= loads
        return trial, g_t, hold.held_residual(self, g_t)


@dataclass(frozen=True)
class _Schur:
    """A hold's constraints on one factorisation (`ChordSolver.compliance`).

    The captured nodes' free dofs idx (dP,) and held (Nf,) marking them, the
    rows' frame coordinates (m,), A[:, rows] (dP, m) and U (m, m) with
    S = A[rows, rows] = UᵀU in its upper triangle.
    """

    key: tuple
    idx: np.ndarray
    held: np.ndarray
    rows: np.ndarray
    A_rows: np.ndarray
    S_upper: np.ndarray


class Hold:
    """The needle's hold in one pass: captured nodes (P,) at x̄ (P, d), stuck (P,), ride (P,) mm, axis n (d,).

    t: the unit vectors across the axis, (d − 1, d) (`needle.transverse_basis`);
    in 2-D the one vector t (2,) may be given as it is.
    """

    def __init__(self, captured, base, stuck, ride, n, t):
        self.captured, self.base, self.stuck, self.ride = captured, base, stuck, ride
        self.n = np.asarray(n, float)
        #: (d − 1, d) the unit vectors across the axis
        self.t = np.atleast_2d(np.asarray(t, float))
        d = self.n.size
        self.d = d
        #: (d, d) the unit vectors (t₁ … t_{d−1}, n) as columns: a captured node's position → (across…, along)
        #: is v @ frame
        self.frame = np.ascontiguousarray(np.vstack([self.t, self.n]).T)
        #: each constraint row's coordinate in the captured nodes' frame [t₀ … n₀ t₁ … n₁ …]: every node's
        #: d − 1 across ones, then the stuck nodes' n's
        across = (d * np.arange(captured.size)[:, None] + np.arange(d - 1)).ravel()
        self.rows = np.concatenate([across, d * np.flatnonzero(stuck) + d - 1])
        #: the rows on the last factorisation a chord step used (`schur_on`)
        self.schur: _Schur | None = None

    def schur_on(self, solver: ChordSolver) -> "_Schur":
        """The hold's Schur complement on the solver's kept factor: computed once per pass and factorisation."""
        if self.schur is None or self.schur.key != solver._key:
            idx, A = solver.compliance(self.captured, self.frame)
            A_rows = A[:, self.rows]
            S_upper, info = lapack.dpotrf(A_rows[self.rows])
            if info != 0:
                raise SolverError("the needle's hold has dependent constraints (its Schur complement is singular)")
            held = np.zeros(solver.tissue.free_dofs.size, bool)
            held[idx] = True
            self.schur = _Schur(solver._key, idx, held, self.rows, A_rows, S_upper)
        return self.schur

    def directions(self) -> np.ndarray:
        """D (dP, m): each constraint row's unit direction on its node's dofs; the across rows for every captured
        node, then n rows for the stuck.

        The explicit C = DᵀEᵀ. The solver works with the rows' coordinates in
        the (t₁ … n) frame (`rows`) instead; the tests check the two agree.
        """
        d, p = self.d, self.captured.size
        D = np.zeros((d * p, self.rows.size))
        for j, row in enumerate(self.rows):  # (a definition for the tests; m rows, not a hot path)
            k, c = divmod(int(row), d)
            D[d * k:d * k + d, j] = self.frame[:, c]
        return D

    def gap(self, x: np.ndarray) -> np.ndarray:
        """r (m,): how far each constraint is from being met at x (its target minus its value), in `rows`' order.

        Across the axis the target is the offset at capture, along it the ride.
        The definition; the solver uses the compiled `gap_into`, which the tests compare with it.
        """
        target = np.zeros((self.captured.size, self.d))
        target[:, -1] = self.ride
        return (target - (x[self.captured] - self.base) @ self.frame).ravel()[self.rows]

    def gap_into(self, x: np.ndarray, out: np.ndarray) -> float:
        """`gap` written into out (m,) by the compiled loop; returns its largest magnitude (mm)."""
        return kernels.hold_gap(x, self.captured, self.base, self.frame, self.ride, self.rows, out)

    def residual(self, tissue: Tissue, g: np.ndarray) -> float:
        """Newton's relative residual under this hold (`solvers.held.Held.residual`): held components left out.

        The definition; the chord steps use the compiled `held_residual`, which the tests compare with it.
        """
        G = g.reshape(-1, self.d).copy()
        gc = G[self.captured]
        gc -= (gc @ self.t.T) @ self.t
        gc[self.stuck] = 0.0
        G[self.captured] = gc
        return float(np.linalg.norm(G.ravel()[tissue.free_dofs])) / tissue.force_scale(g)

    def held_residual(self, solver: ChordSolver, g: np.ndarray) -> float:
        """`residual` by the compiled loop, with the captured dofs' index kept by the solver's Schur rows."""
        t = solver.tissue
        if not self.captured.size:
            return float(np.linalg.norm(g[t.free_dofs])) / t.force_scale(g)
        schur = self.schur_on(solver)
        return kernels.held_residual(g, t.free_dofs, schur.held, schur.idx, self.n, self.stuck, t.dirichlet_dofs,
                                     t.force_floor)

    def conditions(self, loads: np.ndarray) -> Conditions:
        """The same hold as Newton's `Conditions`: stuck nodes held, slipping ones held across the axis."""
        return hold_conditions(self.captured, self.stuck, self.t, loads)

    def place(self, x: np.ndarray) -> np.ndarray:
        """x (N, d) with the captured nodes moved onto the hold (stuck: ridden along; all: back across the axis)."""
        x = x.copy()
        along = np.where(self.stuck, self.ride, (x[self.captured] - self.base) @ self.n)
        x[self.captured] = self.base + along[:, None] * self.n
        return x


def hold_conditions(captured: np.ndarray, stuck: np.ndarray, t: np.ndarray, loads: np.ndarray | None) -> Conditions:
    """Newton's `Conditions` of a needle's hold: every dof of the stuck nodes (P,) held, the slipping ones
    held across the axis (t (d − 1, d) the unit vectors across it), the loads (dN,) mN."""
    t = np.atleast_2d(t)
    d = t.shape[1]
    stuck_nodes, slip = captured[stuck], captured[~stuck]
    along = np.tile(t[0], (slip.size, 1)) if d == 2 else np.tile(t, (slip.size, 1, 1))
    return Conditions(loads=loads, held=(d * stuck_nodes[:, None] + np.arange(d)).ravel(),
                      along_nodes=slip, along=along)
