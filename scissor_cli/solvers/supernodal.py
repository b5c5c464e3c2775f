"""A Cholesky factor kept in single (or double) precision, solved in compiled loops with BLAS (docs/model.md
§12, "The chord step's arithmetic").

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
from numba import njit, types

#: the BLAS routines the compiled solve calls, by the symbol names they are linked under (`_link_blas`):
#: (uplo, trans, diag, n, A, lda, x, incx) and (trans, m, n, alpha, A, lda, x, incx, beta, y, incy), every
#: argument a pointer (Fortran: by reference), passed as an address
_BLAS = {"strsv": 8, "sgemv": 11, "strsm": 11, "sgemm": 13, "dtrsv": 8, "dgemv": 11, "dtrsm": 11, "dgemm": 13}
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
    for name in _BLAS:
        capsule = _cython_blas.__pyx_capi__[name]
        llvmlite.binding.add_symbol(f"scissor_blas_{name}", get_pointer(capsule, get_name(capsule)))


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
    (the kernels fill them), scalars (1, 0, −1) of the blocks' dtype, chars (L, N, T).

    Not allocated inside the compiled loops: there an array read only
    through its address is dead to numba after that read and may be freed
    at once; BLAS-3 routines allocate workspace of their own, which may
    then reuse it (a float32 block solve that failed at random).
    """
    return np.zeros(6, np.int32), np.array([1.0, 0.0, -1.0], dtype), np.array([76, 78, 84], np.uint8)


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
