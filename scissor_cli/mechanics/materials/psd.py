"""Batched PSD projection of symmetric matrix stacks by eigendecomposition (numpy; the 3-D tangent's compiled)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


def project_psd(C, floor: float = 0.0) -> np.ndarray:
    """Batched symmetric PSD projection of ``C`` (M, k, k).

    Eigenvalues below ``floor`` are raised to ``floor`` (``np.linalg.eigh``
    on the stack, which reads the lower triangle, so ``C`` is assumed
    symmetric). Matrices whose smallest eigenvalue is already ``>= floor``
    are returned bit-for-bit unchanged; the result is always a new array.
    """
    C = np.asarray(C, dtype=np.float64)
    if C.ndim != 3 or C.shape[1] != C.shape[2]:
        raise ValueError(f"C must have shape (M, k, k), got {C.shape}")
    out = C.copy()
    if C.shape[0] == 0:
        return out
    # Only matrices that may have an eigenvalue below floor need the (costly,
    # batched) eigendecomposition: 4x4 ones that are clearly positive
    # definite, by Sylvester's criterion with a small shift, are skipped.
    maybe = ~_clearly_positive_definite(C, floor) if C.shape[1] == 4 else np.ones(C.shape[0], bool)
    if not maybe.any():
        return out
    w, V = np.linalg.eigh(C[maybe])
    bad = w[:, 0] < floor
    if bad.any():
        wb = np.maximum(w[bad], floor)
        Vb = V[bad]
        idx = np.flatnonzero(maybe)[bad]
        out[idx] = (Vb * wb[:, None, :]) @ np.swapaxes(Vb, 1, 2)
    return out


def _clearly_positive_definite(C: np.ndarray, floor: float) -> np.ndarray:
    """(M,) bool: C - (floor + δ) I is positive definite for each symmetric 4x4 C (leading minors > 0).

    δ = 1e-10 × the largest |entry| keeps round-off from passing a singular
    matrix; a False only sends the matrix to the exact eigendecomposition.
    """
    with np.errstate(all="ignore"):  # overflowing rows compare False and go to eigh
        shift = floor + 1e-10 * np.abs(C).max(axis=(1, 2))
        A = C - shift[:, None, None] * np.eye(4)
        a = [[A[:, i, j] for j in range(4)] for i in range(4)]
        m1 = a[0][0]
        m2 = a[0][0] * a[1][1] - a[0][1] * a[1][0]
        c00 = a[1][1] * a[2][2] - a[1][2] * a[2][1]
        c01 = a[1][0] * a[2][2] - a[1][2] * a[2][0]
        c02 = a[1][0] * a[2][1] - a[1][1] * a[2][0]
        m3 = a[0][0] * c00 - a[0][1] * c01 + a[0][2] * c02
        m4 = np.linalg.det(A)
        return (m1 > 0) & (m2 > 0) & (m3 > 0) & (m4 > 0)


def _project_psd_scaled(C: np.ndarray) -> np.ndarray:
    """PSD projection of a symmetric stack (M, k, k) with arbitrary entries; finite and PSD in every row.

    Non-finite matrices become 0. Each matrix is divided by its largest
    |entry| (the projection is positively homogeneous), so huge finite
    entries do not overflow; matrices whose smallest eigenvalue (of the
    scaled matrix) is ``>= 0`` are returned bit for bit, the others are
    rebuilt from their clamped eigenvalues (exactly symmetric) and scaled
    back (0 if that overflows). The result is a new C-ordered array.
    """
    C = np.ascontiguousarray(C, dtype=np.float64)
    out = np.empty_like(C)
    _project_rows(C, out)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _project_rows(C, out):
    """`_project_psd_scaled`'s loop over the stack: non-finite matrices 0, the others `project_matrix`."""
    M, k = C.shape[0], C.shape[1]
    L, A = np.empty((k, k)), np.empty((k, k))
    for e in range(M):
        finite = True
        for i in range(k):
            for j in range(k):
                finite = finite and np.isfinite(C[e, i, j])
        if not finite:
            out[e] = 0.0
            continue
        out[e] = C[e]
        project_matrix(out[e], L, A)


@njit(cache=True, nogil=True, error_model="numpy")
def project_matrix(C, L, A):
    """C (k, k), symmetric and finite, replaced in place by its PSD projection (the compiled loops' too).

    Scaled by its largest |entry| first. A matrix that a Cholesky factorisation of C/max|C| − 1e-10 I proves
    positive definite is left as it is without its eigendecomposition (most of the cost: LAPACK's per matrix);
    the others get it, and those with a negative eigenvalue are rebuilt from the clamped ones, exactly
    symmetric (0 if that overflows). L, A (k, k): scratch. The lower triangle is read, as by ``eigh``.
    """
    k = C.shape[0]
    big = 0.0
    for i in range(k):
        for j in range(k):
            big = max(big, abs(C[i, j]))
    if big == 0.0:
        return
    definite = True
    for j in range(k):
        s = C[j, j] / big - 1e-10
        for m in range(j):
            s -= L[j, m] * L[j, m]
        if not s > 0.0:
            definite = False
            break
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, k):
            t = C[i, j] / big
            for m in range(j):
                t -= L[i, m] * L[j, m]
            L[i, j] = t / L[j, j]
    if definite:
        return
    for i in range(k):
        for j in range(k):
            A[i, j] = C[max(i, j), min(i, j)] / big
    w, V = np.linalg.eigh(A)
    if w[0] >= 0.0:
        return
    finite = True
    for i in range(k):
        for j in range(i, k):
            s = 0.0
            for m in range(k):
                if w[m] > 0.0:
                    s += V[i, m] * w[m] * V[j, m]
            s *= big
            finite = finite and np.isfinite(s)
            C[i, j] = s
            C[j, i] = s
    if not finite:
        C[:, :] = 0.0
