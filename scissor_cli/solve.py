"""What every solver shares: results, errors, the implicit-Euler term, factorisations.

The objective of one solve is (MODEL.md §4)

    Φ(x) = U(x) + 1/(2Δt²) ‖x − x̃‖²_M        (dynamics, an `Inertia` given)
    Φ(x) = U(x)                                (quasi-static, no inertia)

over the free degrees of freedom, the Dirichlet ones placed by the strokes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import cvxopt
import qdldl
from cvxopt import cholmod

from .tissue import Tissue


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


class Factorization:
    """Sparse factorisation of a symmetric matrix, its symbolic analysis reused.

    A is the whole symmetric matrix, or with `upper` only its upper triangle
    (what `SparsePattern(upper=True)` assembles: half the work).

    Positive definite matrices (every projected Newton Hessian, the ADMM
    global matrix, a stable equilibrium's tangent) get CHOLMOD's supernodal
    Cholesky (through cvxopt): 2.6x faster than a simplicial LDLᵀ at 16k
    unknowns and 4x at 63k, because its dense supernode blocks run in BLAS.
    A symmetric indefinite matrix falls back to qdldl's LDLᵀ (AMD ordering),
    unless `definite` is asked for: then "not positive definite" is a
    SolverError, which is what Newton wants to hear before it projects.
    `refactor` reuses the symbolic analysis while the sparsity pattern is the
    same (a Newton iteration, the next control step). A singular matrix
    raises SolverError rather than returning inf.
    """

    def __init__(self, A: sp.spmatrix, definite: bool = False, upper: bool = False):
        self.definite = definite
        self.upper = upper
        self._pattern: tuple | None = None
        self._chol = self._ldl = None
        self.refactor(A)

    def refactor(self, A: sp.spmatrix) -> "Factorization":
        A = _symmetric_csr(A)
        n = A.shape[0]
        if self._pattern is None or A.nnz != self._pattern[0] or n != self._pattern[1]:
            # The upper triangle of a sorted symmetric CSR matrix is, entry for
            # entry, the lower triangle in CSC order: CHOLMOD's input, so a
            # refactorisation only copies A.data[upper] (no conversion).
            row = np.repeat(np.arange(n), np.diff(A.indptr))
            if self.upper and np.any(A.indices < row):
                raise ValueError("Factorization(upper=True) needs an upper-triangular matrix")
            upper = slice(None) if self.upper else A.indices >= row
            lower = cvxopt.spmatrix(A.data[upper], A.indices[upper].astype(int), row[upper].astype(int), (n, n))
            self._pattern, self._upper, self._lower = (A.nnz, n), upper, lower
            self._chol = self._ldl = None
        else:
            self._lower.V = cvxopt.matrix(A.data[self._upper])
        try:
            if self._chol is None:
                self._chol = cholmod.symbolic(self._lower)
            cholmod.numeric(self._lower, self._chol)
            self._active = "cholesky"
            return self
        except ArithmeticError:
            if self.definite:
                self._active = None
                raise SolverError("system matrix is not positive definite") from None
        if self.upper:  # qdldl reads the upper triangle of a CSC matrix
            A_csc = A.tocsc()
        else:  # a symmetric CSR matrix is its own transpose: reinterpret it as CSC
            A_csc = sp.csc_matrix((A.data, A.indices, A.indptr), shape=A.shape)
        try:
            if self._ldl is not None:
                self._ldl.update(A_csc)
            else:
                self._ldl = qdldl.Solver(A_csc, upper=self.upper)
        except (ValueError, RuntimeError) as exc:  # qdldl's ways of reporting a zero pivot
            self._active = None
            raise SolverError(f"singular system matrix ({exc})") from None
        self._active = "ldl"
        return self

    @property
    def method(self) -> str:
        """'cholesky' (CHOLMOD) or 'ldl' (qdldl) for the current factor."""
        return self._active

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x with A x = b, for b (n,) or (n, k)."""
        if self._active == "cholesky":
            B = cvxopt.matrix(np.asarray(b, dtype=float))
            cholmod.solve(self._chol, B)
            x = np.array(B)
            return x.reshape(np.shape(b))
        if self._active == "ldl":
            b = np.asarray(b, dtype=float)
            if b.ndim == 1:
                return self._ldl.solve(b)
            return np.column_stack([self._ldl.solve(np.ascontiguousarray(col)) for col in b.T])
        raise SolverError("no valid factorisation: the last refactor failed")


def _symmetric_csr(A: sp.spmatrix) -> sp.csr_matrix:
    """A as CSR with sorted column indices (the pattern's order is relied on)."""
    A = A if sp.isspmatrix_csr(A) else sp.csr_matrix(A)
    if not A.has_sorted_indices:
        A = A.sorted_indices()
    return A


def check_finite(x: np.ndarray, what: str) -> None:
    if not np.all(np.isfinite(x)):
        raise SolverError(f"{what} became non-finite (NaN or inf)")
