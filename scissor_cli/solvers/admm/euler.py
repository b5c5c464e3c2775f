"""Implicit Euler with ADMM-PD along a path of cup strokes (docs/model.md §4).

Each step minimises Φ(x) = U(x) + 1/(2Δt²) ‖x − x̃‖²_M with one
`AdmmSolver` factored for that Δt, warm-started from the previous step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.admm.solver import AdmmSolver, AdmmState
from scissor_cli.solvers.common import Inertia, SolverError, SolveResult


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
    """Step docs/model.md §4 with ADMM along strokes_path (S, C) mm: S steps of dt_s (s) from x0 (N, 2) mm,
    v0 (N, 2) mm/s.

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
