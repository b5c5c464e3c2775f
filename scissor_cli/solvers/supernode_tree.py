"""The supernodes' elimination tree cut into parts that a solve or a factorisation may work on at once.

A supernode's column updates only the rows of its ancestors in the
elimination tree, so two subtrees that share no supernode can be solved
and factored independently, and only their common ancestors (the top)
need both. Nested dissection's first separator makes such a tree: the
top is the chain from the root down to the first supernode with several
children, and the children's subtrees lie below it. CHOLMOD numbers the
supernodes in postorder, so each subtree is a run of consecutive
supernodes, and the parts and the top are runs too:

    part 0 = [cuts[0], cuts[1]), …, part K−1 = [cuts[K−1], cuts[K]), top = [cuts[K], S).

The children's subtrees are grouped into K runs of about equal work
(the factorisation's flops). The cut depends on the layout alone, never on
the threads, so a solve or factorisation gives the same numbers whether
its parts run in turn or at once (`runtime.in_parts`). A layout that is not
postordered, or a tree with no branch, gives one part with everything in
the top: the serial order.
"""

from __future__ import annotations

import numpy as np


def supernode_parents(starts: np.ndarray, row_ptr: np.ndarray, block_rows: np.ndarray) -> np.ndarray:
    """Each supernode's parent (S,) in the elimination tree, −1 for a root: the supernode owning its first row
    below its own columns. starts, row_ptr (S + 1,), block_rows as in `supernodal.SupernodalFactor`."""
    S = starts.size - 1
    owner = np.repeat(np.arange(S), np.diff(starts))
    width, height = np.diff(starts), np.diff(row_ptr)
    below = height > width
    parent = np.full(S, -1, np.int64)
    parent[below] = owner[block_rows[row_ptr[:-1][below] + width[below]]]
    return parent


def factor_flops(starts: np.ndarray, row_ptr: np.ndarray) -> np.ndarray:
    """Each supernode's share (S,) of a factorisation's flops: its diagonal block's Cholesky, the solve of its rows
    below and the update it sends its ancestors (w³/3 + (r − w) w² + (r − w)² w for w columns, r rows)."""
    w = np.diff(starts).astype(float)
    below = np.diff(row_ptr) - w
    return w ** 3 / 3.0 + below * w ** 2 + below ** 2 * w


def tree_cuts(starts: np.ndarray, row_ptr: np.ndarray, block_rows: np.ndarray, parts: int) -> np.ndarray:
    """The bounds (parts + 2,) of the parts and the top (module docstring), in supernodes."""
    S = starts.size - 1
    serial = np.zeros(parts + 2, np.int64)
    serial[-1] = S
    if parts < 2 or S < 2:
        return serial
    parent = supernode_parents(starts, row_ptr, block_rows)
    if np.any((parent >= 0) & (parent <= np.arange(S))):
        return serial  # not postordered: no runs to cut
    children = np.bincount(parent[parent >= 0], minlength=S + 1)
    roots = np.flatnonzero(parent < 0)
    children[S] = roots.size  # a forest hangs under a virtual root S
    parent = np.where(parent < 0, S, parent)
    branch = S
    while children[branch] == 1:
        branch = roots[0] if branch == S else int(np.flatnonzero(parent[:branch] == branch)[-1])
    if children[branch] == 0:
        return serial
    kids = np.flatnonzero(parent[:branch] == branch)  # their subtrees end at each and tile [0, branch)
    work = np.concatenate([[0.0], np.cumsum(factor_flops(starts, row_ptr)[:branch])])[kids + 1]
    total = work[-1]
    cuts = [0]
    for k in range(1, parts):  # each cut at the subtree end nearest to k/parts of the work
        cuts.append(int(kids[np.argmin(np.abs(work - total * k / parts))]) + 1)
    cuts += [branch, S]
    cuts = np.maximum.accumulate(np.array(cuts, np.int64))
    return cuts
