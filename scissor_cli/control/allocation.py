"""The stroke step: the miss across the needle and the bounded, regularised least squares over any number of
cups (docs/model.md §6).

For one target with needle axis n (unit, (2,)) the miss is

    e⊥ = P e,   P = I − n nᵀ,   e = y_d − y,

and the along-axis part n·e is left to the insertion depth. The step is

    δs* = argmin ‖A δs − b‖² + λ ‖δs‖²   subject to  lb ≤ δs ≤ ub,

with A = P J, b = e⊥ (or A = J, b = e for `controller.error: position`),
solved on the stacked system [A; √λ I] δs ≈ [b; 0]: by least squares when
the unbounded optimum is admissible, else exactly over the faces of the
box for up to `FACES_MAX_CUPS` cups (`_on_faces`) and by scipy's
`lsq_linear` (BVLS) beyond.
λ = `REGULARISATION` (mm²/mm², dimensionless as J is): small enough that
the bias it puts on a step (relative λ/σ², σ the smallest singular value
that matters, ≥ 0.05 in the scenes shipped) is below 1e-3 and removed by
the feedback, large enough to pick the least-stroke step when several cups
could correct the same miss (A has more columns than rows).

Two bounded solves give the two numbers the loop needs:

* with the stroke limits only (lo − s ≤ δs ≤ hi − s): the *correctable*
  part A δs and the *uncorrectable* rest b − A δs that no admissible stroke
  can remove (what the tolerance and stall checks look at);
* with the speed limit over one control period as well
  (|δs| ≤ speed · Δt): the step handed to the PID. When the first solution
  already respects the speed limit it is reused.

**Spare cups.** With more cups than the miss needs (C ≥ 2 in 2-D), the
miss alone leaves a null space, and λ would pick the least-stroke step in
it, which may carry the target far along the needle to where the planner
never checked the corridor. So with C ≥ 2 the along-axis error gets a
small secondary weight μ = `ALONG_WEIGHT`:

    min ‖P J δs − P e‖² + μ (nᵀJ δs − nᵀe)² + λ‖δs‖²,

which, when both parts are reachable, cancels the miss exactly and brings
the target to the plan's y_d (where the corridor was verified); when they
are not, the miss wins by a factor 1/μ. With one cup μ = 0 (the square
problem of docs/model.md §6: the miss is cancelled exactly and the along
part left to the depth).

With zero cups nothing can be corrected: the step is empty and the whole
miss is uncorrectable.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.optimize import lsq_linear

#: λ of the regularised step (dimensionless, per mm² of stroke): see the module docstring.
REGULARISATION = 1.0e-6

#: μ: weight of the along-axis error when spare cups can also correct it (C ≥ 2); see the module docstring.
ALONG_WEIGHT = 1.0e-2

#: Up to this many cups a bounded step is solved exactly over the box's faces (`_on_faces`; one cup: a
#: clip), beyond by scipy's BVLS, whose set-up costs more than the whole face search for 1–2 cups.
FACES_MAX_CUPS = 3
#: BVLS's iterations per cup beyond FACES_MAX_CUPS (scipy's default, one per cup, can stop short of the optimum)
BVLS_MAX_ITER = 20

#: How the controller reads the error (config `controller.error`).
ERROR_MODES = ("miss", "position")


@dataclass(frozen=True)
class Step:
    """One step of the law. ds (C,) mm the speed-limited step; correctable, uncorrectable (d,) mm the parts
    of the driven error (e⊥ or e) that strokes within their limits can / cannot remove; along_mm the
    signed along-axis error n·e (0 without an axis); limited: the speed limit cut the step; at_limit: a
    stroke limit keeps the step from the unbounded optimum (part of `uncorrectable` is the limit's)."""

    ds: np.ndarray
    correctable: np.ndarray
    uncorrectable: np.ndarray
    along_mm: float
    limited: bool
    at_limit: bool = False
    along_correctable_mm: float = 0.0  # with spare cups: the along-axis part they can still remove


def _axis(direction: Optional[np.ndarray], mode: str = "miss") -> Optional[np.ndarray]:
    """The unit needle axis n (d,) the miss is taken across (d = 2, or 3 in a body), or None (the full error)."""
    if mode not in ERROR_MODES:
        raise ValueError(f"error mode must be one of {ERROR_MODES}, got {mode!r}")
    if mode == "position" or direction is None:
        return None
    n = np.asarray(direction, float)
    if n.shape not in ((2,), (3,)) or not np.all(np.isfinite(n)) or np.linalg.norm(n) == 0:
        return None
    return n / np.linalg.norm(n)


def projector(direction: Optional[np.ndarray], mode: str = "miss") -> Optional[np.ndarray]:
    """P = I − n nᵀ (d, d) for the needle axis `direction` (d,), or None (use the full error).

    None for `mode` "position" or when there is no finite axis.
    """
    n = _axis(direction, mode)
    return None if n is None else np.eye(n.size) - np.outer(n, n)


def miss_mm(error: np.ndarray, direction: Optional[np.ndarray]) -> float:
    """|P e| mm: the distance across the needle axis (the full |e| without an axis)."""
    P = projector(direction)
    e = np.asarray(error, float)
    return float(np.linalg.norm(e if P is None else P @ e))


def along_mm(error: np.ndarray, direction: Optional[np.ndarray]) -> float:
    """n·e mm: the signed error along the needle axis, for the depth (0 without an axis)."""
    if projector(direction) is None:
        return 0.0
    n = np.asarray(direction, float)
    return float(np.dot(n / np.linalg.norm(n), np.asarray(error, float)))


def _regularised(A: np.ndarray, b: np.ndarray, lam: float) -> np.ndarray:
    """argmin ‖A x − b‖² + λ‖x‖² (C,), unbounded: lstsq on [A; √λ I] x ≈ [b; 0] (closed form for one column)."""
    C = A.shape[1]
    if C == 1:
        a = A[:, 0]
        return np.array([np.dot(a, b) / (np.dot(a, a) + lam)])
    return np.linalg.lstsq(np.vstack([A, np.sqrt(lam) * np.eye(C)]), np.concatenate([b, np.zeros(C)]), rcond=None)[0]


def _objective(A: np.ndarray, b: np.ndarray, x: np.ndarray, lam: float) -> float:
    r = A @ x - b
    return float(np.dot(r, r) + lam * np.dot(x, x))


def _on_faces(A: np.ndarray, b: np.ndarray, lb: np.ndarray, ub: np.ndarray, lam: float) -> np.ndarray:
    """The bounded optimum when the unbounded one is not admissible: the best optimum over the box's faces.

    The objective is strictly convex (λ > 0), so its box minimum is unique
    and, the unbounded optimum lying outside, sits on the boundary: on some
    face x_i = lb_i or ub_i, where it is the minimum of the same kind of
    problem in the other C − 1 strokes (solved the same way). The least
    objective over the 2C faces is that minimum: exact, with no iteration
    (2C small solves of C − 1 strokes each, one stroke in closed form; used
    for 2 ≤ C ≤ FACES_MAX_CUPS).
    """
    C = A.shape[1]
    best, best_f = None, np.inf
    for i in range(C):  # a few cups, not elements
        rest = [k for k in range(C) if k != i]
        A_rest = A[:, rest]
        for v in (lb[i], ub[i]):
            x = np.empty(C)
            x[i] = v
            x[rest] = _in_box(A_rest, b - A[:, i] * v, lb[rest], ub[rest], lam)[0]
            f = _objective(A, b, x, lam)
            if f < best_f:
                best, best_f = x, f
    return best


def _in_box(A: np.ndarray, b: np.ndarray, lb: np.ndarray, ub: np.ndarray, lam: float) -> tuple[np.ndarray, bool]:
    """(argmin ‖A x − b‖² + λ‖x‖² over lb ≤ x ≤ ub (C,), whether the unbounded optimum was admissible)."""
    x = _regularised(A, b, lam)
    if (x >= lb).all() and (x <= ub).all():
        return x, True  # the unconstrained optimum is admissible: no bounded solve
    if A.shape[1] == 1:  # a convex parabola: its minimum over an interval is the clipped one
        return np.clip(x, lb, ub), False
    if A.shape[1] <= FACES_MAX_CUPS:
        return _on_faces(A, b, lb, ub, lam), False
    C = A.shape[1]
    Aa = np.vstack([A, np.sqrt(lam) * np.eye(C)])
    # BVLS stops after max_iter (scipy's default: C) whether or not it has converged, and may need more: a stroke
    # can enter and leave the active set; one that still has not (status 0) gets the exact face search instead
    r = lsq_linear(Aa, np.concatenate([b, np.zeros(C)]), bounds=(lb, ub), method="bvls", max_iter=BVLS_MAX_ITER * C)
    return (r.x if r.status >= 1 else _on_faces(A, b, lb, ub, lam)), False


def _bounded(A: np.ndarray, b: np.ndarray, lb: np.ndarray, ub: np.ndarray, lam: float) -> tuple[np.ndarray, bool]:
    """(argmin ‖A x − b‖² + λ‖x‖² over lb ≤ x ≤ ub (C,), whether the unbounded optimum was admissible).

    The box is widened to hold δs = 0; a cup with no room stays put.
    """
    lb, ub = np.minimum(lb, 0.0), np.maximum(ub, 0.0)  # δs = 0 is always admissible
    if (lb == ub).all():
        return lb.copy(), False
    free = lb < ub
    if not free.all():  # a cup with no room stays put
        x = np.zeros(A.shape[1])
        x[~free] = lb[~free]
        x[free] = _in_box(A[:, free], b - A[:, ~free] @ x[~free], lb[free], ub[free], lam)[0]
        return x, False
    return _in_box(A, b, lb, ub, lam)


def stroke_step(
    J: np.ndarray,
    error: np.ndarray,
    strokes: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    max_step: Optional[np.ndarray] = None,
    direction: Optional[np.ndarray] = None,
    mode: str = "miss",
    lam: float = REGULARISATION,
    seen: Optional[np.ndarray] = None,
) -> Step:
    """The law's step for J (d, C) mm/mm, error e = y_d − y (d,) mm at strokes (C,) mm within [lo, hi] (C,);
    d = 2 in a layer, 3 in a body.

    max_step (C,) mm: the most each cup may move in one control period
    (speed · Δt; None: no speed limit). direction (d,): the needle axis n;
    with mode "miss" the driven error is P e, else e. seen (d, d): the
    projector onto what the sensor observes (a body seen by one camera: not
    the depth along its view); the error's unseen components (NaN) count as
    0, and only the observed part S (P e) is driven.
    """
    e = np.asarray(error, float)
    d = e.size
    J = np.asarray(J, float).reshape(d, -1)
    if seen is not None:
        e = np.where(np.isfinite(e), e, 0.0)
    n = _axis(direction, mode)
    if n is None:
        A, b, along = J, e, 0.0
    else:
        P = np.eye(d) - np.outer(n, n)
        A, b, along = P @ J, P @ e, float(np.dot(n, e if seen is None else seen @ e))
    if seen is not None:
        A, b = seen @ A, seen @ b
    C = J.shape[1]
    if C == 0:
        return Step(np.zeros(0), np.zeros(d), b.copy(), along, False)
    As, bs = A, b
    if n is not None and C >= 2:  # spare cups: the along-axis error as a secondary objective
        w = np.sqrt(ALONG_WEIGHT)
        As, bs = np.vstack([A, w * (n @ J)[None]]), np.append(b, w * along)
    s = np.asarray(strokes, float)
    lb, ub = np.asarray(lo, float) - s, np.asarray(hi, float) - s
    full, inside = _bounded(As, bs, lb, ub, lam)
    corr = A @ full
    along_corr = abs(float(n @ J @ full)) if As is not A else 0.0
    ds, limited = full, False
    if max_step is not None:
        m = np.asarray(max_step, float)
        if np.any(np.abs(full) > m):
            ds, limited = _bounded(As, bs, np.maximum(lb, -m), np.minimum(ub, m), lam)[0], True
    return Step(ds, corr, b - corr, along, limited, not inside, along_corr)
