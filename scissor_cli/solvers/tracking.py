"""An equilibrium followed as the cup strokes change: what a control loop solves (docs/model.md §5, §6).

Each move starts from the tangent predictor x + (∂x/∂s) Δs and is corrected
by the one Newton iteration of `solvers.newton` with chord steps on the
tracker's last factorisation of K_ff (kept while they shrink the residual ≥
3×, refactored otherwise: same sparsity pattern, numeric work only). When
∂x/∂s is wanted — the controller's Jacobian — it is solved with the exact
tangent at the converged state. In 2-D that tangent is factored there and
is the next move's chord matrix. In 3-D the exact tangent is factored at
the move's predicted start instead (a body's tangent changes too much over
a loop's move for an older factor to carry the chord steps), and ∂x/∂s at
the end is conjugate gradients preconditioned with it (TANGENT_RTOL); the
tangent is factored at the equilibrium only when they do not converge fast.
A tracker that solves to a loose tolerance (KEEP_FACTOR_FROM_TOL: the
trials' controller model) factors at a move's start only when its
factorisation no longer preconditions well. A tracker that does without the
tangent (the truth) keeps its ∂x/∂s as a predictor by Broyden's secant
update from each move instead. Once a few equilibria are known, the
predictor is a polynomial in the strokes (degree ≤ 6, as high as the
history supports, capped after each move at the degree that would have
predicted it best) fitted to the last ones, through their exact tangents too
when the tracker has them: its start residuals are decades below the
tangent predictor's on the small moves of a loop. A move the fast path
cannot finish (the predictor inverts an element, or Newton does not
converge from it) is solved by `solvers.newton.solve_newton` with load
continuation (`_continued`), from the move's start or, when a known
equilibrium (`guesses`) is much nearer in stroke, from that one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from scissor_cli.mechanics import fem
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.common import SolverError, check_finite
from scissor_cli.solvers.linear import (
    KRYLOV_MAX_ITER,
    KRYLOV_STALE_ITER,
    Factorization,
    factorize_free,
    preconditioned_cg,
)
from scissor_cli.solvers.newton import krylov_default, newton_iterations, solve_newton
from scissor_cli.solvers.stroke_polynomial import MAX_DEGREE, highest_degree, lowest_degree, taylor, weights

#: How many of its last equilibria a tracker keeps for the polynomial predictor (`TrackedEquilibrium._fitted`).
HISTORY = 28
#: In 3-D, after each move its predictor's degree is capped for the next at the degree whose fit would have landed
#: nearest the equilibrium reached (`_best_degree`); off, every fit is of the highest degree its history allows (for
#: A/B runs: benchmarks/ab_trials.py). Not in 2-D: a layer's move costs about as much as those fits, and the layer's
#: trials took as many gradients and factorisations either way (tried with ab_trials on paper_trials_prosthesis).
SELECT_DEGREE = True
#: the dofs `_best_degree` compares the fits on: those the move moved most
BEST_DEGREE_DOFS = 64
#: The polynomial predictor serves moves up to this many times the stroke distance of the farthest state it fits.
REACH = 3.0
#: ∂x/∂s solved by conjugate gradients on an earlier factorisation (3-D): to this relative residual of K_ff ∂x/∂s =
#: −K_fc B, far below what the controller's J or the Hermite predictor can tell from the direct solve's; a tracker
#: with a looser tolerance solves it to its own (its states are no more precise than that)
TANGENT_RTOL = 1e-10
#: A 3-D tracker wanting the tangent factors K_ff at each move's predicted start when it solves tighter than this;
#: from this up it goes on with its factorisation while that preconditions well (`_factor_fit`): from the predictor
#: a loose settle is a step or two of CG on an older factor, a tight one needs a fresh factor's fast contraction
#: (benchmarks/ab_trials.py with experiments.body_trials.BODY_MODEL_TOL, docs/performance.md)
KEEP_FACTOR_FROM_TOL = 1e-6


class TrackedEquilibrium:
    """The quasi-static equilibrium of one tissue, followed as the strokes change.

    x (N, 2) mm: node positions at `strokes` (C,) mm. `response` (2N, C) is
    ∂x/∂s (mm/mm) at `tangent_x`, the point where K_ff was last factored
    exactly (the equilibrium itself right after `move_to(..., tangent=True)`);
    after moves without the tangent it is that ∂x/∂s secant-updated by each
    move since (`_secant`): a predictor, not a Jacobian (`jacobian_is_current`
    is False then, as x is no longer `tangent_x`).
    Arrays are replaced, never written in place, so another tracker may
    hold them (see `adopt`). Each tracker keeps its own factorisation slot
    (`factors`), so a model and a truth on the same mesh do not overwrite
    each other's chord matrix.
    """

    def __init__(self, tissue: Tissue, tol: float = 1e-10, max_iter: int = 30):
        self.tissue, self.tol, self.max_iter = tissue, tol, max_iter
        self.x = tissue.rest
        self.strokes = np.zeros(tissue.n_cups)
        self.factors: dict = {}
        self._B = np.column_stack([tissue.cup_displacement(c) for c in range(tissue.n_cups)]
                                  + [np.zeros((tissue.rest.size, 0))])  # (dN, C); C may be 0
        self._cup_elems = np.flatnonzero(np.any(self._B[tissue.ops.elem_dofs] != 0, axis=(1, 2)))
        self.response: Optional[np.ndarray] = None
        self.tangent_x: Optional[np.ndarray] = None
        self.stats = {"moves": 0, "refactors": 0, "fallbacks": 0, "newton_iterations": 0}
        #: the highest degree the next move's polynomial predictor may have, and whether each move sets it
        #: (`_best_degree`; SELECT_DEGREE)
        self.degree_cap, self.select_degree = MAX_DEGREE, SELECT_DEGREE and tissue.dim == 3
        # Known (near-)equilibria (strokes (C,), x (N, 2)) to start a big move from, e.g. the planner's. x may be a
        # function returning it, called whenever a move starts there: a loop's moves are its drives' steps, so it
        # seldom does, and a guess given so costs nothing until then.
        self.guesses: list[tuple[np.ndarray, np.ndarray | Callable[[], np.ndarray]]] = []
        # Its last equilibria (strokes (C,), x (N, 2), the exact ∂x/∂s there or None), oldest first:
        # what the polynomial predictor is fitted to.
        self.history: list[tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]] = []
        # Where the slot's factorisation is the exact K_ff (x (N, d), made by `_factor`), or None when a Newton
        # solve made it (at an iterate this tracker does not know): a restored state refactors there.
        self._factor_x: Optional[np.ndarray] = None
        # After `restore` the factorisation slot holds another state's K_ff: refactor before the next move.
        self._factor_elsewhere: Optional[FactorState] = None
        # ∂x/∂s by conjugate gradients on an earlier factorisation (in 3-D, where factoring dominates a move)
        self._krylov = krylov_default(tissue, None)

    def refactor(self, x: np.ndarray) -> None:
        """Factor the exact K_ff at x (N, d) and compute ∂x/∂s there (docs/model.md §5)."""
        self._tangent(x, iterate=False)

    def _tangent(self, x: np.ndarray, iterate: bool = True) -> None:
        """∂x/∂s (dN, C) at the equilibrium x (N, d): K_ff ∂x_f/∂s = −(K B)_f with the exact tangent K.

        With `iterate` (and `_krylov`) first by conjugate gradients preconditioned with the slot's
        factorisation while that is an exact tangent of this tracker's (`_factor_x`) and not stale; K_ff is
        factored at x when they do not reach TANGENT_RTOL (or the tracker's looser tolerance) within
        `_tangent_iterations` a column.
        """
        t = self.tissue
        Ke = t.element_stiffness(x)
        K = t.stiffness_free(x, Ke=Ke, upper=True)
        rhs = -self._cup_forces(x, Ke)[t.free_dofs] if t.n_cups else np.zeros((t.free_dofs.size, 0))
        solved = self._iterated(K, rhs) if iterate and self._krylov else None
        if solved is None:
            try:
                factor = self._factor(x, K)
            except SolverError:  # not positive definite (an unstable state): LDLᵀ for the response only
                factor = Factorization(K, upper=True)
            solved = self._iterated(K, rhs) if factor.in_float32 else None  # (made to precondition: CG on it)
            solved = factor.solve(rhs) if solved is None else solved
        D = self._B.copy()
        D[t.free_dofs] = solved
        check_finite(D, "the cup response (K_ff singular?)")
        self.response, self.tangent_x = D, x

    def _factor(self, x: np.ndarray, K=None) -> Factorization:
        """Factor the exact K_ff at x (N, d) (its upper triangle K when already assembled) in the slot; SolverError
        when it is not positive definite."""
        t = self.tissue
        self.stats["refactors"] += 1
        self._factor_x, self._factor_elsewhere = x, None
        try:
            return factorize_free(t, t.stiffness_free(x, upper=True) if K is None else K, self.factors,
                                  single=self._krylov)
        except SolverError:
            self._factor_x = None
            raise

    def _factor_exact(self) -> bool:
        """Whether the slot holds this tracker's exact tangent (made by `_factor`), Cholesky-factored."""
        factor = self.factors.get("free")
        return self._factor_x is not None and factor is not None and factor.method == "cholesky"

    def _factor_fit(self) -> bool:
        """Whether the slot's factorisation is fit to precondition: this tracker's exact tangent, not stale (a
        restored state's counts when the one it held was, `_refactor_as` making it again)."""
        held = self._factor_elsewhere
        if held is not None:
            return held.exact and not held.stale
        return self._factor_exact() and not self.factors["free"].stale

    @property
    def _tangent_iterations(self) -> int:
        """CG iterations a column of ∂x/∂s may take before K_ff is factored for it: a Newton step's when the tracker
        keeps its factor (beyond KRYLOV_STALE_ITER it is marked stale for the next move's start), else fewer."""
        return KRYLOV_MAX_ITER if self.tol >= KEEP_FACTOR_FROM_TOL else KRYLOV_STALE_ITER

    def _keeps_factor(self) -> bool:
        """Whether a move goes on with the slot's factorisation, not factoring at its start (KEEP_FACTOR_FROM_TOL)."""
        return self.tol >= KEEP_FACTOR_FROM_TOL and self._factor_fit()

    def _iterated(self, K, rhs: np.ndarray) -> Optional[np.ndarray]:
        """K_ff⁻¹ rhs (Nf, C) by `preconditioned_cg` on the slot's factorisation, or None when it has none fit
        to precondition (not this tracker's exact tangent, stale, another pattern) or a column does not converge."""
        factor = self.factors.get("free")
        if self._factor_elsewhere is not None or not self._factor_fit() or not factor.matches(K):
            return None
        columns = []
        for b in rhs.T:
            d, _, _ = preconditioned_cg(K, b, factor, max(TANGENT_RTOL, self.tol), self._tangent_iterations)
            if d is None:
                return None
            columns.append(d)
        return np.column_stack(columns) if columns else np.zeros_like(rhs)

    def _cup_forces(self, x: np.ndarray, Ke: np.ndarray) -> np.ndarray:
        """K B (dN, C) at x: each cup's unit stroke through the tangent whose element Hessians are Ke."""
        t = self.tissue
        if not t.element.per_element:  # its coupling (the nodal one) reaches beyond the cup's elements
            return np.column_stack([t.stiffness_times(x, self._B[:, c], Ke) for c in range(t.n_cups)])
        # from the elements that touch a cup: B vanishes on every other element's dofs
        e = self._cup_elems
        dofs = t.ops.elem_dofs[e]
        KB_e = np.einsum("eij,ejc->eic", fem.unpack(Ke[:, e]), self._B[dofs])
        return np.stack([np.bincount(dofs.ravel(), weights=KB_e[:, :, c].ravel(), minlength=self._B.shape[0])
                         for c in range(t.n_cups)], axis=1)  # (dN, C): a few cups, not elements

    @property
    def jacobian_is_current(self) -> bool:
        return self.tangent_x is self.x

    def move_to(self, strokes: np.ndarray, tangent: bool = True) -> None:
        """Solve the equilibrium at `strokes` (C,) mm, warm-started from the current one.

        tangent=True also leaves the exact ∂x/∂s at the new equilibrium
        (what the controller's J needs); the truth does without it.
        Raises SolverError if even the load-continuation Newton fails.
        """
        strokes = np.asarray(strokes, float)
        self.stats["moves"] += 1
        if self.response is None:
            self.refactor(self.x)
        if not np.array_equal(strokes, self.strokes):
            # With the tangent wanted (3-D), K_ff is factored at the move's predicted start: its chord steps then
            # contract fast (a loop's move changes a body's tangent enough that one factored at the last
            # equilibrium contracts them by only 0.3-0.8) and ∂x/∂s at the end needs a few CG iterations on it;
            # a loose tracker goes on with a factor that still preconditions well (KEEP_FACTOR_FROM_TOL).
            at_start = tangent and self._krylov and not self._keeps_factor()
            if self._factor_elsewhere is not None and not at_start:  # (restored: the chord steps need its factor)
                self._refactor_as(self._factor_elsewhere)
            fallbacks = self.stats["fallbacks"]
            fitted = self._fitted(strokes - self.strokes)
            x0, s0 = (self.x, self.strokes) if fitted is not None else self._start(strokes)
            x = self._corrected(strokes, x0, s0, fitted, at_start)
            if x is None:
                if self._factor_elsewhere is not None:  # (the predictor inverted an element before it was factored)
                    self._refactor_as(self._factor_elsewhere)
                self.stats["fallbacks"] += 1
                if fitted is not None:  # (the fit starts from the current state) a nearer guess is a shorter path
                    x0, s0 = self._nearest_guess(strokes) or (x0, s0)
                self._factor_x = None
                r = self._continued(strokes, x0, s0)
                x = r.x
                self.stats["refactors"] += r.factorizations
                self.refactor(x)  # the old tangent just failed as a predictor
            if fitted is not None and self.select_degree:
                self.degree_cap = self._best_degree(strokes - self.strokes, x)
            if not tangent and self.stats["fallbacks"] == fallbacks:  # (a fallback left the exact tangent)
                self._secant(x - x0, strokes - s0)
            tangent_here = self.response if self.tangent_x is self.x else None
            self.history = (self.history + [(self.strokes, self.x, tangent_here)])[-HISTORY:]
            self.x, self.strokes = x, strokes.copy()
        if tangent and not self.jacobian_is_current:
            self._tangent(self.x)

    def _continued(self, strokes: np.ndarray, x0: np.ndarray, s0: np.ndarray):
        """`solve_newton`'s load continuation to `strokes` (C,) mm from the move's start (x0, s0): a guess
        nearer in stroke when the move had one (a shorter path, fewer load steps), else the current state, which
        is also where it starts again when the guess's path fails (a guess may be another tissue's state)."""
        try:
            return solve_newton(self.tissue, strokes, x0=x0, strokes0=s0, tol=self.tol, factors=self.factors)
        except SolverError:
            if x0 is self.x:
                raise
        return solve_newton(self.tissue, strokes, x0=self.x, strokes0=self.strokes, tol=self.tol,
                            factors=self.factors)

    def _fitted(self, ds: np.ndarray, cap: Optional[int] = None,
                rows: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
        """The move's increment (2N,) from a polynomial in the strokes fitted to recent equilibria, or None.

        x(s0 + d) ≈ x0 + Σ_{n=1..p} (1/n!) A_n[d, …, d] around the current
        equilibrium x0. With the exact tangent A_1 = ∂x/∂s at x0 (the
        controller's model, which factors it for J at every move) the higher
        terms are fitted to the last equilibria that kept their exact tangent,
        each giving its position and its C tangent columns (Hermite); without
        it (the truth) A_1 is fitted too, to positions only. The degree p is
        the highest ≤ MAX_DEGREE with at most MAX_UNKNOWNS unknowns per dof
        whose equations the history at hand covers (`highest_degree`; with a full
        history, one cup: 6 for both; two cups: 6 with the tangent, 5
        without); the equations are as many as the unknowns with one cup
        (interpolation), a third more with several (a square fit
        extrapolates worse there). The remembered equilibria are converged to
        the solver's tolerance, so on the small moves of a loop each added
        degree still lowers the start residual (two cups, the truth: degree 3
        ~2e-5, degree 5 ~8e-7; the model's Hermite fit ~1e-7). None (the
        tangent predictor is used) without enough history or for a move
        beyond REACH times the farthest fitted state. cap: the highest degree
        (default `degree_cap`, set by the last move: `_best_degree`); rows:
        the dofs predicted (default all; then (len(rows),)).
        """
        C = ds.size
        if C == 0:
            return None
        exact, with_tangent, per_state = self._fit_history()
        fit = highest_degree(C, exact, len(with_tangent) * per_state, self.degree_cap if cap is None else cap)
        if fit is None:
            return None
        E, coefficient, equations = fit
        n_past = -(-equations // per_state)  # ⌈equations / per_state⌉
        past = with_tangent[-n_past:]
        d = np.array([h[0] - self.strokes for h in past])  # (m, C)
        if np.linalg.norm(ds) > REACH * np.max(np.linalg.norm(d, axis=1)):
            return None  # a polynomial extrapolates badly: beyond the history the tangent is safer
        # Each fitted quantity is linear in the remembered ones: the increment is w Y with the weights
        # w (m',) = lstsq(Aᵀ, f(ds)), the rows of pinv(A) f(ds) (A (m', k): the fit's equations), and
        # Y (m', 2N) the fitted data. w Y is formed from the few weights, not from a stacked Y.
        rows = slice(None) if rows is None else rows
        X = np.stack([h[1].ravel()[rows] for h in past])  # (m, 2N)
        x = self.x.ravel()[rows]
        f = taylor(E, coefficient, ds[None])[0]
        if not exact:
            w = weights(taylor(E, coefficient, d), f)
            return w @ X - w.sum() * x
        # Hermite: Y = [positions − x − d Gᵀ; each tangent column c − G_c].
        G = self.response[rows]
        A = np.vstack([taylor(E, coefficient, d)] + [taylor(E, coefficient, d, along=c) for c in range(C)])
        w = weights(A, f)
        w0, wc = w[:len(past)], w[len(past):].reshape(C, len(past))
        T = np.stack([h[2][rows] for h in past])  # (m, 2N, C)
        return (G @ (ds - w0 @ d - wc.sum(axis=1)) + w0 @ X - w0.sum() * x
                + np.matmul(T, wc.T[:, :, None]).sum(axis=0)[:, 0])  # Σ_m T_m wc[:, m], batched

    def _fit_history(self) -> tuple[bool, list, int]:
        """(whether the fit has the exact tangent at x, the remembered states it fits, the equations each gives: its
        position, and with the tangent its C tangent columns)."""
        exact = self.tangent_x is self.x
        with_tangent = [h for h in self.history if h[2] is not None] if exact else self.history
        return exact, with_tangent, 1 + self.strokes.size if exact else 1

    def _best_degree(self, ds: np.ndarray, x: np.ndarray) -> int:
        """The degree whose fit, made before the move ds (C,) mm, lands nearest the equilibrium x (N, d) the move
        reached: the next move's cap. A loop's path is smooth over most of its moves, where the highest degree
        predicts best; where it bends sharply (a body near its cups' rims) the highest degree overshoots by far
        more than a low one, and the next move's path bends alike. Nearest: the largest error over the
        BEST_DEGREE_DOFS dofs the move moved most (where the fits differ; each fit then costs its small
        least-squares solve, not a pass over every dof)."""
        exact, with_tangent, per_state = self._fit_history()
        top = highest_degree(ds.size, exact, len(with_tangent) * per_state)
        if top is None:
            return MAX_DEGREE
        moved = x.ravel() - self.x.ravel()
        rows = np.argpartition(np.abs(moved), -BEST_DEGREE_DOFS)[-BEST_DEGREE_DOFS:] \
            if moved.size > BEST_DEGREE_DOFS else None
        target = moved if rows is None else moved[rows]
        highest, errors = int(top[0].sum(axis=1).max()), {}
        for p in range(lowest_degree(exact), highest + 1):
            increment = self._fitted(ds, cap=p, rows=rows)
            if increment is not None:
                errors[p] = float(np.max(np.abs(increment - target)))
        best = max(errors, key=lambda p: (-errors[p], p)) if errors else highest  # (a tie: the higher degree)
        return MAX_DEGREE if best == highest else best  # (the highest: uncapped, as the history grows)

    def _secant(self, dx: np.ndarray, ds: np.ndarray) -> None:
        """Broyden's update of `response` with a solved move ds (C,) → dx (N, 2): no longer an exact tangent.

        D ← D + (dx − D ds) dsᵀ / dsᵀds makes D reproduce the move just made
        and leaves it unchanged across ds (the cup rows stay B: there dx =
        B ds). Without it a tracker that never asks for the tangent (the
        truth) predicts from wherever it last factored (at the start, the
        rest state): start residuals ~0.1 instead of ~3e-3, two chord steps
        more per move.
        """
        dd = float(ds @ ds)
        if dd > 0:
            self.response = self.response + np.outer(dx.ravel() - self.response @ ds, ds / dd)

    def _start(self, strokes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where a move to `strokes` starts: the current state, or a guess much nearer in stroke.

        A guess gets this tissue's own tangent (one factorisation), so it
        may come from another tissue on the same mesh (the model's state for
        the truth): it is only a starting point. `move_to` asks only when the
        tracker has no polynomial fit of its own for the move: its own
        equilibria predict a loop's small move far better than another
        tissue's state (a slab-truth loop passing the plan's strokes started
        from the nominal slab there at a residual of 1e-1, against 1e-3 from
        its fit, and paid a factorisation for it).
        """
        guess = self._nearest_guess(strokes)
        if guess is not None:
            self.refactor(guess[0])
            return guess
        return self.x, self.strokes

    def _nearest_guess(self, strokes: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """(x, strokes) of the guess nearest in stroke to `strokes` (C,) mm, if it is much nearer than the current
        state (less than half its distance), else None."""
        if not self.guesses:
            return None
        s_g, x_g = min(self.guesses, key=lambda g: np.linalg.norm(g[0] - strokes))
        if np.linalg.norm(s_g - strokes) < 0.5 * np.linalg.norm(self.strokes - strokes):
            return (x_g() if callable(x_g) else x_g), s_g
        return None

    def _corrected(self, strokes: np.ndarray, x0: np.ndarray, s0: np.ndarray,
                   fitted: Optional[np.ndarray] = None, at_start: bool = False) -> Optional[np.ndarray]:
        """Predictor from (x0, s0), then Newton with chord steps; None if that fails.

        The predictor is x0 + `fitted` (2N,) (`_fitted`) when given and it
        inverts no element, else the tangent one x0 + (∂x/∂s) Δs. With
        `at_start` the chord matrix is the exact K_ff factored there.
        """
        t = self.tissue
        for dx in ([fitted] if fitted is not None else []) + [self.response @ (strokes - s0)]:
            start = t.apply_strokes(x0 + dx.reshape(x0.shape), strokes)
            if np.min(t.jacobians(start)) > 0:
                break
        else:
            return None  # the predictor inverts an element
        if at_start:
            try:
                self._factor(start)
            except SolverError:  # (an unstable start: Newton's own steps project its Hessian)
                pass
        before = self._slot_record()
        try:
            r = newton_iterations(t, start, tol=self.tol, max_iter=self.max_iter, chord=True, chord_above=0.0,
                                  factors=self.factors)
        except SolverError:
            r = None
        if self._slot_record() != before:  # Newton factored at an iterate: no longer a known exact tangent
            self._factor_x = None
        if r is None:
            return None
        self.stats["newton_iterations"] += r.iterations
        self.stats["refactors"] += r.factorizations
        return r.x if r.converged else None

    def _slot_record(self) -> tuple:
        """(the slot's factorisation, its numeric factorisations so far): changes whenever it is factored."""
        factor = self.factors.get("free")
        return (id(factor), None if factor is None else factor.factorizations)

    def snapshot(self) -> "TrackerState":
        """This tracker's state at an equilibrium with its exact tangent, to `restore` later (this tracker's own)."""
        if not self.jacobian_is_current:
            raise ValueError("snapshot needs the exact tangent at the equilibrium (move_to(..., tangent=True))")
        if self._factor_elsewhere is not None:  # (restored and not moved since: its factorisation is still owed)
            held = self._factor_elsewhere
        else:
            factor = self.factors.get("free")
            held = FactorState(self.x if self._factor_x is None else self._factor_x,
                               factor is not None and factor.stale, None if factor is None else factor.cg_rate,
                               self._factor_exact())
        return TrackerState(self.x, self.strokes.copy(), self.response, tuple(self.history), held, self.degree_cap)

    def restore(self, state: "TrackerState") -> None:
        """Go back to a `snapshot` of this tracker: from here on it answers exactly as it did after taking it.

        The factorisation is not kept in the state (it is large and CHOLMOD
        overwrites it in place) but where it was made is: the next move factors
        K_ff there again first (`_refactor_as`) — the very factorisation the
        tracker held, so the moves that follow are, bit for bit, the ones it
        would have made.
        """
        self.x, self.strokes, self.response = state.x, state.strokes.copy(), state.response
        self.tangent_x, self.history, self.degree_cap = state.x, list(state.history), state.degree_cap
        self._factor_elsewhere = state.factor

    def _refactor_as(self, held: "FactorState") -> None:
        """The slot's factorisation as a snapshot held it: the exact K_ff at held.x, its CG record with it."""
        try:
            factor = self._factor(held.x)
        except SolverError:  # (as it failed when the state was taken: an unstable state's LDLᵀ was not kept)
            return
        factor.stale, factor.cg_rate = held.stale, held.cg_rate

    def adopt(self, other: "TrackedEquilibrium") -> None:
        """Take another tracker's state of the same tissue (same x, strokes and ∂x/∂s)."""
        self.x, self.strokes = other.x, other.strokes.copy()
        self.response, self.tangent_x = other.response, other.tangent_x
        # Our own factorisation is now at some other state; the next move refreshes it when it matters.


@dataclass(frozen=True)
class FactorState:
    """Where a tracker's factorisation was made (the exact K_ff at x (N, d) mm) and its conjugate-gradient record
    there (`Factorization.stale`, `.cg_rate`): what `TrackedEquilibrium.restore` needs to factor it again."""

    x: np.ndarray
    stale: bool
    cg_rate: Optional[float]
    #: it was the tracker's exact tangent, Cholesky-factored (`TrackedEquilibrium._factor_exact`)
    exact: bool = False


@dataclass(frozen=True)
class TrackerState:
    """A tracker's equilibrium (`TrackedEquilibrium.snapshot`): x (N, d) mm at strokes (C,) mm, ∂x/∂s there
    (dN, C), the history its polynomial predictor fits and where its factorisation was made. Arrays are
    shared, never written."""

    x: np.ndarray
    strokes: np.ndarray
    response: np.ndarray
    history: tuple
    factor: FactorState
    #: the cap on its predictor's next degree (`TrackedEquilibrium.degree_cap`)
    degree_cap: int = MAX_DEGREE
