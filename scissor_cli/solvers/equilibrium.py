"""The one entry point for equilibria of the tissue (docs/model.md §4).

Every caller that needs the tissue at rest under given cup strokes — the
forward cases, the needle planner, the trials' warm starts, the solver study
and the accuracy-driven selection — calls `solve_equilibrium` or keeps an
`EquilibriumSolver` when it solves the same tissue many times (it keeps the
ADMM's prefactored matrix; Newton's symbolic factorisation lives on the
tissue). The controller's incremental tracker (`solvers.tracking`) runs the
same Newton iteration.

What a solve holds and pushes beyond the tissue's fixed sides and cups —
external loads, dofs a needle holds — is a `Conditions` input, not a
subclass of anything.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from scissor_cli.config import SolverConfig
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.common import NO_CONDITIONS, Conditions, Inertia, SolverError, SolveResult
from scissor_cli.solvers.newton import solve_newton

METHODS = ("newton", "admm")
#: Newton's default relative residual: the exact reference
NEWTON_TOL = 1e-10
#: ADMM's default relative residual (docs/model.md §4: the paper's solver, approximate)
ADMM_TOL = 1e-4


@dataclass
class EquilibriumSolver:
    """Solves equilibria of one tissue with one method, keeping what carries over between solves.

    method: "newton" (the exact reference) or "admm" (the paper's ADMM-PD);
    tol, max_iter: the method's relative residual and iteration cap (None:
    NEWTON_TOL / 100 for Newton, ADMM_TOL / 2000 for ADMM); anderson_memory:
    ADMM's Anderson acceleration (0 = off). How `solve_case` reaches a
    forward case: dt_s (s) None for a quasi-static solve, else implicit Euler
    with `settle_steps` after the ramp; initial_guess "rest" or "mirrored".
    """

    tissue: Tissue
    method: str = "newton"
    tol: float | None = None
    max_iter: int | None = None
    anderson_memory: int = 0
    dt_s: float | None = None
    settle_steps: int = 20
    initial_guess: str = "rest"
    _admm: object = field(default=None, init=False, repr=False)
    _admm_state: object = field(default=None, init=False, repr=False)

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.tol is None:
            self.tol = NEWTON_TOL if self.method == "newton" else ADMM_TOL
        if self.max_iter is None:
            self.max_iter = 100 if self.method == "newton" else 2000

    @classmethod
    def from_config(cls, tissue: Tissue, solver_cfg: SolverConfig) -> "EquilibriumSolver":
        """The solver a config's `solver` section asks for."""
        case = dict(dt_s=solver_cfg.dt_s, settle_steps=solver_cfg.steps, initial_guess=solver_cfg.initial_guess)
        if solver_cfg.kind == "newton":
            return cls(tissue, "newton", solver_cfg.newton_tolerance, solver_cfg.newton_max_iterations, **case)
        return cls(tissue, "admm", solver_cfg.tolerance, solver_cfg.max_iterations, solver_cfg.anderson_memory, **case)

    def solve_case(self, strokes: np.ndarray) -> SolveResult:
        """A forward case as configured: quasi-static from the configured start, or implicit Euler."""
        if self.dt_s is not None:
            return self.solve_dynamic(strokes, self.dt_s, self.settle_steps)
        if self.initial_guess == "mirrored":
            return self.solve(strokes, mirrored_start(self.tissue), np.zeros_like(np.asarray(strokes, float)))
        return self.solve(strokes)

    def solve(
        self,
        strokes: np.ndarray,
        start: np.ndarray | None = None,
        start_strokes: np.ndarray | None = None,
        conditions: Conditions = NO_CONDITIONS,
        inertia: Inertia | None = None,
        continue_previous: bool = False,
        factors: dict | None = None,
    ) -> SolveResult:
        """The equilibrium (or one implicit-Euler step) for cup strokes (C,) mm.

        start (N, 2): warm start, an equilibrium at start_strokes (C,) (None:
        the rest state, or — if start_strokes is None too — any guess, which
        Newton replaces by rest when it is inverted). continue_previous: ADMM
        goes on from the last solve's full state (its z and u, not only x),
        so a tighter tolerance continues the same iteration. factors: Newton's
        factorisation slot (a dict the solve keeps its factors in; None: the
        tissue's own cache). Raises SolverError when the method does not
        converge (with the partial result).
        """
        strokes = np.asarray(strokes, float)
        if self.method == "newton":
            return solve_newton(self.tissue, strokes, x0=start, strokes0=start_strokes, inertia=inertia,
                                tol=self.tol, max_iter=self.max_iter, conditions=conditions, factors=factors)
        if not conditions.trivial:
            raise ValueError("the ADMM solver takes no external loads or held dofs: use method 'newton'")
        if factors is not None:
            raise ValueError("a factorisation slot is Newton's: the ADMM solver keeps its own factor")
        solver = self._admm_for(inertia)
        if continue_previous and self._admm_state is not None:
            state = self._admm_state
        else:
            state = None if start is None else solver.state_from_positions(start)
        result, self._admm_state = solver.solve(strokes, state=state, inertia=inertia, tol=self.tol,
                                                max_iter=self.max_iter)
        if not result.converged:
            raise SolverError(f"ADMM did not converge: {result.message}", result)
        return result

    def _admm_for(self, inertia: Inertia | None):
        from scissor_cli.solvers.admm.solver import AdmmSolver  # built only when asked for

        if not self.tissue.element.per_element:  # (the config check says so first: docs/model.md §21)
            raise ValueError("the ADMM solver needs every energy term per element: element "
                             f"{self.tissue.element.name!r} is solved by method 'newton'")
        dt_s = None if inertia is None else inertia.dt_s
        if self._admm is None or self._admm.dt_s != dt_s:
            self._admm = AdmmSolver(self.tissue, dt_s=dt_s, anderson_memory=self.anderson_memory)
            self._admm_state = None
        return self._admm

    def solve_dynamic(self, strokes: np.ndarray, dt_s: float, settle_steps: int) -> SolveResult:
        """Implicit Euler (docs/model.md §4): ramp the strokes at the cups' speed, then `settle_steps` more steps."""
        t = self.tissue
        strokes = np.asarray(strokes, float)
        speeds = np.array([c.speed_mm_per_s for c in t.scene.cups])
        ramp_s = float(np.max(np.abs(strokes) / speeds)) if len(speeds) else 0.0
        n_ramp = max(int(np.ceil(ramp_s / dt_s)), 1)
        x = t.rest.copy()
        v = np.zeros(x.size)
        t0, iterations = time.perf_counter(), 0
        s_prev = np.zeros_like(strokes)
        for step in range(n_ramp + settle_steps):
            s = strokes * min(1.0, (step + 1) / n_ramp)
            inertia = Inertia(dt_s, x.ravel() + dt_s * v, t.mass)
            r = self.solve(s, x, s_prev, inertia=inertia)
            iterations += r.iterations
            v = (r.x - x).ravel() / dt_s
            x, s_prev = r.x, s
        r.iterations, r.time_s = iterations, time.perf_counter() - t0
        speed = float(np.abs(v[t.free_dofs]).max()) if len(t.free_dofs) else 0.0
        r.message = (f"implicit Euler, {n_ramp} ramp + {settle_steps} settling steps of {dt_s:g} s; "
                     f"final max speed {speed:.3g} mm/s")
        return r


def solve_equilibrium(
    tissue: Tissue,
    strokes: np.ndarray,
    *,
    method: str = "newton",
    start: np.ndarray | None = None,
    start_strokes: np.ndarray | None = None,
    conditions: Conditions = NO_CONDITIONS,
    inertia: Inertia | None = None,
    tol: float | None = None,
    max_iter: int | None = None,
    anderson_memory: int = 0,
    factors: dict | None = None,
) -> SolveResult:
    """The tissue's equilibrium for cup strokes (C,) mm: positions (N, 2) mm and how it was solved.

    One call of `EquilibriumSolver(tissue, method, tol, max_iter,
    anderson_memory).solve(...)`; keep an EquilibriumSolver to solve the same
    tissue repeatedly with ADMM.
    """
    solver = EquilibriumSolver(tissue, method, tol, max_iter, anderson_memory)
    return solver.solve(strokes, start, start_strokes, conditions, inertia, factors=factors)


def mirrored_start(tissue: Tissue) -> np.ndarray:
    """The rest state mirrored top to bottom (N, 2): every element inverted, a stress test of recovery."""
    x = tissue.rest.copy()
    y = x[:, 1]
    x[:, 1] = y.max() + y.min() - y
    return x
