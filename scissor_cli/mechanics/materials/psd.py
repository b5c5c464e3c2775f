"""Batched PSD projection of symmetric matrix stacks by eigendecomposition."""

from __future__ import annotations

import numpy as np


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
    |entry| before ``eigh`` (the projection is positively homogeneous), so
    huge finite entries do not overflow inside it; matrices whose smallest
    eigenvalue (of the scaled matrix) is ``>= 0`` are returned bit for bit,
    the others are rebuilt from their clamped eigenvalues, symmetrised and
    scaled back (0 if that overflows). The result is a new array.
    """
    out = np.array(C, dtype=np.float64, copy=True, order="C")
    if out.shape[0] == 0:
        return out
    out[~np.isfinite(out).all(axis=(1, 2))] = 0.0
    scale = np.abs(out).max(axis=(1, 2))
    scale[scale == 0.0] = 1.0
    w, V = np.linalg.eigh(out / scale[:, None, None])
    neg = w[:, 0] < 0.0
    if neg.any():
        Vn = V[neg]
        Cn = (Vn * np.maximum(w[neg], 0.0)[:, None, :]) @ np.swapaxes(Vn, 1, 2)
        Cn += np.swapaxes(Cn, 1, 2)  # V w Vᵀ is symmetric only to round-off
        Cn *= 0.5 * scale[neg][:, None, None]
        Cn[~np.isfinite(Cn).all(axis=(1, 2))] = 0.0
        out[neg] = Cn
    return out
