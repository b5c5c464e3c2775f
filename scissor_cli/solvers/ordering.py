"""Fill-reducing orderings of a sparse symmetric matrix's unknowns, by node (`linear.Factorization`'s
nested dissection; docs/model.md §13, "Linear algebra in 3-D")."""

from __future__ import annotations

import numpy as np
import pymetis
import scipy.sparse as sp


def nested_dissection(A: sp.csr_matrix, groups: np.ndarray | None = None) -> np.ndarray:
    """A fill-reducing permutation p (n,) of symmetric A (its pattern, or one triangle's) by METIS.

    p[k] is the unknown eliminated k-th (CHOLMOD's `P A Pᵀ`). With `groups`
    (n,), the node numbers of the unknowns, METIS orders the (3x smaller)
    graph of the nodes and each node's unknowns follow in their own order:
    the same fill as ordering the unknowns, for a third of the time, and
    whole node blocks in the factor's supernodes.
    """
    n = A.shape[0]
    if groups is None:
        groups = np.arange(n)
    G, node_of = node_graph(A, groups)
    if G.nnz == 0:
        return np.arange(n)
    perm = np.asarray(pymetis.nested_dissection(pymetis.CSRAdjacency(G.indptr, G.indices))[0])
    rank = np.empty(G.shape[0], np.int64)
    rank[perm] = np.arange(G.shape[0])
    return np.lexsort((np.arange(n), rank[node_of]))


def node_graph(A: sp.spmatrix, groups: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """The graph of the nodes whose unknowns A (n, n) couples (its pattern, or one triangle's): the adjacency
    (m, m) of the m distinct `groups` (n,), both triangles, no diagonal, indices sorted (METIS's input); and each
    unknown's node (n,), 0..m-1 in the order of the group numbers."""
    A = sp.csr_matrix(A)
    nodes, node_of = np.unique(np.asarray(groups), return_inverse=True)
    rows = np.repeat(node_of, np.diff(A.indptr))
    cols = node_of[A.indices]
    off = rows != cols
    G = sp.csr_matrix((np.ones(int(off.sum())), (rows[off], cols[off])), shape=(len(nodes), len(nodes)))
    G = (G + G.T).tocsr()
    G.sort_indices()
    return G, node_of
