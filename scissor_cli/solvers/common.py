"""What every solver shares: results, errors, the implicit-Euler term, the residual.

The objective of one solve is (docs/model.md §4)

    Φ(x) = U(x) − fᵀx + 1/(2Δt²) ‖x − x̃‖²_M    (dynamics, an `Inertia` given)
    Φ(x) = U(x) − fᵀx                            (quasi-static, no inertia)

over the free degrees of freedom, the Dirichlet ones placed by the strokes;
f are external nodal loads (`Conditions.loads`, zero by default), and
`Conditions.held` free dofs stay where the start puts them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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


@dataclass(frozen=True)
class Conditions:
    """What one equilibrium holds and pushes beyond the tissue's own boundary (fixed sides, cups).

    loads (2N,) mN: external nodal forces (a needle's friction and tip
    force); held (H,): indices of free dofs (of the dN, d = tissue.dim) that stay where the
    start puts them (nodes a needle holds). Inputs to every solve, not
    subclasses of the tissue: the sparsity pattern of K_ff stays the same,
    so a factorisation's symbolic analysis is reused when they change.
    """

    loads: np.ndarray | None = None
    held: np.ndarray | None = None
    #: nodes (A,) held across a direction, free along it (a needle holding a
    #: node across its axis, any axis direction): `along` gives each node's
    #: held unit vectors, (A, d) in 2-D (one each) or (A, d − 1, d)
    #: orthonormal (3-D: both directions across the axis); the node's
    #: displacement components along them stay where the start puts them,
    #: the remaining one is free. Solved by rotating each such node's d×d
    #: block (`solvers.held.Held`), so K_ff keeps its pattern.
    along_nodes: np.ndarray | None = None
    along: np.ndarray | None = None

    def held_free(self, tissue: Tissue) -> np.ndarray:
        """Positions of the held dofs among the free ones (H,); ValueError if one is not free."""
        if self.held is None or len(self.held) == 0:
            return np.zeros(0, np.int64)
        held = np.unique(np.asarray(self.held, np.int64))
        if held.min() < 0 or held.max() >= tissue.free_index.size:
            raise ValueError(f"held dofs must lie in [0, {tissue.free_index.size}), got {held.min()}..{held.max()}")
        pos = tissue.free_index[held]
        if np.any(pos < 0):
            raise ValueError(f"held dofs {held[pos < 0][:5].tolist()} are already Dirichlet dofs (fixed or gripped)")
        return pos

    def along_free(self, tissue: Tissue) -> tuple[np.ndarray, np.ndarray]:
        """Free positions (A, d) of the `along_nodes`' dofs and their frames (A, d, d).

        A frame's columns are the held unit vectors, then the free one that
        completes them to a right-handed orthonormal basis (2-D: u⊥, u turned
        by +90°; 3-D: t₁ × t₂). ValueError if a node is not fully free, is
        also in `held`, or its vectors are not orthonormal.
        """
        d = tissue.dim
        if self.along_nodes is None or len(self.along_nodes) == 0:
            return np.zeros((0, d), np.int64), np.zeros((0, d, d))
        nodes = np.asarray(self.along_nodes, np.int64)
        u = np.asarray(self.along, float)
        if u.size != nodes.size * (d - 1) * d or np.unique(nodes).size != nodes.size:
            raise ValueError(f"along_nodes must be distinct, {d - 1} unit vector(s) ({d},) per node")
        u = u.reshape(nodes.size, d - 1, d)
        gram = np.einsum("aid,ajd->aij", u, u)
        if np.any(np.abs(gram - np.eye(d - 1)) > 1e-9):
            raise ValueError("the `along` vectors must be orthonormal unit vectors")
        if nodes.min() < 0 or d * nodes.max() + d - 1 >= tissue.free_index.size:
            raise ValueError("along_nodes out of range")
        dofs = tissue.free_index[d * nodes[:, None] + np.arange(d)]
        if np.any(dofs < 0):
            bad = nodes[np.any(dofs < 0, axis=1)]
            raise ValueError(f"along_nodes {bad[:5].tolist()} have Dirichlet dofs (fixed or gripped)")
        if self.held is not None and np.isin((d * nodes[:, None] + np.arange(d)).ravel(), self.held).any():
            raise ValueError("a node is both in along_nodes and in held")
        if d == 2:
            free = np.stack([-u[:, 0, 1], u[:, 0, 0]], axis=1)
        else:
            free = np.cross(u[:, 0], u[:, 1])
        frame = np.concatenate([u, free[:, None, :]], axis=1).transpose(0, 2, 1)  # columns: held…, free
        return dofs, frame

    @property
    def trivial(self) -> bool:
        return (self.loads is None and (self.held is None or len(self.held) == 0)
                and (self.along_nodes is None or len(self.along_nodes) == 0))


NO_CONDITIONS = Conditions()


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
    #: sparse factorisations the solve made (numeric refactorisations included)
    factorizations: int = 0
    #: load substeps the continuation took before the final solve (`newton.solve_newton`; 0 otherwise)
    substeps: int = 0

    def displacement(self, rest: np.ndarray) -> np.ndarray:
        return self.x - rest


class SolverError(RuntimeError):
    """A solve failed: not converged, inverted element, or non-finite values.

    Carries the partial result so callers can keep what was reached.
    """

    def __init__(self, message: str, result: SolveResult | None = None):
        super().__init__(message)
        self.result = result


def objective_gradient(
    tissue: Tissue, x: np.ndarray, inertia: Inertia | None, loads: np.ndarray | None = None,
    require_positive_J: bool = False, strain: tuple[float, np.ndarray] | None = None,
) -> tuple[float, np.ndarray | None]:
    """Φ (µJ) and ∇Φ (2N,) in mN at positions x (N, 2), with external loads (2N,) mN if given.

    With require_positive_J, (inf, None) when an element is inverted (a trial step to reject).
    `strain`, U and ∇U at x if the caller has them already (`Tissue.energy_gradient_stiffness`).
    """
    energy, grad = tissue.energy_gradient(x, require_positive_J) if strain is None else strain
    if grad is None:
        return energy, None
    if loads is not None:
        energy -= float(np.dot(loads, x.ravel()))
        grad = grad - loads
    if inertia is not None:
        dx = x.ravel() - inertia.x_tilde
        energy += 0.5 * float(np.dot(inertia.weight * dx, dx))
        grad = grad + inertia.weight * dx
    return energy, grad


def relative_residual(tissue: Tissue, grad: np.ndarray, held_free: np.ndarray | None = None) -> float:
    """‖∇Φ_f‖ over the force scale of the Dirichlet reactions (dimensionless).

    Held free dofs (`Conditions.held_free`) carry reactions, not residuals: they are left out.
    """
    g = grad[tissue.free_dofs]
    if held_free is not None and len(held_free):
        g = g.copy()
        g[held_free] = 0.0
    return float(np.linalg.norm(g)) / tissue.force_scale(grad)


def check_finite(x: np.ndarray, what: str) -> None:
    if not np.isfinite(x).all():
        raise SolverError(f"{what} became non-finite (NaN or inf)")
