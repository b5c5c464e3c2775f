"""Sparse symmetric linear systems: one factorisation class for every solve.

Newton's steps, the tangent predictor, the Jacobian, the ADMM's global step
and the controller's updates all factor a symmetric sparse matrix whose
pattern is fixed per mesh and boundary set; `Factorization` keeps the
symbolic analysis and refactors numerically.
"""

from __future__ import annotations

import math
from typing import Callable

import cvxopt
import numpy as np
import qdldl
import scipy.sparse as sp
from cvxopt import cholmod

from scissor_cli.solvers.cholmod_factor import supernodal_copy
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.ordering import nested_dissection
from scissor_cli.solvers.single_factor import SingleFactorizer
from scissor_cli.solvers.supernodal import SupernodalFactor

#: conjugate-gradient iterations `solve_free` spends on an earlier factor before it refactors:
#: a 3-D refactorisation costs about 25 of them at 65k unknowns (docs/performance.md)
KRYLOV_MAX_ITER = 12
#: a 2-D K_ff with at least this many unknowns is ordered by nested dissection (`factorize_free`):
#: below it CHOLMOD keeps AMD's sparser factor; above it METIS's factor is sparser and its one-time
#: cost pays off within a run's factorisations (benchmarks/bench_forward.py)
ND_MIN_UNKNOWNS_2D = 10_000
#: conjugate gradients and Newton's chord steps solve with a float32 copy of the factor (`Factorization.single`):
#: they only precondition or propose a step that the float64 residual judges, and the copy's solve reads half the
#: bytes; off, CHOLMOD's float64 solve (for A/B runs: benchmarks/ab_trials.py)
SINGLE_PRECISION_STEPS = True
#: a 3-D refactorisation only to precondition (`solve_free`'s inexact steps, a tracker's response) is float32's on
#: the slot's first CHOLMOD layout (`single_factor.SingleFactorizer`), CHOLMOD's float64 one made when a float64 solve
#: asks (`Factorization.refactor`); off, CHOLMOD factors each time (A/B runs: benchmarks/ab_trials.py)
SINGLE_FACTORIZATION = True
#: a solve that needed more CG iterations than this marks its factor stale: the
#: tangent has moved away from it, so the next solve factors instead of trying
KRYLOV_STALE_ITER = 6
#: a slot released when its tracker is done (`release_free`) is taken by the next new slot of the same pattern:
#: it keeps its symbolic analysis and CHOLMOD's copy of the pattern, so that slot's first factorisation is a
#: refactorisation (each trial's trackers start new slots on the same mesh); off, every new slot analyses anew
#: (for A/B runs: benchmarks/ab_trials.py)
REUSE_RELEASED = True
#: released factorisations a tissue's cache keeps (each holds its factor: tens of MB on a body)
RELEASED_KEPT = 2


class NotPositiveDefinite(SolverError):
    """K_ff is not positive definite. `factored`: a factorisation found it (else preconditioned conjugate
    gradients met a direction of non-positive curvature, which proves it: no factorisation was tried)."""

    def __init__(self, message: str, factored: bool):
        super().__init__(message)
        self.factored = factored


class Factorization:
    """Sparse factorisation of a symmetric matrix, its symbolic analysis reused.

    A is the whole symmetric matrix, or with `upper` only its upper triangle
    (what `SparsePattern(upper=True)` assembles: half the work).

    Positive definite matrices (every projected Newton Hessian, the ADMM
    global matrix, a stable equilibrium's tangent) get CHOLMOD's supernodal
    Cholesky (through cvxopt): faster than a simplicial LDLᵀ from a few
    thousand unknowns on, its dense supernode blocks in BLAS. With
    `supernodal=False` the solves use CHOLMOD's simplicial LDLᵀ: slower to
    factor, faster to solve with at a few thousand unknowns (no padded
    supernodes), for a factor kept over many solves (docs/performance.md);
    with `definite` a supernodal LLᵀ is then factored first to check.
    A symmetric indefinite matrix falls back to qdldl's LDLᵀ (AMD ordering),
    unless `definite` is asked for: then "not positive definite" is a
    SolverError, which is what Newton wants to hear before it projects.
    `refactor` reuses the symbolic analysis while the sparsity pattern is the
    same (a Newton iteration, the next control step). A singular matrix
    raises SolverError rather than returning inf.

    `ordering`: "amd" (CHOLMOD's own; cvxopt's CHOLMOD has no METIS) or
    "nested_dissection" (`ordering.nested_dissection`), computed once per
    pattern; `groups` (n,) numbers each unknown's node so the ordering keeps
    a node's unknowns together; `perm` (n,), a nested-dissection ordering of
    this pattern already computed (an earlier factor's `perm`), skips METIS.
    On a 3-D tangent AMD fills in badly (nested dissection halves the
    factor's nonzeros and time at 65k unknowns); in 2-D it is as good up to
    ~10k unknowns (benchmarks/bench_forward.py). With a user ordering
    CHOLMOD still tries AMD and keeps the sparser factor.
    """

    def __init__(self, A: sp.spmatrix, definite: bool = False, upper: bool = False,
                 ordering: str = "amd", groups: np.ndarray | None = None, supernodal: bool = True,
                 perm: np.ndarray | None = None, float32_steps: bool = False, single: bool = False):
        if ordering not in ("amd", "nested_dissection"):
            raise ValueError(f"unknown ordering {ordering!r}: 'amd' or 'nested_dissection'")
        if perm is not None and (ordering != "nested_dissection" or len(perm) != A.shape[0]):
            raise ValueError("a given perm is a nested-dissection ordering of A's unknowns")
        self.definite = definite
        self.supernodal = supernodal
        #: whether `stepping_solve` uses the float32 copy (3-D: `factorize_free`; a 2-D factor is small and its
        #: solves overhead-bound, so it keeps float64)
        self.float32_steps = float32_steps
        self.upper = upper
        self.ordering = ordering
        self.groups = groups
        #: numeric factorisations tried (failed ones too), and conjugate-gradient
        #: iterations preconditioned by this factor (`preconditioned_cg`)
        self.factorizations = self.cg_iterations = 0
        #: set by `preconditioned_cg` when preconditioning with this factor got slow
        self.stale = False
        #: per-iteration residual contraction of the last converged `preconditioned_cg` on this
        #: factor (an upper bound, rtol^(1/iterations)); None since the last refactorisation
        self.cg_rate: float | None = None
        self._pattern: tuple | None = None
        self._chol = self._ldl = None
        #: float32 factorisations on the pattern's layout (`refactor(single=True)`), whether `stepping_solve` is on
        #: one of the current values, and whether CHOLMOD's of them is still to be made (a float64 solve makes it)
        self._single: SingleFactorizer | None = None
        self.in_float32 = self.deferred = False
        self._given_perm = None if perm is None else cvxopt.matrix(np.asarray(perm).tolist(), tc="i")
        self.refactor(A, single)

    def refactor(self, A: sp.spmatrix, single: bool = False) -> "Factorization":
        """Factor A on the kept analysis (a new one when its pattern changed). With `single` (a caller that only
        preconditions: `stepping_solve`) in float32 once CHOLMOD's first factor gave the layout, CHOLMOD's float64
        one deferred to a float64 solve (SINGLE_FACTORIZATION); CHOLMOD decides where float32 breaks down."""
        A = _symmetric_csr(A)
        n = A.shape[0]
        self.in_float32 = self.deferred = False
        if self._pattern is None or A.nnz != self._pattern[0] or n != self._pattern[1]:
            self._single = None
            # The upper triangle of a sorted symmetric CSR matrix is, entry for
            # entry, the lower triangle in CSC order: CHOLMOD's input, so a
            # refactorisation only copies A.data[upper] (no conversion).
            row = np.repeat(np.arange(n), np.diff(A.indptr))
            if self.upper and np.any(A.indices < row):
                raise ValueError("Factorization(upper=True) needs an upper-triangular matrix")
            upper = slice(None) if self.upper else A.indices >= row
            lower = cvxopt.spmatrix(A.data[upper], A.indices[upper].astype(int), row[upper].astype(int), (n, n))
            self._pattern, self._upper, self._lower = (A.nnz, n), upper, lower
            self._pattern_arrays = (A.indptr.copy(), A.indices.copy())
            self._chol = self._ldl = None
            self._perm, self._given_perm = self._given_perm, None  # (given for the first pattern only)
        else:
            self._lower.V = cvxopt.matrix(A.data[self._upper])
        self.factorizations += 1
        self.stale = False
        self.cg_rate = None
        self._copies: dict = {}  # (its float32 and float64 copies, made on demand: `single`, `double`)
        single = single and SINGLE_FACTORIZATION and self.float32_steps and self.upper and self.supernodal
        if single and self._single is not None and (own := self._single.factor(A.data)) is not None:
            self._copies[np.float32], self._active = own, "cholesky"
            self.in_float32 = self.deferred = True
            return self
        try:
            if self._chol is None:
                self._chol = self._symbolic(A, self.supernodal)
                self._check = None if self.supernodal else self._symbolic(A, True)
            if self._check is not None:
                # CHOLMOD's simplicial factor is LDLᵀ, which takes indefinite matrices
                # too: the supernodal LLᵀ says whether A is positive definite.
                cholmod.numeric(self._lower, self._check)
            cholmod.numeric(self._lower, self._chol)
            self._active = "cholesky"
            if single and self._single is None and (layout := self.single()) is not None:
                self._single = SingleFactorizer(layout, *self._pattern_arrays)
                # the first one made too, so that what a slot steps on never depends on its history
                if (own := self._single.factor(A.data)) is not None:
                    self._copies[np.float32], self.in_float32 = own, True
            return self
        except ArithmeticError:
            if self.definite:
                self._active = None
                raise NotPositiveDefinite("system matrix is not positive definite", factored=True) from None
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

    def cg_iterations_for(self, rtol: float) -> float:
        """Conjugate-gradient iterations this factor is expected to need for rtol (0 when not yet known).

        From `cg_rate`, the contraction per iteration its last preconditioned
        solve reached: the tangent only drifts further from the factor, so
        the rate is not expected to improve.
        """
        if self.cg_rate is None or not 0.0 < self.cg_rate < 1.0:
            return 0.0
        return math.log(rtol) / math.log(self.cg_rate)

    def same_pattern(self, A: sp.spmatrix) -> bool:
        """Whether A (as given to `refactor`) has exactly this factor's pattern, entry for entry."""
        if self._pattern is None:
            return False
        A = _symmetric_csr(A)
        indptr, indices = self._pattern_arrays
        return np.array_equal(A.indptr, indptr) and np.array_equal(A.indices, indices)

    def matches(self, A: sp.spmatrix) -> bool:
        """Whether A (as given to `refactor`) has the pattern's size and entry count, so the factor can
        precondition it."""
        return self._pattern is not None and (A.nnz, A.shape[0]) == self._pattern

    @property
    def perm(self) -> np.ndarray | None:
        """The nested-dissection ordering (n,) this factor's analysis was given (METIS's, or `perm`'s), or None
        (AMD): what another factorisation of the same pattern may take as its `perm`."""
        return None if self._perm is None else np.asarray(memoryview(self._perm)).ravel().astype(np.int64)

    @property
    def nnz_factor(self) -> int:
        """Entries of the Cholesky factor L (0 without one): the fill the ordering left. Factors a copy (for
        reports, not hot paths): cvxopt's `getfactor` turns the factor it reads into a symbolic, simplicial one."""
        if self._active != "cholesky":
            return 0
        copy = self._symbolic(self._pattern_csr, self.supernodal)
        cholmod.numeric(self._lower, copy)
        return len(cholmod.getfactor(copy).V)

    def _symbolic(self, A: sp.csr_matrix, supernodal: bool = True):
        """CHOLMOD's symbolic analysis of the pattern, with this factor's ordering: a supernodal LLᵀ or a
        simplicial LDLᵀ."""
        self._pattern_csr = A
        saved = cholmod.options.get("supernodal", 2)
        cholmod.options["supernodal"] = 2 if supernodal else 0  # read by the analysis only
        try:
            if self.ordering == "nested_dissection":
                if self._perm is None:  # once per pattern
                    self._perm = cvxopt.matrix(nested_dissection(A, self.groups).tolist(), tc="i")
                return cholmod.symbolic(self._lower, p=self._perm)
            return cholmod.symbolic(self._lower)
        finally:
            cholmod.options["supernodal"] = saved

    def single(self) -> SupernodalFactor | None:
        """The current supernodal Cholesky factor in float32, solved in compiled loops (`solvers.supernodal`):
        float32's own (`refactor(single=True)`) or CHOLMOD's copied (`solvers.cholmod_factor`); None for any other
        factor, or one CHOLMOD does not lay out as expected. For solves that only precondition or step."""
        return self._copy(np.float32)

    def double(self) -> SupernodalFactor | None:
        """`single`'s copy in float64, for a factor whose condition float32 cannot carry: the same compiled
        loops solve a block of right-hand sides at once, where cvxopt's CHOLMOD goes column by column."""
        return self._copy(np.float64)

    def _numeric(self) -> None:
        """CHOLMOD's factorisation of the current values where it was deferred (NotPositiveDefinite: as `refactor`)."""
        if not self.deferred:
            return
        self.deferred = False
        try:
            cholmod.numeric(self._lower, self._chol)
        except ArithmeticError:
            self._active = None
            raise NotPositiveDefinite("system matrix is not positive definite", factored=True) from None

    def _copy(self, dtype) -> SupernodalFactor | None:
        if dtype != np.float32:
            self._numeric()
        if dtype not in self._copies and self._active == "cholesky" and self.supernodal:
            self._copies[dtype] = supernodal_copy(self._chol, self._pattern[1], dtype) or False
        return self._copies.get(dtype) or None

    @property
    def method(self) -> str:
        """'cholesky' (CHOLMOD) or 'ldl' (qdldl) for the current factor."""
        return self._active

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x with A x = b, for b (n,) or (n, k)."""
        if self._active == "cholesky":
            self._numeric()
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


def conjugate_gradients(times: Callable[[np.ndarray], np.ndarray], precondition: Callable[[np.ndarray], np.ndarray],
                        b: np.ndarray, rtol: float, max_iter: int, x0: np.ndarray | None = None,
                        relative_to: str = "rhs") -> tuple[np.ndarray | None, int, str]:
    """x with times(x) = b by preconditioned conjugate gradients; (x or None, iterations, why it stopped).

    `times` is a symmetric positive definite operator, `precondition` an
    approximation of its inverse (a nearby matrix's factorisation), x0 the
    start (default 0). Converged when, with relative_to
    * "rhs": ‖b − times(x)‖ ≤ rtol ‖b‖, the true residual checked at the end;
    * "solution": the preconditioned residual ‖M⁻¹ r‖ ≤ rtol ‖x‖ — for a
      solve on a constraint's null space (the preconditioner projects onto
      it), whose residual keeps the constraint's reactions and never vanishes.
    Returns (x, iterations, "converged"), or (None, iterations, why):
    "curvature" (a direction of non-positive curvature: the operator is not
    positive definite), "non-finite", "iterations" (not converged within
    max_iter) or "residual" (the recursive residual drifted from the true one).
    """
    if relative_to not in ("rhs", "solution"):
        raise ValueError(f"relative_to must be 'rhs' or 'solution', got {relative_to!r}")
    b = np.asarray(b, dtype=float)
    b_norm = float(np.linalg.norm(b))
    x = np.zeros_like(b) if x0 is None else np.array(x0, dtype=float)
    if b_norm == 0.0 and x0 is None:
        return x, 0, "converged"
    r = b - times(x) if x0 is not None else b.copy()
    z = precondition(r)
    p = z.copy()
    rz = float(r @ z)
    for k in range(max_iter + 1):
        if relative_to == "solution" and np.linalg.norm(z) <= rtol * max(float(np.linalg.norm(x)), 1e-300):
            return x, k, "converged"
        if k == max_iter:
            break
        q = times(p)
        curvature = float(p @ q)
        if not np.isfinite(rz) or not np.isfinite(curvature):
            return None, k + 1, "non-finite"
        if not curvature > 0.0:
            return None, k + 1, "curvature"
        a = rz / curvature
        x += a * p
        r -= a * q
        if relative_to == "rhs" and np.linalg.norm(r) <= rtol * b_norm:
            true = float(np.linalg.norm(b - times(x)))
            return (x, k + 1, "converged") if true <= 2.0 * rtol * b_norm else (None, k + 1, "residual")
        z = precondition(r)
        rz_next = float(r @ z)
        p = z + (rz_next / rz) * p
        rz = rz_next
    return None, max_iter, "iterations"


def preconditioned_cg(A: sp.csr_matrix | Callable[[np.ndarray], np.ndarray], b: np.ndarray, factor: Factorization,
                      rtol: float, max_iter: int = KRYLOV_MAX_ITER,
                      upper: bool = True) -> tuple[np.ndarray | None, int, str]:
    """x with A x = b to ‖b − A x‖ ≤ rtol ‖b‖ by `conjugate_gradients` preconditioned with `factor`.

    A (n, n) symmetric, given by its upper triangle when `upper`, or as the
    operator v ↦ A v (a Hessian applied without assembling it,
    `solvers.hessian_free`); `factor` a Cholesky factorisation of a nearby
    matrix (an earlier Newton tangent). Returns (x, iterations, "converged"),
    or (None, iterations, why) when the iteration meets a direction of
    non-positive curvature ("curvature": A is not positive definite), turns
    non-finite, or does not reach rtol within max_iter
    (`conjugate_gradients`' reasons). The true residual is checked before x
    is returned. Records on the factor the iterations, the rate reached and
    whether it is `stale` (a converged solve that needed more than
    KRYLOV_STALE_ITER iterations: the next solve factors instead).
    """
    if callable(A):
        times = A
    elif upper:
        diag, AT = A.diagonal(), A.T

        def times(v):
            return A @ v + AT @ v - diag * v
    else:
        times = A.__matmul__
    x, k, why = conjugate_gradients(times, stepping_solve(factor), b, rtol, max_iter)
    factor.cg_iterations += k
    if x is not None:
        factor.stale = k > KRYLOV_STALE_ITER
        if k > 0:
            factor.cg_rate = rtol ** (1.0 / k)
    return x, k, why


def stepping_solve(factor: Factorization) -> Callable[[np.ndarray], np.ndarray]:
    """b ↦ the factor's solve for a preconditioner or a trial step: on its float32 copy where it asks for one
    (`Factorization.float32_steps`, SINGLE_PRECISION_STEPS) and has one, else its own."""
    single = factor.single() if SINGLE_PRECISION_STEPS and factor.float32_steps else None
    return factor.solve if single is None else single.solve


def solve_free(tissue, K_upper: sp.csr_matrix, b: np.ndarray, factors: dict | None = None,
               rtol: float | None = None, max_iter: int = KRYLOV_MAX_ITER) -> tuple[np.ndarray, bool]:
    """x with K_ff x = b (K_ff from its upper triangle); returns (x, whether K_ff was factored).

    With `rtol`, the factorisation already in the slot (an earlier tangent's)
    first preconditions conjugate gradients to that relative residual
    (`preconditioned_cg`, at most max_iter iterations); only when that
    fails, or when the last such solve needed more than KRYLOV_STALE_ITER
    iterations (the factor is stale), is
    K_ff factored (`factorize_free`). NotPositiveDefinite if it is not
    positive definite: found by the factorisation, or by conjugate gradients
    meeting negative curvature (then the factorisation, which would fail
    after most of its cost, is not tried, and the slot keeps its factor).
    Without rtol K_ff is always factored: the direct solve. With rtol it is
    factored in float32 (`Factorization.refactor`'s `single`) and solved by
    CG on it, directly (CHOLMOD's float64 factor) only if that fails.
    """
    factors = tissue.factor_cache if factors is None else factors
    factor = factors.get("free")
    if (rtol is not None and factor is not None and factor.method == "cholesky" and not factor.stale
            and factor.matches(K_upper)):
        x, k, why = preconditioned_cg(K_upper, b, factor, rtol, max_iter)
        if x is not None:
            return x, False
        if why == "curvature":
            raise NotPositiveDefinite("system matrix is not positive definite (conjugate gradients met negative "
                                      "curvature)", factored=False)
    factor = factorize_free(tissue, K_upper, factors, single=rtol is not None)
    if factor.in_float32:
        x, _, _ = preconditioned_cg(K_upper, b, factor, rtol, max_iter)
        if x is not None:
            return x, True
    return factor.solve(b), True


def factorize_free(tissue, K_upper: sp.csr_matrix, factors: dict | None = None,
                   supernodal: bool = True, single: bool = False) -> Factorization:
    """A positive definite factorisation of K_ff from its upper triangle (Nf, Nf).

    Refactors the symbolic analysis kept in `factors["free"]` (default: the
    tissue's own slot, one per mesh and boundary set, shared by every solve
    on it; the controller's trackers keep their own). A new slot's nested
    dissection is computed once per pattern and kept in the tissue's cache
    (shared by the tissues `Tissue.with_material` derives): each trial's
    trackers analyse the same pattern again, and METIS is most of that
    analysis on the nodal element's wider pattern. A new slot first takes a
    slot an ended loop released of exactly its pattern (`release_free`),
    refactored: the rest of the analysis is kept too. Raises SolverError if
    K_ff is not positive definite (Newton then projects). A 3-D tissue's
    factor is ordered by nested dissection (`Factorization`), a 2-D one's by
    AMD below ND_MIN_UNKNOWNS_2D unknowns and by nested dissection above.
    `supernodal` (the slot's first factorisation decides) and `single` (a caller that only preconditions with
    it) as in `Factorization`.
    """
    factors = tissue.factor_cache if factors is None else factors
    factor = factors.get("free")
    if factor is None and (factor := _released(tissue, K_upper, supernodal, single)) is not None:
        factors["free"] = factor
        return factor
    if factor is None:
        large = tissue.dim == 3 or K_upper.shape[0] >= ND_MIN_UNKNOWNS_2D
        ordering = "nested_dissection" if large else "amd"
        known = ("ordering", K_upper.shape[0], K_upper.nnz)  # (a wrong match would only cost fill, never accuracy)
        perm = tissue.factor_cache.get(known) if large else None
        factor = factors["free"] = Factorization(K_upper, definite=True, upper=True, ordering=ordering,
                                                 groups=tissue.free_dofs // tissue.dim, supernodal=supernodal,
                                                 perm=perm, float32_steps=tissue.dim == 3, single=single)
        if large and perm is None and factor.perm is not None:
            tissue.factor_cache[known] = factor.perm
        return factor
    return factor.refactor(K_upper, single)


def release_free(tissue, factors: dict) -> None:
    """Hand back the slot `factors["free"]` of a tracker that is done with it (its trial ended): the next new slot
    of the same pattern on a tissue sharing `tissue`'s cache refactors it instead of analysing anew
    (`factorize_free`, REUSE_RELEASED). The slot is emptied either way."""
    factor = factors.pop("free", None)
    if not REUSE_RELEASED or factor is None or factor.method != "cholesky":
        return
    released = tissue.factor_cache.setdefault("released", [])
    released.append(factor)
    del released[:-RELEASED_KEPT]


def _released(tissue, K_upper: sp.csr_matrix, supernodal: bool, single: bool) -> Factorization | None:
    """A released factorisation (`release_free`) of K_upper's exact pattern and kind, refactored at K_upper with
    its counts from 0 (as a new one's: what it held before is gone), or None. SolverError as `refactor`.
    Each is taken off the list before it is looked at (`list.pop` is atomic), so trials on threads sharing a
    tissue never take the same one."""
    released = tissue.factor_cache.get("released", [])
    for _ in range(len(released)):
        try:
            factor = released.pop(0)
        except IndexError:  # (another thread took the last one)
            return None
        if factor.supernodal == supernodal and factor.same_pattern(K_upper):
            factor.factorizations = factor.cg_iterations = 0
            return factor.refactor(K_upper, single)
        released.append(factor)
    return None
