"""A model-predictive control law: the next H frames' strokes planned as one convex QP (docs/model.md §22).

Each frame, with the controller model's J (d, C) mm/mm, the measured error
e0 = y_d − y (d,) mm and the commanded strokes s0 (C,) mm, the law plans
the next H frames' strokes s_1..s_H and applies the first move u_1:

    min  Σ_k ‖P (e0 − J δ_k)‖² + μ (nᵀ(e0 − J δ_k))² + ρ Σ_k ‖δ_k − δ_{k−1}‖²
    s.t. lo ≤ s0 + δ_k ≤ hi,   |δ_k − δ_{k−1}| ≤ max_step,   k = 1..H,

in the stroke offsets δ_k = s_k − s0 (δ_0 = 0, so u_k = δ_k − δ_{k−1}).
This is the error-and-action cost of §22 with the strokes as the variables
rather than the moves: the tracking term is then block-diagonal and the
moves' penalty tridiagonal, so the Hessian stays sparse (with the moves as
variables every s_k sums all earlier moves and the Hessian is dense), and
the constraint matrix, [I; first difference], depends on (C, H) only.
P = I − n nᵀ and μ = `allocation.ALONG_WEIGHT` for C ≥ 2 (the "spare cups"
of allocation.py: the miss alone leaves a null space in which the target
would drift along the needle); P = I, μ = 0 with error mode "position" or
no axis; μ = 0 with one cup. ρ (`action_weight`) > 0 makes the minimiser
unique.

The QP is solved by OSQP (ADMM), then *polished* here: the constraints
the ADMM iterate and its duals hold are imposed as equalities and the
reduced KKT system is solved densely (rows the result violates join, rows
whose multipliers pull the wrong way leave, for a few rounds). A polished
plan is kept only when it is feasible and its multipliers have the right
signs: the KKT conditions, which certify it as the exact optimum. OSQP
iterates in runs of doubling length (`FIRST_ITER`, then twice as many,
...), each followed by a polish, until one is certified; on a degenerate
optimum that no polish certifies OSQP's own iterate at `EPS` is used. A certificate usually comes after the
first run, long before the ADMM meets a tight EPS, which takes it thousands
of iterations when many speed limits are active over a long horizon.
OSQP's own polish is not used: in osqp 1.x it prints "Polishing not
needed" to stdout on every solve with no active constraint, whatever
`verbose` says (osqp/osqp#785), and it runs only once, at the end.

Strokes outside [lo, hi] (the limits changed under a command) cannot obey
the box and the speed limit at once, and a box widened to just what the
drives reach would leave the QP a feasible set without interior, which
OSQP may call infeasible. So the plan starts from the strokes clipped into
the box, s0' = clip(s0, lo, hi), with the error the model predicts there,
e0 − J (s0' − s0) (the same predicted lesion at every stroke), and its
first move, planned from s0', is cut to what the drives reach from s0:
such a cup comes back at full speed, and lands in the box when it is
within one move of it.

The solve is deterministic: a new OSQP instance per call (no warm start or
adapted ρ carried between calls), iteration-counted ρ adaptation (not the
timed one), no randomness. Its cost: benchmarks/bench_mpc.py.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any, Optional

import numpy as np
import osqp
import scipy.sparse as sp

from scissor_cli.control.allocation import ALONG_WEIGHT, projector

#: OSQP's absolute and relative tolerances (on the constraints, mm of stroke, and on the cost's gradient): what
#: the plan is accurate to when no polish certifies it (a degenerate optimum); a certified plan is exact to
#: round-off.
EPS = 1.0e-7

#: ADMM iterations before the first polish; each further run doubles the last, up to MAX_ITER in all.
FIRST_ITER = 100

#: ADMM iterations in all before the law gives up (MPCError).
MAX_ITER = 50_000

#: Equality-constrained solves per polish, each correcting the guessed active set (`_polished`).
POLISH_ROUNDS = 4

#: Relative slack of the polish's certificate (stationarity, feasibility, multipliers' signs): round-off.
CERTIFICATE_SLACK = 1.0e-9

#: OSQP's other settings. The polish is this module's (the module docstring). Warm starting lets each run
#: go on from the last one's iterate (every call sets up a new solver, so nothing crosses calls); ρ is
#: adapted every 50 iterations (adaptive_rho 1), not on a clock (2), which would make the iterates depend on
#: timing.
_SETTINGS = {"polishing": False, "warm_starting": True, "adaptive_rho": 1, "adaptive_rho_interval": 50}


class MPCError(ValueError):
    """OSQP did not solve the law's QP (its status in the message)."""


@lru_cache(maxsize=32)
def _structure(C: int, H: int) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The (C, H) problem's fixed parts: the constraint matrix A (2CH, CH) = [I; D ⊗ I_C], sparse and dense,
    and the upper-triangular CSC pattern of the Hessian: indptr, then each entry's row and column.

    Variable k·C + c is δ_{k+1} of cup c. The Hessian couples a cup's stroke with the other cups' in the
    same frame (JᵀWJ) and with its own in the neighbouring frames (ρ DᵀD); cached as the law asks for the
    same (C, H) every frame. Callers must not modify what is returned.
    """
    n = C * H
    D = sp.identity(n, format="csc") - sp.eye(n, k=-C, format="csc")
    A = sp.vstack([sp.identity(n, format="csc"), D], format="csc")
    A.sort_indices()
    indptr, indices, cols = [0], [], []
    for j in range(n):  # the columns in order; in each, the rows ascending
        k, c = divmod(j, C)
        rows = ([(k - 1) * C + c] if k else []) + [k * C + r for r in range(c + 1)]
        indices += rows
        cols += [j] * len(rows)
        indptr.append(len(indices))
    out = (A.toarray(), np.array(indptr, dtype=np.int64), np.array(indices, dtype=np.int64),
           np.array(cols, dtype=np.int64))
    for a in out:
        a.flags.writeable = False  # shared by every call with this (C, H)
    return (A, *out)


def _hessian(Q: np.ndarray, H: int, rho: float) -> np.ndarray:
    """kron(I_H, Q) + ρ kron(DᵀD, I_C) (CH, CH): the QP's Hessian (half the cost's), DᵀD the first difference's
    square with δ_0 = 0 (2 on the diagonal, 1 in the last frame, −1 beside it)."""
    L = 2.0 * np.eye(H) - np.eye(H, k=1) - np.eye(H, k=-1)
    L[-1, -1] = 1.0  # the last frame's stroke has no move after it
    return np.kron(np.eye(H), Q) + rho * np.kron(L, np.eye(Q.shape[0]))


def _bounds(s0, lo, hi, m, H: int) -> tuple[np.ndarray, np.ndarray]:
    """lb, ub (2CH,) of [I; D] δ from strokes s0 (C,) mm in [lo, hi]: each frame's stroke box, then the speed
    limit m (C,) mm on every move. δ = 0 is admissible.

    A frame's box that its cup cannot reach at full speed from s0 (k m within it after k frames; a cup with
    m = 0 among them) is left out (±inf): it holds wherever the speed limits do, and beside them it would
    repeat their normals — a degenerate optimum the polish cannot certify and the ADMM crawls towards.
    """
    k = np.repeat(np.arange(1, H + 1, dtype=float), s0.size)
    reach = k * np.tile(m, H)
    lo_k, hi_k = np.tile(lo - s0, H), np.tile(hi - s0, H)
    implied = (lo_k <= -reach) & (hi_k >= reach)
    return (np.concatenate([np.where(implied, -np.inf, lo_k), np.tile(-m, H)]),
            np.concatenate([np.where(implied, np.inf, hi_k), np.tile(m, H)]))


def _active(A: np.ndarray, lb: np.ndarray, ub: np.ndarray, x: np.ndarray, y: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """The rows (m,) bool an ADMM iterate x (n,) with duals y (m,) holds at their lower and at their upper
    bound: at the lower one when the slack there is smaller than the dual's pull (−y), at the upper one when
    ub − Ax < y (OSQP's own test); a row with lb = ub counts as lower (an equality). A (m, n), lb, ub (m,)."""
    z = A @ x
    equal = lb == ub
    return ((z - lb < -y) & ~equal) | equal, (ub - z < y) & ~equal


def _polished(K: np.ndarray, q: np.ndarray, A: np.ndarray, lb: np.ndarray, ub: np.ndarray, lower: np.ndarray,
              upper: np.ndarray) -> Optional[np.ndarray]:
    """The exact optimum x (n,) found from the guess that rows `lower` and `upper` (m,) bool are held at
    their bounds, or None without a certificate. K (n, n), q (n,): the QP's ½xᵀKx + qᵀx; A (m, n), lb, ub (m,):
    lb ≤ Ax ≤ ub.

    An early ADMM iterate often has not reached every face the optimum lies on: the rows the equality-
    constrained solution then violates join the guess, those whose multipliers pull the wrong way leave it,
    for up to POLISH_ROUNDS solves.
    """
    equal = lb == ub
    tol_p = CERTIFICATE_SLACK * max(1.0, np.abs(lb[np.abs(lb) < 1e20]).max(initial=0.0),
                                    np.abs(ub[np.abs(ub) < 1e20]).max(initial=0.0))
    violation = np.zeros(lb.shape)
    for _ in range(POLISH_ROUNDS):
        sol, rows, sign = _face_optimum(K, q, A, lb, ub, lower, upper, equal, violation)
        if sol is None:
            return None
        x, lam = sol[: K.shape[0]], sol[K.shape[0]:]
        tol_d = CERTIFICATE_SLACK * (1.0 + np.abs(q).max() + np.abs(K).max() * np.abs(sol).max())
        z = A @ x
        below, above, wrong = z < lb - tol_p, z > ub + tol_p, sign * lam < -tol_d
        # feasible, and the multipliers of K x + q + Aᵀλ = 0 push back from their faces (upper λ ≥ 0, lower
        # λ ≤ 0): the KKT conditions, so x is the optimum
        if not (below.any() or above.any() or wrong.any()):
            return x
        leave = np.zeros_like(lower)
        leave[rows[wrong]] = True
        lower, upper = (lower | below) & ~leave, (upper | above) & ~leave
        # of rows that repeat one another, the next solve holds the one this solution violates most: with
        # the same normal, a box face at 0 and a speed limit at −m cannot both hold, and only the tighter is
        # the optimum's
        violation = np.maximum(lb - z, z - ub).clip(min=0.0)
    return None


def _face_optimum(K: np.ndarray, q: np.ndarray, A: np.ndarray, lb: np.ndarray, ub: np.ndarray, lower: np.ndarray,
                  upper: np.ndarray, equal: np.ndarray, priority: np.ndarray
                  ) -> tuple[Optional[np.ndarray], np.ndarray, np.ndarray]:
    """(x and λ stacked, or None when the KKT system is singular; the rows (r,) held; their signs (r,): +1
    upper, −1 lower, 0 an equality) for min ½xᵀKx + qᵀx with the rows `lower`/`upper` at their bounds.

    Rows that repeat others (a cup at a box face in two frames and at full speed between them) are dropped:
    their multipliers are zero. Which of them stay is `_independent`'s choice: equalities first, then the
    rows in descending `priority` (m,).
    """
    rows = np.flatnonzero(lower | upper)
    if rows.size:
        order = np.lexsort((rows, -priority[rows], ~equal[rows]))  # equalities, then priority, then index
        rows = np.sort(_independent(A, rows[order]))
    n, r = K.shape[0], rows.size
    kkt = np.zeros((n + r, n + r))
    kkt[:n, :n], kkt[n:, :n] = K, A[rows]
    kkt[:n, n:] = kkt[n:, :n].T
    rhs = np.concatenate([-q, np.where(upper, ub, lb)[rows]])
    sign = np.where(upper, 1.0, np.where(equal, 0.0, -1.0))[rows]
    try:
        sol = np.linalg.solve(kkt, rhs)
    except np.linalg.LinAlgError:
        return None, rows, sign
    tol = CERTIFICATE_SLACK * (1.0 + np.abs(q).max() + np.abs(K).max() * np.abs(sol).max())
    # solved: an ill-conditioned K (ρ ≪ the tracking's curvature) may leave a residual
    if not np.all(np.isfinite(sol)) or np.abs(kkt @ sol - rhs).max() > tol:
        return None, rows, sign
    return sol, rows, sign


def _independent(A: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The rows (r,) of A (m, n), taken in the given order, that are not combinations of those kept before
    them (Gram–Schmidt, orthogonalised twice against round-off). The rows are few and short."""
    basis = np.zeros((0, A.shape[1]))
    keep = []
    for i in rows:
        v = A[i].astype(float)
        for _ in range(2):
            v = v - basis.T @ (basis @ v)
        norm = np.linalg.norm(v)
        if norm > 1e-9 * max(np.linalg.norm(A[i]), 1.0):
            keep.append(i)
            basis = np.vstack([basis, v / norm])
    return np.array(keep, dtype=rows.dtype)


def _plan(J, error_mm, strokes_mm, lo_mm, hi_mm, max_step_mm, horizon: int, action_weight: float,
          direction=None, mode: str = "miss") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(δ (H, C) mm the planned stroke offsets s_k − s0, the first move's lower and upper bounds (C,) mm)."""
    e = np.asarray(error_mm, float).reshape(-1)
    d = e.size
    J = np.asarray(J, float)
    if J.ndim != 2 or J.shape[0] != d:
        raise ValueError(f"J must be (d, C) with d = {d} (the error's size), got {J.shape}")
    C = J.shape[1]
    s0, lo, hi, m = (np.asarray(a, float).reshape(-1) for a in (strokes_mm, lo_mm, hi_mm, max_step_mm))
    if any(a.size != C for a in (s0, lo, hi, m)):
        raise ValueError(f"strokes, limits and max_step must each have one value per cup ({C})")
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(e)) and np.all(np.isfinite(s0))):
        raise ValueError("J, the error and the strokes must be finite")
    if np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo > hi):
        raise ValueError("stroke limits must satisfy lo ≤ hi")
    if np.any(np.isnan(m)) or np.any(m < 0):
        raise ValueError("max_step must be ≥ 0 (inf: no speed limit)")
    if int(horizon) != horizon or horizon < 1:
        raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
    if not (np.isfinite(action_weight) and action_weight > 0):
        raise ValueError(f"action_weight must be > 0 (it makes the plan unique), got {action_weight!r}")
    H = int(horizon)
    if direction is not None and np.size(direction) != d:
        raise ValueError(f"direction must have the error's size {d}, got {np.shape(direction)}")
    P = projector(direction, mode)  # validates the mode
    if P is None:
        W = np.eye(d)
    else:
        n = np.asarray(direction, float) / np.linalg.norm(direction)
        W = P + (ALONG_WEIGHT if C >= 2 else 0.0) * np.outer(n, n)  # PᵀP = P
    # the first move's bounds from s0 itself: the box or, outside it, back towards it, and the speed limit
    # last (clipped, so that (s0 − m) − s0 rounding past −m cannot take a bound beyond it)
    first = (np.clip(np.minimum(lo, s0 + m) - s0, -m, m), np.clip(np.maximum(hi, s0 - m) - s0, -m, m))
    if C == 0:
        return np.zeros((H, 0)), *first
    inside = np.clip(s0, lo, hi)  # the plan's origin (the module docstring); s0 itself when within the limits
    e = e - J @ (inside - s0)
    K = _hessian(J.T @ W @ J, H, float(action_weight))
    q = np.tile(-(J.T @ (W @ e)), H)
    lb, ub = _bounds(inside, lo, hi, m, H)
    return (inside - s0) + _solve(K, q, C, H, lb, ub).reshape(H, C), *first


def _solve(K: np.ndarray, q: np.ndarray, C: int, H: int, lb: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """argmin ½xᵀKx + qᵀx subject to lb ≤ [I; D] x ≤ ub (x: (CH,) mm): OSQP in runs of doubling length, each
    followed by the polish, until one is certified or OSQP meets EPS.

    Certified polishes usually come long before the ADMM meets a tight EPS (it converges slowly when many
    speed limits are active over a long horizon), and they are exact. MPCError when neither happens within
    MAX_ITER iterations, or OSQP finds the problem infeasible or non-convex (bad input).
    """
    A, A_dense, indptr, rows, cols = _structure(C, H)
    lc, uc = np.maximum(lb, -1e30), np.minimum(ub, 1e30)  # OSQP's infinity
    # A new instance every call: no iterate, adapted ρ or factorisation carries over between frames
    # (determinism). The builtin linear algebra is named, not probed for (mkl, cuda): the same on every
    # machine, and no imports per call.
    solver = osqp.OSQP(algebra="builtin")
    solver.setup(sp.csc_matrix((K[rows, cols], rows, indptr), shape=K.shape), q, A, lc, uc, verbose=False,
                 eps_abs=EPS, eps_rel=EPS, max_iter=min(FIRST_ITER, MAX_ITER), **_SETTINGS)
    done, run = 0, min(FIRST_ITER, MAX_ITER)
    tried = set()  # the active sets polished without a certificate: the same set gives the same answer
    while True:
        res = solver.solve(raise_error=False)
        done += res.info.iter
        status = res.info.status
        if status in ("solved", "solved inaccurate", "maximum iterations reached"):
            x_admm = np.array(res.x)  # a copy: the solver reuses its arrays
            lower, upper = _active(A_dense, lc, uc, x_admm, np.array(res.y))
            key = lower.tobytes() + upper.tobytes()
            x = None if key in tried else _polished(K, q, A_dense, lc, uc, lower, upper)
            if x is not None:
                return x
            tried.add(key)
            # "solved inaccurate" (EPS × 10) after a short run is not the answer yet: run on
            if status == "solved" or (status == "solved inaccurate" and done >= MAX_ITER):
                return x_admm
        if status not in ("solved inaccurate", "maximum iterations reached") or done >= MAX_ITER:
            raise MPCError(f"OSQP did not solve the MPC problem (C={C}, H={H}): status {status!r} after "
                           f"{done} iterations")
        run = min(2 * run, MAX_ITER - done)
        solver.update_settings(max_iter=run)


def mpc_step(J, error_mm, strokes_mm, lo_mm, hi_mm, max_step_mm, horizon: int, action_weight: float,
             direction=None, mode: str = "miss") -> np.ndarray:
    """The first move u_1 (C,) mm of the law's H-frame plan (the module docstring).

    J (d, C) mm of lesion per mm of stroke, d = 2 (a layer) or 3 (a body);
    error_mm e0 = desired − measured (d,) mm; strokes_mm s0 (C,) the
    commanded strokes; lo_mm, hi_mm (C,) the stroke limits; max_step_mm
    (C,) the most a cup moves in one frame (speed × frame period; inf: no
    limit); horizon H ≥ 1 frames; action_weight ρ > 0 (dimensionless) on
    Σ‖u_k‖²; direction (d,) the needle axis n (None or zeros: none);
    mode "miss" (across n) or "position" (the full error).

    The move obeys |u_1| ≤ max_step exactly and, with s0 in [lo, hi],
    lo ≤ s0 + u_1 ≤ hi (to one rounding of the sum): the solver's round-off
    is clipped away. A cup outside [lo, hi] comes back towards the box at
    full speed (max_step), into it when within max_step of it (the module
    docstring). Zero cups: an empty move. Raises MPCError
    when OSQP does not solve the QP, ValueError on inconsistent inputs.
    """
    delta, lb, ub = _plan(J, error_mm, strokes_mm, lo_mm, hi_mm, max_step_mm, horizon, action_weight,
                          _axis_or_none(direction), mode)
    return np.clip(delta[0], lb, ub)


def _axis_or_none(direction) -> Optional[np.ndarray]:
    """The plug-in protocol's all-zeros axis means none."""
    if direction is None:
        return None
    n = np.asarray(direction, float)
    return n if np.any(n) else None


class MPCLaw:
    """A controller with the plug-in protocol (`control.plugin.ControllerLaw`): reset(observation, info)
    and act(observation, info) -> velocities (C,) mm/s, the first move of `mpc_step` over one frame.

    horizon H (frames) and action_weight ρ (dimensionless): the QP's (the
    module docstring). After each `act`, `plan_mm` (H, C) holds the planned
    strokes s_1..s_H (mm); it is None before the first frame of a
    manipulation.
    """

    def __init__(self, horizon: int = 10, action_weight: float = 1.0e-3):
        if int(horizon) != horizon or horizon < 1:
            raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
        if not (np.isfinite(action_weight) and action_weight > 0):
            raise ValueError(f"action_weight must be > 0, got {action_weight!r}")
        self.horizon, self.action_weight = int(horizon), float(action_weight)
        self.n_cups: Optional[int] = None
        self.plan_mm: Optional[np.ndarray] = None

    def reset(self, observation: dict[str, Any], info: dict[str, Any]) -> None:
        """Start a manipulation: check that the frame's J, strokes and limits agree on the cups and clear
        the last plan. observation, info: the plug-in protocol's dictionaries."""
        C = np.asarray(observation["strokes_mm"]).size
        d = np.asarray(observation["desired_mm"]).size
        if np.shape(info["jacobian"]) != (d, C):
            raise ValueError(f"jacobian is {np.shape(info['jacobian'])}, expected ({d}, {C})")
        if not info["dt_s"] > 0:
            raise ValueError(f"dt_s must be > 0, got {info['dt_s']!r}")
        self.n_cups, self.plan_mm = C, None

    def act(self, observation: dict[str, Any], info: dict[str, Any]) -> np.ndarray:
        """The velocities (C,) mm/s that make this frame's move u_1 in dt_s: |v| ≤ speed_mm_per_s."""
        if self.n_cups is None:
            self.reset(observation, info)
        s0, dt = np.asarray(observation["strokes_mm"], float), float(info["dt_s"])
        speed = np.asarray(info["speed_mm_per_s"], float)
        # an axis the sensor does not see (NaN: a body under one camera) is no error to correct
        error = np.nan_to_num(np.asarray(observation["desired_mm"], float)
                              - np.asarray(observation["measured_mm"], float), nan=0.0)
        delta, lb, ub = _plan(info["jacobian"], error, s0, info["stroke_lo_mm"],
                              info["stroke_hi_mm"], speed * dt, self.horizon, self.action_weight,
                              _axis_or_none(observation["direction"]), info["error_mode"])
        self.plan_mm = s0 + delta
        # clip the velocity itself too: u/dt·dt may round past speed·dt by an ulp, the drives' limit is speed
        return np.clip(np.clip(delta[0], lb, ub) / dt, -speed, speed)
