"""Numeric Cholesky factorisations in float32, supernode by supernode, on a CHOLMOD factor's layout (docs/model.md
§12, "The chord step's arithmetic").

CHOLMOD factors in float64 only, and a 3-D refactorisation that only
preconditions or steps (the needle's chord steps, Newton's conjugate
gradients, the trackers' responses) needs float32 blocks: here the values
go straight into float32 blocks of the layout `solvers.supernodal` solves
with and are factored left-looking, by BLAS and LAPACK called from the
compiled loop (linked as there: `supernodal._link_blas`). The elimination
tree's parts (`supernode_tree`) are factored at once where the process has
the threads, their common top after them.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from scissor_cli import runtime
from scissor_cli.solvers.supernodal import (
    SupernodalFactor,
    _by_reference,
    _link_blas,
    _sgemm,
    _spotrf,
    _ssyrk,
    _strsm,
)


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
        cuts = layout.cuts
        #: each column's supernode (n,) and each supernode's part of the tree (S,): `_factor_run`'s lists
        self._owner = np.repeat(np.arange(layout.starts.size - 1), np.diff(layout.starts))
        self._home = np.repeat(np.arange(cuts.size - 1), np.diff(cuts))
        most = max(1, int(np.max(heights)) * int(np.max(np.diff(layout.starts))))
        parts = cuts.size - 2
        # each part's descendant update and row places, kept alive beside the compiled loops
        self._update, self._place = np.empty((parts, most), np.float32), np.empty((parts, layout.n), np.int64)

    def matches(self, A) -> bool:
        """Whether A (upper triangle, CSR) could have this factorizer's pattern (its order and stored count)."""
        return A.shape == (self.layout.n, self.layout.n) and A.nnz == self.nnz

    def factor(self, data: np.ndarray) -> SupernodalFactor | None:
        """The float32 factor of the matrix whose stored values (in the pattern's order) are data (nnz,), or None
        when float32 breaks down on it (a diagonal block not positive definite)."""
        lay, cuts = self.layout, self.layout.cuts
        K, S = cuts.size - 2, lay.starts.size - 1
        blocks = np.zeros(int(lay.block_ptr[-1]), np.float32)
        blocks[self._into] = data
        _link_blas()
        heads, after, next_row = np.full((K + 1, S), -1, np.int64), np.full(S, -1, np.int64), np.zeros(S, np.int64)
        refs = [_by_reference(np.float32) for _ in range(K)]
        tree = (lay.starts, lay.row_ptr, lay.block_rows, lay.block_ptr)
        lists = (self._owner, self._home, heads, after, next_row)
        failed = max(runtime.in_parts(*[
            lambda k=k: _factor_run(tree, blocks, lists, cuts[k], cuts[k + 1], (self._place[k], self._update[k]),
                                    refs[k]) for k in range(K)]))
        if not failed:  # the top, once every part is done
            failed = _factor_run(tree, blocks, lists, cuts[K], S, (self._place[0], self._update[0]), refs[0])
        return None if failed else SupernodalFactor(lay.starts, lay.row_ptr, lay.block_ptr, lay.block_rows, blocks,
                                                    lay.perm, cuts)


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def _factor_run(lay, blocks, lists, s0, s1, scratch, refs):
    """Supernodes s0 ≤ j < s1 of blocks (float32, A's lower triangle scattered in) overwritten with L,
    left-looking: 0, or 1 + the supernode whose diagonal block was not positive definite.

    A supernode's descendants wait in linked lists under the supernode of
    their next row (as CHOLMOD's supernodal numeric factorisation keeps
    them), one list per part of the tree (a supernode's list: its part,
    `supernode_tree`), so the parts' runs may go at once: a part's
    descendants are its own, and the top's supernodes walk every part's
    list, in order. lay: (starts, row_ptr, block_rows, block_ptr); lists:
    (owner (n,) each column's supernode, home (S,) each supernode's list,
    heads (K + 1, S), after and next_row (S,): the links and each
    descendant's next row); scratch: (place (n,), update), this run's own,
    as refs (`_by_reference`).
    """
    starts, row_ptr, block_rows, block_ptr = lay
    owner, home, heads, after, next_row = lists
    place, update = scratch
    dims, scalars, chars = refs
    z = 4
    d, sc, ch = np.int64(dims.ctypes.data), np.int64(scalars.ctypes.data), np.int64(chars.ctypes.data)
    blk, up = np.int64(blocks.ctypes.data), np.int64(update.ctypes.data)
    for j in range(s0, s1):
        c0, w = starts[j], starts[j + 1] - starts[j]
        r0, r = row_ptr[j], row_ptr[j + 1] - row_ptr[j]
        for k in range(r):
            place[block_rows[r0 + k]] = k
        for part in range(heads.shape[0]):
            e = heads[part, j]
            heads[part, j] = -1
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
                if p2 < er:  # on to the supernode of its next row, in its own part's list
                    o = owner[block_rows[e0 + p2]]
                    after[e], heads[home[e], o] = heads[home[e], o], e
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
            after[j], heads[home[j], o] = heads[home[j], o], j
    return 0
