"""Held dofs in a Newton solve, and nodes held across a direction by a rotated frame (docs/model.md §12).

Split from `solvers.newton` (its only user, with the needle's chord solver
for its residual): what a `Conditions` holds, turned into what the Newton
loop does with K_ff and the gradient.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.common import Conditions, relative_residual


class Held:
    """Held free dofs (H,) in a solve: zero in every step, identity rows in every K_ff.

    Keeping them in the system as identity rows (instead of dropping them)
    leaves the sparsity pattern, and so the symbolic factorisation, unchanged.

    Nodes held across a direction (`Conditions.along_nodes`) are solved in
    rotated coordinates: each such node's d dofs become its components in
    an orthonormal frame R (d, d) whose first d − 1 columns are the held
    directions and whose last is the free one (2-D: [u u⊥]; 3-D:
    [t₁ t₂ t₁×t₂]). K_ff becomes RᵀK_ffR (the same node blocks, so the same
    pattern) and the first d − 1 rotated dofs are held like any other.
    `vector` and `matrix` map to these coordinates, `unrotate` maps a step
    back; with no such nodes all three are the identity.
    """

    def __init__(self, tissue: Tissue, conditions: Conditions):
        plain = conditions.held_free(tissue)
        #: (A, d) free positions of each rotated node's dofs, (A, d, d) its frame
        self.dofs, self.frame = conditions.along_free(tissue)
        d = tissue.dim
        held_rotated = self.dofs[:, :d - 1].ravel()
        self.pos = np.concatenate([plain, held_rotated]) if len(self.dofs) else plain
        self.n_free = tissue.free_dofs.size
        self._mask: tuple | None = None

    def __bool__(self) -> bool:
        return bool(len(self.pos))

    def rotate(self, v: np.ndarray) -> np.ndarray:
        """v (Nf,) in the rotated coordinates, Rᵀv per rotated node (v itself when nothing is rotated)."""
        if not len(self.dofs):
            return v
        v = v.copy()
        v[self.dofs] = np.einsum("aij,ai->aj", self.frame, v[self.dofs])
        return v

    def unrotate(self, q: np.ndarray) -> np.ndarray:
        """q (Nf,) in rotated coordinates back to the x/y(/z) dofs: R q per rotated node."""
        if not len(self.dofs):
            return q
        q = q.copy()
        q[self.dofs] = np.einsum("aij,aj->ai", self.frame, q[self.dofs])
        return q

    def vector(self, g: np.ndarray) -> np.ndarray:
        """g (Nf,) rotated, with the held entries zeroed (a copy when there are any)."""
        if not len(self.pos):
            return g
        g = self.rotate(g.copy())
        g[self.pos] = 0.0
        return g

    def matrix(self, K: sp.csr_matrix) -> sp.csr_matrix:
        """K (Nf, Nf), upper triangle, rotated, with held rows and columns replaced by the identity."""
        if not len(self.pos):
            return K
        if self._mask is None or self._mask[0] != K.nnz:
            rows = np.repeat(np.arange(K.shape[0]), np.diff(K.indptr))
            is_held = np.zeros(K.shape[0], bool)
            is_held[self.pos] = True
            touched = is_held[rows] | is_held[K.indices]
            diag = touched & (rows == K.indices)
            self._mask = (K.nnz, touched, diag, self._rotation_plan(K, rows, touched))
        _, touched, diag, plan = self._mask
        K = K.copy()
        if plan is not None:
            rotated, idx, cr, cc = plan
            K.data[rotated] = np.einsum("ei,eij,ej->e", cr, K.data[idx], cc)
        K.data[touched] = 0.0
        K.data[diag] = 1.0
        return K

    def _rotation_plan(self, K: sp.csr_matrix, rows: np.ndarray, touched: np.ndarray):
        """For each stored entry (r, c) of RᵀKR that rotation changes: its d×d source entries and weights.

        (RᵀKR)[r, c] = Σ_ij R[a_i, r] K[a_i, b_j] R[b_j, c] over the d dofs
        a_i of r's node and b_j of c's; the node blocks of P1 elements are
        full, so every K[a_i, b_j] is a stored entry. An unrotated dof is its
        own single source (weights (1, 0, …)).
        """
        if not len(self.dofs):
            return None
        n = K.shape[0]
        d = self.dofs.shape[1]
        cols = K.indices
        is_rot = np.zeros(n, bool)
        is_rot[self.dofs.ravel()] = True
        rotated = np.flatnonzero((is_rot[rows] | is_rot[cols]) & ~touched)
        # per dof: the d source dofs and their weights (R's column)
        src = np.repeat(np.arange(n)[:, None], d, axis=1)
        w = np.zeros((n, d))
        w[:, 0] = 1.0
        for j in range(d):  # (d columns, not a loop over nodes)
            src[self.dofs[:, j]] = self.dofs
            w[self.dofs[:, j]] = self.frame[:, :, j]
        r, c = rows[rotated], cols[rotated]
        a, b = src[r][:, :, None], src[c][:, None, :]
        keys = np.minimum(a, b) * n + np.maximum(a, b)  # (E, d, d), symmetric lookup in the upper triangle
        stored = rows.astype(np.int64) * n + cols
        order = np.argsort(stored, kind="stable")
        pos = np.searchsorted(stored[order], keys)
        pos = np.minimum(pos, stored.size - 1)
        idx = order[pos]
        ok = stored[idx] == keys
        cr, cc = w[r], w[c]
        weight = cr[:, :, None] * cc[:, None, :]
        if not np.all(ok | (weight == 0.0)):
            raise ValueError("a rotated node's block is not stored in K_ff's pattern")
        return rotated, np.where(ok, idx, 0), cr, cc

    def residual(self, tissue: Tissue, grad: np.ndarray) -> float:
        """The relative residual (`relative_residual`) without the held (rotated) components."""
        if not len(self.dofs):
            return relative_residual(tissue, grad, self.pos)
        g = self.vector(grad[tissue.free_dofs])
        return float(np.linalg.norm(g)) / tissue.force_scale(grad)
