"""A Cholesky factor kept in single (or double) precision, solved in compiled loops with BLAS (docs/model.md §12,
"The chord step's arithmetic"); `single_factor` factors into the same blocks in float32.

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

from scissor_cli import runtime
from scissor_cli.solvers.supernode_tree import tree_cuts

#: the BLAS routines the compiled solve calls, by the symbol names they are linked under (`_link_blas`):
#: (uplo, trans, diag, n, A, lda, x, incx) and (trans, m, n, alpha, A, lda, x, incx, beta, y, incy), every
#: argument a pointer (Fortran: by reference), passed as an address
_BLAS = {"strsv": 8, "sgemv": 11, "strsm": 11, "sgemm": 13, "dtrsv": 8, "dgemv": 11, "dtrsm": 11, "dgemm": 13,
         "ssyrk": 10}
#: LAPACK's Cholesky of a supernode's diagonal block, (uplo, n, A, lda, info): `single_factor.SingleFactorizer`
_LAPACK = {"spotrf": 5}
_strsv = types.ExternalFunction("scissor_blas_strsv", types.void(*[types.intp] * _BLAS["strsv"]))
_sgemv = types.ExternalFunction("scissor_blas_sgemv", types.void(*[types.intp] * _BLAS["sgemv"]))
#: (side, uplo, trans, diag, m, n, alpha, A, lda, B, ldb) and (transa, transb, m, n, k, alpha, A, lda, B, ldb,
#: beta, C, ldc): the same supernode sweeps on a block of right-hand sides (`_forward_block`, `_backward_block`)
_strsm = types.ExternalFunction("scissor_blas_strsm", types.void(*[types.intp] * _BLAS["strsm"]))
_sgemm = types.ExternalFunction("scissor_blas_sgemm", types.void(*[types.intp] * _BLAS["sgemm"]))
#: the same four in double precision, for float64 blocks
_dtrsv = types.ExternalFunction("scissor_blas_dtrsv", types.void(*[types.intp] * _BLAS["dtrsv"]))
_dgemv = types.ExternalFunction("scissor_blas_dgemv", types.void(*[types.intp] * _BLAS["dgemv"]))
_dtrsm = types.ExternalFunction("scissor_blas_dtrsm", types.void(*[types.intp] * _BLAS["dtrsm"]))
_dgemm = types.ExternalFunction("scissor_blas_dgemm", types.void(*[types.intp] * _BLAS["dgemm"]))
#: (uplo, trans, n, k, alpha, A, lda, beta, C, ldc): a descendant's update of a diagonal block
#: (`single_factor._factor_run`)
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
                 blocks: np.ndarray, perm: np.ndarray, cuts: np.ndarray | None = None):
        self.starts, self.row_ptr, self.block_ptr = starts, row_ptr, block_ptr
        self.block_rows, self.blocks, self.perm = block_rows, blocks, perm
        self.n = perm.size
        if cuts is not None:  # (a factor of the same layout: its tree's cut is the same)
            self.cuts = cuts

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x (float64) with A x = b, for b (n,) or (n, k).

        Several right-hand sides are solved together, each supernode's block
        read once for all of them (BLAS-3 `strsm`, `sgemm`: `_forward_block`,
        `_backward_block`); one is solved with the matrix–vector kernels
        (`_forward`, `_backward`). Either way the elimination tree's
        independent parts go at once where the process has threads for them
        (`supernode_tree`, `runtime.in_parts`).
        """
        b = np.asarray(b, dtype=float)
        B = b.reshape(b.shape[0], -1)
        _link_blas()
        if B.shape[1] == 1:
            return self._solve_vector(B[:, 0]).reshape(b.shape)
        return self._solve_columns(B).reshape(b.shape)

    @functools.cached_property
    def cuts(self) -> np.ndarray:
        """The parts' and the top's bounds in supernodes (`supernode_tree.tree_cuts`), one part per thread."""
        return tree_cuts(self.starts, self.row_ptr, self.block_rows, runtime.MOST_THREADS)

    def _solve_vector(self, b: np.ndarray) -> np.ndarray:
        cuts, K = self.cuts, self.cuts.size - 2
        lay = (self.starts, self.row_ptr, self.block_rows, self.block_ptr, self.blocks, self.perm)
        top0, tmp, refs = self._scratch(1)
        y, spills = np.empty(self.n, self.blocks.dtype), np.empty((K, self.n - top0), self.blocks.dtype)
        x = np.empty(self.n)
        runtime.in_parts(*[lambda k=k: _forward(lay, b, y, cuts[k], cuts[k + 1], top0, spills[k], tmp[k], refs[k])
                           for k in range(K)])
        _top(lay, b, y, x, cuts[K], spills, tmp[K], refs[K])
        runtime.in_parts(*[lambda k=k: _backward(lay, y, x, cuts[k], cuts[k + 1], tmp[k], refs[k])
                           for k in range(K)])
        return x

    def _solve_columns(self, B: np.ndarray) -> np.ndarray:
        cuts, K, dtype = self.cuts, self.cuts.size - 2, self.blocks.dtype
        lay = (self.starts, self.row_ptr, self.block_rows, self.block_ptr, self.blocks)
        top0, tmp, refs = self._scratch(B.shape[1])
        spills = [np.empty((self.n - top0, B.shape[1]), dtype, order="F") for _ in range(K)]
        Y = np.asfortranarray(B[self.perm], dtype=dtype)  # P b, each column contiguous
        runtime.in_parts(*[lambda p=p: _forward_block(lay, Y, cuts[p], cuts[p + 1], top0, spills[p], tmp[p], refs[p])
                           for p in range(K)])
        for p in range(K):  # the parts' updates of the top's rows, in order
            Y[top0:] -= spills[p]
        _forward_block(lay, Y, cuts[K], cuts[K + 1], self.n, np.empty((0, B.shape[1]), dtype, order="F"), tmp[K],
                       refs[K])
        _backward_block(lay, Y, cuts[K], cuts[K + 1], tmp[K], refs[K])
        runtime.in_parts(*[lambda p=p: _backward_block(lay, Y, cuts[p], cuts[p + 1], tmp[p], refs[p])
                           for p in range(K)])
        X = np.empty(B.shape)
        X[self.perm] = Y
        return X

    def _scratch(self, columns: int) -> tuple:
        """The top's first column, and each part's and the top's (K + 1) BLAS buffer (the most rows below a
        supernode × columns) and by-reference arguments (`_by_reference`): made per solve, so two threads may
        solve with one factor."""
        K, dtype = self.cuts.size - 2, self.blocks.dtype
        most = max(1, int(np.max(np.diff(self.row_ptr) - np.diff(self.starts))))
        return (int(self.starts[self.cuts[K]]), np.empty((K + 1, most * columns), dtype),
                [_by_reference(dtype) for _ in range(K + 1)])


def _by_reference(dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The BLAS calls' by-reference arguments, owned by the caller for the whole compiled solve: dims (6,) int32
    (the kernels fill them), scalars (1, 0, −1) of the blocks' dtype, chars (L, N, T, R).

    Not allocated inside the compiled loops: there an array read only
    through its address is dead to numba after that read and may be freed
    at once; BLAS-3 routines allocate workspace of their own, which may
    then reuse it (a float32 block solve that failed at random).
    """
    return np.zeros(6, np.int32), np.array([1.0, 0.0, -1.0], dtype), np.array([76, 78, 84, 82], np.uint8)


@njit(cache=True, nogil=True)
def _forward(lay, b, y, s0, s1, own_end, spill, tmp, refs, gather=True):
    """L y = P b over supernodes s0 ≤ s < s1: their columns of y (n,), in the blocks' precision, gathered from b
    (n,) (unless `gather` is False: the caller did) and solved in place. lay: (starts, row_ptr, block_rows,
    block_ptr, blocks, perm); refs: (dims, scalars, chars), `_by_reference`'s, here dims (n, lda, m, inc); tmp:
    a row buffer (BLAS linked: `_link_blas`). A row at or past own_end belongs to the top (`supernode_tree`): its
    updates are summed into spill (n − own_end,), zeroed first, for `_top` to subtract."""
    starts, row_ptr, block_rows, block_ptr, blocks, perm = lay
    dims, scalars, chars = refs
    if gather:
        for c in range(starts[s0], starts[s1]):
            y[c] = b[perm[c]]
    spill[:] = 0.0
    z = blocks.itemsize  # bytes per entry: float32's or float64's routines
    # addresses as signed integers: unsigned plus signed would be a float in numba's arithmetic
    d, s_, ch = np.int64(dims.ctypes.data), np.int64(scalars.ctypes.data), np.int64(chars.ctypes.data)
    blk, yp, tp = np.int64(blocks.ctypes.data), np.int64(y.ctypes.data), np.int64(tmp.ctypes.data)
    dims[3] = 1
    for s in range(s0, s1):
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
                row = block_rows[r0 + w + k]
                if row < own_end:
                    y[row] -= tmp[k]
                else:
                    spill[row - own_end] += tmp[k]


@njit(cache=True, nogil=True)
def _backward(lay, y, x, s0, s1, tmp, refs):
    """Lᵀ y = y in place over supernodes s1 > s ≥ s0 (`_forward`'s arguments), their columns then scattered into
    x (n,) = Pᵀ y: reads the rows below each, which the top or this run's later supernodes have finished, and
    writes only the run's own."""
    starts, row_ptr, block_rows, block_ptr, blocks, perm = lay
    dims, scalars, chars = refs
    z = blocks.itemsize
    d, s_, ch = np.int64(dims.ctypes.data), np.int64(scalars.ctypes.data), np.int64(chars.ctypes.data)
    blk, yp, tp = np.int64(blocks.ctypes.data), np.int64(y.ctypes.data), np.int64(tmp.ctypes.data)
    dims[3] = 1
    for s in range(s1 - 1, s0 - 1, -1):
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
    for c in range(starts[s0], starts[s1]):
        x[perm[c]] = y[c]


@njit(cache=True, nogil=True)
def _top(lay, b, y, x, s0, spills, tmp, refs):
    """The top's part of a solve, after the parts' `_forward`: from supernode s0 on, its columns gathered, the
    parts' spills (K, n − starts[s0]) subtracted in order, L and Lᵀ solved, its columns scattered into x."""
    starts, perm = lay[0], lay[5]
    s1, c0 = starts.size - 1, starts[s0]
    for c in range(c0, perm.size):
        y[c] = b[perm[c]]
        for k in range(spills.shape[0]):
            y[c] -= spills[k, c - c0]
    _forward(lay, b, y, s0, s1, perm.size, spills[0, :0], tmp, refs, False)
    _backward(lay, y, x, s0, s1, tmp, refs)


@njit(cache=True, nogil=True)
def _forward_block(lay, Y, s0, s1, own_end, spill, tmp, refs):
    """L Y = P B in place over supernodes s0 ≤ s < s1, Y (n, k) of the blocks' dtype, column-major, permuted: the
    sweep of `_forward` with a block of columns in place of one, by BLAS-3 (`strsm`, `sgemm`). lay: (starts,
    row_ptr, block_rows, block_ptr, blocks); refs: `_by_reference`'s, here dims (m, n, k, lda, ldb, ldc); tmp:
    (most rows below × k,). A row at or past own_end is the top's: its updates go into spill (n − own_end, k),
    zeroed first."""
    starts, row_ptr, block_rows, block_ptr, blocks = lay
    dims, scalars, chars = refs
    n, k = Y.shape
    spill[:, :] = 0.0
    z = blocks.itemsize  # bytes per entry: float32's or float64's routines
    d, s_, ch = np.int64(dims.ctypes.data), np.int64(scalars.ctypes.data), np.int64(chars.ctypes.data)
    blk, yp, tp = np.int64(blocks.ctypes.data), np.int64(Y.ctypes.data), np.int64(tmp.ctypes.data)
    dims[1], dims[4] = k, n
    for s in range(s0, s1):
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
                    row = block_rows[r0 + w + i]
                    if row < own_end:
                        Y[row, j] -= tmp[j * below + i]
                    else:
                        spill[row - own_end, j] += tmp[j * below + i]


@njit(cache=True, nogil=True)
def _backward_block(lay, Y, s0, s1, tmp, refs):
    """Lᵀ X = Y in place over supernodes s1 > s ≥ s0 (`_forward_block`'s arguments): reads the rows below each,
    which the top or this run's later supernodes have finished, and writes only the run's own."""
    starts, row_ptr, block_rows, block_ptr, blocks = lay
    dims, scalars, chars = refs
    n, k = Y.shape
    z = blocks.itemsize
    d, s_, ch = np.int64(dims.ctypes.data), np.int64(scalars.ctypes.data), np.int64(chars.ctypes.data)
    blk, yp, tp = np.int64(blocks.ctypes.data), np.int64(Y.ctypes.data), np.int64(tmp.ctypes.data)
    dims[1], dims[4] = k, n
    for s in range(s1 - 1, s0 - 1, -1):
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
