"""What every solver shares: results, errors, the implicit-Euler term, the residual.

The objective of one solve is (MODEL.md §4)

    Φ(x) = U(x) + 1/(2Δt²) ‖x − x̃‖²_M        (dynamics, an `Inertia` given)
    Φ(x) = U(x)                                (quasi-static, no inertia)

over the free degrees of freedom, the Dirichlet ones placed by the strokes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from scissor_cli.mechanics.tissue import Tissue


@dataclass(frozen=True)
class Inertia:
    """The implicit-Euler term of one step: x̃ (2N,) mm, Δt (s), lumped mass (2N,) kg."""

    dt_s: float
    x_tilde: np.ndarray
    mass: np.ndarray

    @property
    def weight(self) -> np.ndarray:
        """M/Δt² per dof (2N,) in mN/mm."""
        return self.mass / self.dt_s**2


@dataclass
class SolveResult:
    """One solve: positions (N, 2) mm and how it went.

    `residual` is the relative force residual ‖∇Φ_f‖ / (Dirichlet reactions),
    the same measure for every solver so they can be compared.
    """

    x: np.ndarray
    converged: bool
    iterations: int
    residual: float
    time_s: float
    solver: str
    message: str = ""
    history: list[float] = field(default_factory=list)

    def displacement(self, rest: np.ndarray) -> np.ndarray:
        return self.x - rest


class SolverError(RuntimeError):
    """A solve failed: not converged, inverted element, or non-finite values.

    Carries the partial result so callers can keep what was reached.
    """

    def __init__(self, message: str, result: SolveResult | None = None):
        super().__init__(message)
        self.result = result


def objective_gradient(tissue: Tissue, x: np.ndarray, inertia: Inertia | None) -> tuple[float, np.ndarray]:
    """Φ (µJ) and ∇Φ (2N,) in mN at positions x (N, 2)."""
    energy, grad = tissue.energy_gradient(x)
    if inertia is not None:
        dx = x.ravel() - inertia.x_tilde
        energy += 0.5 * float(np.dot(inertia.weight * dx, dx))
        grad = grad + inertia.weight * dx
    return energy, grad


def relative_residual(tissue: Tissue, grad: np.ndarray) -> float:
    """‖∇Φ_f‖ over the force scale of the Dirichlet reactions (dimensionless)."""
    return float(np.linalg.norm(grad[tissue.free_dofs])) / tissue.force_scale(grad)


def check_finite(x: np.ndarray, what: str) -> None:
    if not np.all(np.isfinite(x)):
        raise SolverError(f"{what} became non-finite (NaN or inf)")
