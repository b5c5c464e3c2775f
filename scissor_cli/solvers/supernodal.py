"""A Cholesky factor kept in single (or double) precision, solved — and in float32 also factored — in compiled
loops with BLAS (docs/model.md §12, "The chord step's arithmetic").

The needle's chord solver (`insertion.chord`) solves with one kept factor of
the slab's K_ff a thousand times or more before it refactors, and a 3-D
Newton step's conjugate gradients tens of times (`linear.stepping_solve`). CHOLMOD's
supernodal solve through cvxopt reads the whole float64 factor twice per
solve (tens of MB on a picked slab: memory-bound) and converts its operands
on every call. A chord step only needs the solve as a preconditioner — its
convergence is judged on the float64 residual of the true gradient, so the
step's solution is the same equilibrium to the solver's tolerance — so the
factor is copied once per factorisation into float32 dense supernode
blocks (half the bytes) and solved here: per supernode a triangular solve
on its diagonal block and a matrix–vector product with the rows below
(BLAS `strsv`, `sgemv` from scipy's own BLAS, called from the compiled loop).
Where float32 is not enough (a nearly incompressible body's condition: the
chord steps stall at float32's floor) the same blocks are copied in float64
and solved by the same loops with `dtrsv`, `dgemv` (and `dtrsm`, `dgemm`):
CHOLMOD's own solve through cvxopt solves several right-hand sides column
by column (`benchmarks/bench_needle_incompressible.py`).

Layout: L = the factor of P A Pᵀ (P the ordering `perm`); supernode s spans
columns starts[s] … starts[s+1] − 1, all with the rows block_rows[row_ptr[s]
: row_ptr[s+1]] (its own columns first), stored column-major (lda = its row
count) from blocks[block_ptr[s]].
"""

from __future__ import annotations

import ctypes
import functools

import llvmlite.binding
import numpy as np
import scipy.linalg.cython_blas as _cython_blas
import scipy.linalg.cython_lapack as _cython_lapack
from numba import njit, types

#: the BLAS routines the compiled solve calls, by the symbol names they are linked under (`_link_blas`):
#: (uplo, trans, diag, n, A, lda, x, incx) and (trans, m, n, alpha, A, lda, x, incx, beta, y, incy), every
#: argument a pointer (Fortran: by reference), passed as an address
_BLAS = {"strsv": 8, "sgemv": 11, "strsm": 11, "sgemm": 13, "dtrsv": 8, "dgemv": 11, "dtrsm": 11, "dgemm": 13,
         "ssyrk": 10}
#: LAPACK's Cholesky of a supernode's diagonal block, (uplo, n, A, lda, info): `SingleFactorizer`
_LAPACK = {"spotrf": 5}
_strsv = types.ExternalFunction("scissor_blas_strsv", types.void(*[types.intp] * _BLAS["strsv"]))
_sgemv = types.ExternalFunction("scissor_blas_sgemv", types.void(*[types.intp] * _BLAS["sgemv"]))
#: (side, uplo, trans, diag, m, n, alpha, A, lda, B, ldb) and (transa, transb, m, n, k, alpha, A, lda, B, ldb,
#: beta, C, ldc): the same supernode sweeps on a block of right-hand sides (`_solve_block`)
_strsm = types.ExternalFunction("scissor_blas_strsm", types.void(*[types.intp] * _BLAS["strsm"]))
_sgemm = types.ExternalFunction("scissor_blas_sgemm", types.void(*[types.intp] * _BLAS["sgemm"]))
#: the same four in double precision, for float64 blocks
_dtrsv = types.ExternalFunction("scissor_blas_dtrsv", types.void(*[types.intp] * _BLAS["dtrsv"]))
_dgemv = types.ExternalFunction("scissor_blas_dgemv", types.void(*[types.intp] * _BLAS["dgemv"]))
_dtrsm = types.ExternalFunction("scissor_blas_dtrsm", types.void(*[types.intp] * _BLAS["dtrsm"]))
_dgemm = types.ExternalFunction("scissor_blas_dgemm", types.void(*[types.intp] * _BLAS["dgemm"]))
#: (uplo, trans, n, k, alpha, A, lda, beta, C, ldc): a descendant's update of a diagonal block (`_factor_blocks`)
_ssyrk = types.ExternalFunction("scissor_blas_ssyrk", types.void(*[types.intp] * _BLAS["ssyrk"]))
_spotrf = types.ExternalFunction("scissor_lapack_spotrf", types.void(*[types.intp] * _LAPACK["spotrf"]))


@functools.cache
def _link_blas() -> None:
    """Point the symbol names `_strsv`, `_sgemv` call at scipy's own BLAS in this process (once, before the
    first solve).

    By name, not by address: the compiled solve then refers to a symbol,
    so numba can cache it on disk and a new process only links the name
    again (an address baked in would differ between processes).
    """
    get_name = ctypes.pythonapi.PyCapsule_GetName
    get_name.restype, get_name.argtypes = ctypes.c_char_p, [ctypes.py_object]
    get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
    get_pointer.restype, get_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    for module, prefix, names in ((_cython_blas, "blas", _BLAS), (_cython_lapack, "lapack", _LAPACK)):
        for name in names:
            capsule = module.__pyx_capi__[name]
            llvmlite.binding.add_symbol(f"scissor_{prefix}_{name}", get_pointer(capsule, get_name(capsule)))


class SupernodalFactor:
    """L of P A Pᵀ = L Lᵀ in float32 (or float64) supernode blocks (module docstring); `solve` gives A⁻¹b.

    starts, row_ptr, block_ptr (S + 1,) int64, block_rows (int32) and blocks
    (float32 or float64; each block's upper triangle is not read) in the
    module's layout, perm (n,) int64 (row k of P A Pᵀ is row perm[k] of A):
    as CHOLMOD's supernodal factor lays them out (`solvers.cholmod_factor`
    reads them there; `Factorization.single`, `Factorization.double`). The
    arrays are kept, not copied. The relative error of a solve is that of
    the blocks' arithmetic on the factor's condition.
    """

    def __init__(self, starts: np.ndarray, row_ptr: np.ndarray, block_ptr: np.ndarray, block_rows: np.ndarray,
                 blocks: np.ndarray, perm: np.ndarray):
        self.starts, self.row_ptr, self.block_ptr = starts, row_ptr, block_ptr
        self.block_rows, self.blocks, self.perm = block_rows, blocks, perm
        self.n = perm.size

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x (float64) with A x = b, for b (n,) or (n, k).

        Several right-hand sides are solved together, each supernode's block
        read once for all of them (BLAS-3 `strsm`, `sgemm`: `_solve_block`);
        one is solved with the matrix–vector kernels (`_solve_columns`).
        """
        b = np.asarray(b, dtype=float)
        B = b.reshape(b.shape[0], -1)
        _link_blas()
        refs = _by_reference(self.blocks.dtype)
        if B.shape[1] == 1:
            X = np.empty(B.shape)
            _solve_columns(self.starts, self.row_ptr, self.block_rows, self.block_ptr, self.blocks, self.perm, B, X,
                           *refs)
            return X.reshape(b.shape)
        Y = np.asfortranarray(B[self.perm], dtype=self.blocks.dtype)  # P b, each column contiguous
        _solve_block(self.starts, self.row_ptr, self.block_rows, self.block_ptr, self.blocks, Y, *refs)
        X = np.empty(B.shape)
        X[self.perm] = Y
        return X.reshape(b.shape)


def _by_reference(dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The BLAS calls' by-reference arguments, owned by the caller for the whole compiled solve: dims (6,) int32
    (the kernels fill them), scalars (1, 0, −1) of the blocks' dtype, chars (L, N, T, R).

    Not allocated inside the compiled loops: there an array read only
    through its address is dead to numba after that read and may be freed
    at once; BLAS-3 routines allocate workspace of their own, which may
    then reuse it (a float32 block solve that failed at random).
    """
    return np.zeros(6, np.int32), np.array([1.0, 0.0, -1.0], dtype), np.array([76, 78, 84, 82], np.uint8)


@njit(cache=True)
def _solve_columns(starts, row_ptr, block_rows, block_ptr, blocks, perm, B, X, dims, scalars, chars):
    """X[:, c] = A⁻¹ B[:, c] for each column: P, L⁻¹ and L⁻ᵀ supernode by supernode, Pᵀ, in the blocks' precision
    (BLAS linked: `_link_blas`; dims, scalars, chars: `_by_reference`, here dims (n, lda, m, inc))."""
    n = perm.size
    y = np.empty(n, blocks.dtype)
    tmp = np.empty(n, blocks.dtype)
    z = blocks.itemsize  # bytes per entry: float32's or float64's routines
    # addresses as signed integers: unsigned plus signed would be a float in numba's arithmetic
    d, s_, ch = np.int64(dims.ctypes.data), np.int64(scalars.ctypes.data), np.int64(chars.ctypes.data)
    blk, yp, tp = np.int64(blocks.ctypes.data), np.int64(y.ctypes.data), np.int64(tmp.ctypes.data)
    dims[3] = 1
    n_super = starts.size - 1
    for col in range(B.shape[1]):
        for k in range(n):
            y[k] = B[perm[k], col]
        for s in range(n_super):  # L y = b
            c0, w = starts[s], starts[s + 1] - starts[s]
            r0, r = row_ptr[s], row_ptr[s + 1] - row_ptr[s]
            dims[0], dims[1], dims[2] = w, r, r - w
            a = blk + z * block_ptr[s]
            if z == 8:
                _dtrsv(ch, ch + 1, ch + 1, d, a, d + 4, yp + z * c0, d + 12)
            else:
                _strsv(ch, ch + 1, ch + 1, d, a, d + 4, yp + z * c0, d + 12)
            if r > w:
                if z == 8:
                    _dgemv(ch + 1, d + 8, d, s_, a + z * w, d + 4, yp + z * c0, d + 12, s_ + z, tp, d + 12)
                else:
                    _sgemv(ch + 1, d + 8, d, s_, a + z * w, d + 4, yp + z * c0, d + 12, s_ + z, tp, d + 12)
                for k in range(r - w):
                    y[block_rows[r0 + w + k]] -= tmp[k]
        for s in range(n_super - 1, -1, -1):  # Lᵀ x = y
            c0, w = starts[s], starts[s + 1] - starts[s]
            r0, r = row_ptr[s], row_ptr[s + 1] - row_ptr[s]
            dims[0], dims[1], dims[2] = w, r, r - w
            a = blk + z * block_ptr[s]
            if r > w:
                for k in range(r - w):
                    tmp[k] = y[block_rows[r0 + w + k]]
                if z == 8:
                    _dgemv(ch + 2, d + 8, d, s_ + 2 * z, a + z * w, d + 4, tp, d + 12, s_, yp + z * c0, d + 12)
                else:
                    _sgemv(ch + 2, d + 8, d, s_ + 2 * z, a + z * w, d + 4, tp, d + 12, s_, yp + z * c0, d + 12)
            if z == 8:
                _dtrsv(ch, ch + 2, ch + 1, d, a, d + 4, yp + z * c0, d + 12)
            else:
                _strsv(ch, ch + 2, ch + 1, d, a, d + 4, yp + z * c0, d + 12)
        for k in range(n):
            X[perm[k], col] = y[k]


@njit(cache=True)
def _solve_block(starts, row_ptr, block_rows, block_ptr, blocks, Y, dims, scalars, chars):
    """Y (n, k) of the blocks' dtype, column-major, permuted: overwritten with L⁻ᵀ L⁻¹ Y, supernode by supernode
    with BLAS-3 (`_solve_columns`' sweeps with a block of columns in place of one; BLAS linked: `_link_blas`;
    dims, scalars, chars: `_by_reference`, here dims (m, n, k, lda, ldb, ldc))."""
    n, k = Y.shape
    most = 0
    for s in range(starts.size - 1):
        most = max(most, row_ptr[s + 1] - row_ptr[s] - (starts[s + 1] - starts[s]))
    tmp = np.empty(max(most, 1) * k, blocks.dtype)  # (below, k) column-major
    z = blocks.itemsize  # bytes per entry: float32's or float64's routines
    d, s_, ch = np.int64(dims.ctypes.data), np.int64(scalars.ctypes.data), np.int64(chars.ctypes.data)
    blk, yp, tp = np.int64(blocks.ctypes.data), np.int64(Y.ctypes.data), np.int64(tmp.ctypes.data)
    dims[1], dims[4] = k, n
    n_super = starts.size - 1
    for s in range(n_super):  # L Y = B
        c0, w = starts[s], starts[s + 1] - starts[s]
        r0, r = row_ptr[s], row_ptr[s + 1] - row_ptr[s]
        below = r - w
        dims[0], dims[2], dims[3], dims[5] = w, w, r, max(below, 1)
        a = blk + z * block_ptr[s]
        if z == 8:
            _dtrsm(ch, ch, ch + 1, ch + 1, d, d + 4, s_, a, d + 12, yp + z * c0, d + 16)
        else:
            _strsm(ch, ch, ch + 1, ch + 1, d, d + 4, s_, a, d + 12, yp + z * c0, d + 16)
        if below > 0:
            dims[0] = below
            if z == 8:
                _dgemm(ch + 1, ch + 1, d, d + 4, d + 8, s_, a + z * w, d + 12, yp + z * c0, d + 16, s_ + z, tp,
                       d + 20)
            else:
                _sgemm(ch + 1, ch + 1, d, d + 4, d + 8, s_, a + z * w, d + 12, yp + z * c0, d + 16, s_ + z, tp,
                       d + 20)
            for j in range(k):
                for i in range(below):
                    Y[block_rows[r0 + w + i], j] -= tmp[j * below + i]
    for s in range(n_super - 1, -1, -1):  # Lᵀ X = Y
        c0, w = starts[s], starts[s + 1] - starts[s]
        r0, r = row_ptr[s], row_ptr[s + 1] - row_ptr[s]
        below = r - w
        dims[0], dims[2], dims[3], dims[5] = w, below, r, max(below, 1)
        a = blk + z * block_ptr[s]
        if below > 0:
            for j in range(k):
                for i in range(below):
                    tmp[j * below + i] = Y[block_rows[r0 + w + i], j]
            # Y_s −= A_belowᵀ tmp: (w × below)(below × k)
            if z == 8:
                _dgemm(ch + 2, ch + 1, d, d + 4, d + 8, s_ + 2 * z, a + z * w, d + 12, tp, d + 20, s_, yp + z * c0,
                       d + 16)
            else:
                _sgemm(ch + 2, ch + 1, d, d + 4, d + 8, s_ + 2 * z, a + z * w, d + 12, tp, d + 20, s_, yp + z * c0,
                       d + 16)
        if z == 8:
            _dtrsm(ch, ch, ch + 2, ch + 1, d, d + 4, s_, a, d + 12, yp + z * c0, d + 16)
        else:
            _strsm(ch, ch, ch + 2, ch + 1, d, d + 4, s_, a, d + 12, yp + z * c0, d + 16)


class SingleFactorizer:
    """Numeric Cholesky factorisations in float32 on one supernodal layout: CHOLMOD's symbolic analysis of a
    pattern, read from a factor of it (`layout`, a `SupernodalFactor`, `Factorization.single`).

    indptr, indices: the pattern of the matrices factored, their upper
    triangle in CSR as `linear.Factorization` was given it; `factor` takes
    their values in that order. A factor slot makes one from its first
    CHOLMOD factor (`Factorization.refactor(single=True)`) for the 3-D
    refactorisations that only precondition or step (the needle's chord
    steps, Newton's conjugate gradients, the trackers' responses): CHOLMOD
    factors in float64 only, and a float32 copy of it would be made after;
    here the values go straight into float32 blocks and are factored
    left-looking, supernode by supernode — each descendant's update by BLAS
    `ssyrk` and `sgemm`, the diagonal block by LAPACK `spotrf`, the rows
    below by `strsm` — in the layout's order (`benchmarks/bench_insertion3d.py`
    times both).
    """

    def __init__(self, layout: SupernodalFactor, indptr: np.ndarray, indices: np.ndarray):
        self.layout = layout
        self.nnz = int(indices.size)
        iperm = np.empty(layout.n, np.int64)
        iperm[layout.perm] = np.arange(layout.n)
        i, j = iperm[np.repeat(np.arange(layout.n), np.diff(indptr))], iperm[indices]
        col, row = np.minimum(i, j), np.maximum(i, j)  # the entry's place in L: column ≤ row
        owner = np.repeat(np.arange(layout.starts.size - 1), np.diff(layout.starts))[col]
        heights = np.diff(layout.row_ptr)
        # its row's place among its supernode's rows (sorted within each supernode)
        local = np.empty(row.size, np.int64)
        _rows_in(layout.block_rows, layout.row_ptr, owner, row, local)
        #: (nnz,) where each stored value of A goes in the blocks
        self._into = layout.block_ptr[owner] + (col - layout.starts[owner]) * heights[owner] + local
        most = max(1, int(np.max(heights)) * int(np.max(np.diff(layout.starts))))
        self._update = np.empty(most, np.float32)  # a descendant's update, kept alive beside the compiled loop

    def matches(self, A) -> bool:
        """Whether A (upper triangle, CSR) could have this factorizer's pattern (its order and stored count)."""
        return A.shape == (self.layout.n, self.layout.n) and A.nnz == self.nnz

    def factor(self, data: np.ndarray) -> SupernodalFactor | None:
        """The float32 factor of the matrix whose stored values (in the pattern's order) are data (nnz,), or None
        when float32 breaks down on it (a diagonal block not positive definite)."""
        lay = self.layout
        blocks = np.zeros(int(lay.block_ptr[-1]), np.float32)
        blocks[self._into] = data
        _link_blas()
        failed = _factor_blocks(lay.starts, lay.row_ptr, lay.block_rows, lay.block_ptr, blocks, self._update,
                                *_by_reference(np.float32))
        return None if failed else SupernodalFactor(lay.starts, lay.row_ptr, lay.block_ptr, lay.block_rows, blocks,
                                                    lay.perm)


@njit(cache=True)
def _rows_in(block_rows, row_ptr, owner, row, out):
    """out[k]: the place of row[k] among its supernode owner[k]'s rows (binary search: they are sorted)."""
    for k in range(row.size):
        a = row_ptr[owner[k]]
        lo, hi = a, row_ptr[owner[k] + 1]
        while lo < hi:
            mid = (lo + hi) // 2
            if block_rows[mid] < row[k]:
                lo = mid + 1
            else:
                hi = mid
        out[k] = lo - a


@njit(cache=True)
def _factor_blocks(starts, row_ptr, block_rows, block_ptr, blocks, update, dims, scalars, chars):
    """blocks (float32, A's lower triangle scattered in) overwritten with L, left-looking: 0, or 1 + the
    supernode whose diagonal block was not positive definite. A supernode's descendants wait in a linked list
    under the supernode of their next row (as CHOLMOD's supernodal numeric factorisation keeps them)."""
    n_super = starts.size - 1
    owner = np.empty(starts[n_super], np.int64)
    for s in range(n_super):
        for c in range(starts[s], starts[s + 1]):
            owner[c] = s
    place = np.empty(starts[n_super], np.int64)  # a row's place in the supernode being factored
    head = np.full(n_super, -1, np.int64)
    after = np.full(n_super, -1, np.int64)
    next_row = np.zeros(n_super, np.int64)
    z = 4
    d, sc, ch = np.int64(dims.ctypes.data), np.int64(scalars.ctypes.data), np.int64(chars.ctypes.data)
    blk, up = np.int64(blocks.ctypes.data), np.int64(update.ctypes.data)
    for j in range(n_super):
        c0, w = starts[j], starts[j + 1] - starts[j]
        r0, r = row_ptr[j], row_ptr[j + 1] - row_ptr[j]
        for k in range(r):
            place[block_rows[r0 + k]] = k
        e = head[j]
        head[j] = -1
        while e != -1:
            following = after[e]
            e0, er, ew = row_ptr[e], row_ptr[e + 1] - row_ptr[e], starts[e + 1] - starts[e]
            p1 = next_row[e]
            p2 = p1
            while p2 < er and block_rows[e0 + p2] < c0 + w:
                p2 += 1
            nd, m = p2 - p1, er - p1
            a = blk + z * (block_ptr[e] + p1)
            # update (m × nd) = L_e[p1:] L_e[p1:p2]ᵀ: its top nd × nd by syrk (lower triangle), the rest by gemm
            dims[0], dims[1], dims[2], dims[3] = nd, ew, er, m
            _ssyrk(ch, ch + 1, d, d + 4, sc, a, d + 8, sc + z, up, d + 12)
            if m > nd:
                dims[0], dims[1], dims[2], dims[3], dims[4] = m - nd, nd, ew, er, m
                _sgemm(ch + 1, ch + 2, d, d + 4, d + 8, sc, a + z * nd, d + 12, a, d + 12, sc + z, up + z * nd,
                       d + 16)
            for jj in range(nd):
                base = block_ptr[j] + (block_rows[e0 + p1 + jj] - c0) * r
                for ii in range(jj, m):
                    blocks[base + place[block_rows[e0 + p1 + ii]]] -= update[ii + jj * m]
            next_row[e] = p2
            if p2 < er:  # on to the supernode of its next row
                o = owner[block_rows[e0 + p2]]
                after[e], head[o] = head[o], e
            e = following
        a = blk + z * block_ptr[j]
        dims[0], dims[1] = w, r
        _spotrf(ch, d, a, d + 4, d + 8)
        if dims[2] != 0:
            return j + 1
        if r > w:  # L_below = A_below L_diag⁻ᵀ
            dims[0], dims[1], dims[2] = r - w, w, r
            _strsm(ch + 3, ch, ch + 2, ch + 1, d, d + 4, sc, a, d + 8, a + z * w, d + 8)
            next_row[j] = w
            o = owner[block_rows[r0 + w]]
            after[j], head[o] = head[o], j
    return 0
