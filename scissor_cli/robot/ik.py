"""Inverse kinematics of the puncture module, in closed form (docs/model.md §11).

For a needle tip (3,) mm and a horizontal approach direction (3,) in the
robot base frame, the joints q = (d1, d2, d3, θ4, d5) in mm/rad: θ4 from the
direction, d1 from the height, and d2, d3 linear in the free insertion d5,
whose feasible values form an interval (`linear_interval`). An unreachable
pose still gets the exact solution with the least limit violation, and a
report of which joint is out by how much. Paper-structure chains only
(`RobotModel.require_closed_form`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scissor_cli.robot.chain import LIMIT_TOL, RobotModel


@dataclass
class IKResult:
    """Joint values for one tip/approach request.

    q: (5,) d1, d2, d3 (mm), θ4 (rad), d5 (mm). When unreachable it is the
        exact solution with the least total limit violation (it still places
        the tip; some joints are outside their limits).
    reachable: every joint inside its limits.
    violations: joint name → signed excess over the nearest limit, mm or
        deg (> 0 above the upper limit, < 0 below the lower); empty if
        reachable.
    reason: human-readable explanation.
    """

    q: np.ndarray
    reachable: bool
    violations: dict[str, float]
    reason: str


@dataclass
class IKBatch:
    """Vectorised IK: q (M,5), reachable (M,), violation (M,5) signed, mm/rad."""

    q: np.ndarray
    reachable: np.ndarray
    violation: np.ndarray


def _excess(x: np.ndarray, lo, hi) -> np.ndarray:
    """Signed distance outside [lo, hi] (0 inside, >0 above, <0 below)."""
    return np.where(x > hi, x - hi, np.where(x < lo, x - lo, 0.0))


def linear_interval(b: np.ndarray, k: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """The interval of t with lo ≤ b + k·t ≤ hi, element-wise: (t_lo, t_hi), each shaped like b.

    b, k (M,) arrays in the units of the limits lo, hi (a joint value b + k·t
    that moves linearly with a parameter t, e.g. d2 or d3 with the insertion
    d5). An empty interval is (inf, −inf); k = 0 gives (−inf, inf) or
    (inf, −inf) as b alone lies inside or outside [lo, hi]. Intervals of
    several joints intersect by max of the t_lo, min of the t_hi.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - b) / k, (hi - b) / k
    t_lo = np.where(k > 0, t1, t2)
    t_hi = np.where(k > 0, t2, t1)
    # k == 0: every t or none, depending on b alone
    inside = (b >= lo) & (b <= hi)
    zero = k == 0
    t_lo = np.where(zero, np.where(inside, -np.inf, np.inf), t_lo)
    t_hi = np.where(zero, np.where(inside, np.inf, -np.inf), t_hi)
    return t_lo, t_hi


def _wrap_into(angle: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The 2π-representative of angle closest to [lo, hi] (inside if possible)."""
    cands = angle[:, None] + 2 * np.pi * np.array([-1.0, 0.0, 1.0])
    dist = np.abs(_excess(cands, lo, hi))
    return cands[np.arange(angle.size), np.argmin(dist, axis=1)]


#: the largest vertical component of a unit approach the horizontal needle is taken to have
HORIZONTAL_TOL = 1e-6


def _normalised_horizontal(approach: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(approach, axis=1)
    if np.any(norm < 1e-12):
        raise ValueError("approach direction has zero length")
    u = approach / norm[:, None]
    if np.any(np.abs(u[:, 2]) > HORIZONTAL_TOL):
        raise ValueError(
            "approach must be horizontal (z component 0): this robot keeps the needle "
            f"in a horizontal plane; got z = {u[np.argmax(np.abs(u[:, 2])), 2]:.3g} after normalising"
        )
    return u


def ik_batch(tip, approach, robot: RobotModel) -> IKBatch:
    """IK for M requests: tip (M,3) mm, approach (M,3) → IKBatch.

    θ4 from the direction, d1 from the height; d2 and d3 are linear in the
    free insertion d5, so the feasible d5 is an interval: take its lower end
    (shortest insertion). If it is empty, take the d5 in its limits that
    minimises the total violation of d2 and d3 (ties → shortest).
    Raises ValueError for a non-horizontal or zero approach.
    """
    cf = robot.require_closed_form()
    tip = np.atleast_2d(np.asarray(tip, dtype=float))
    u = _normalised_horizontal(np.atleast_2d(np.asarray(approach, dtype=float)))
    tip, u = np.broadcast_arrays(tip, u)
    lo, hi = robot.lower, robot.upper
    off = cf.offsets
    tol = LIMIT_TOL

    # axis = (−cos Θ4, −sin Θ4, 0) with Θ4 = θ4 + offset
    th4 = _wrap_into(np.arctan2(-u[:, 1], -u[:, 0]) - off[3], lo[3], hi[3])
    c, s = np.cos(th4 + off[3]), np.sin(th4 + off[3])
    q1 = tip[:, 2] - cf.a5 - off[0]
    # q3 = b3 + c·d5, q2 = b2 + s·d5 (from tip = C + (d5 + d6)·axis)
    b3 = tip[:, 0] - cf.a1 - off[2] + (cf.d6 + off[4]) * c
    b2 = tip[:, 1] - cf.a3 - off[1] + (cf.d6 + off[4]) * s

    # Feasibility with a round-off slack; the chosen d5 from the exact limits
    # so that a configuration on a limit maps back onto it.
    i3 = linear_interval(b3, c, lo[2] - tol, hi[2] + tol)
    i2 = linear_interval(b2, s, lo[1] - tol, hi[1] + tol)
    t_hi = np.minimum.reduce([np.full_like(b3, hi[4] + tol), i3[1], i2[1]])
    d5_ok = np.maximum.reduce([np.full_like(b3, lo[4] - tol), i3[0], i2[0]]) <= t_hi
    t_lo = np.maximum.reduce([np.full_like(b3, lo[4]), linear_interval(b3, c, lo[2], hi[2])[0],
                              linear_interval(b2, s, lo[1], hi[1])[0]])
    t_lo = np.minimum(t_lo, t_hi)

    # Infeasible d5 interval: least total d2+d3 violation is piecewise
    # linear and convex in d5, so its minimum sits at a breakpoint.
    with np.errstate(divide="ignore", invalid="ignore"):
        cands = np.stack([np.full_like(b3, lo[4]), np.full_like(b3, hi[4]),
                          (lo[2] - b3) / c, (hi[2] - b3) / c, (lo[1] - b2) / s, (hi[1] - b2) / s], axis=1)
    cands = np.clip(np.where(np.isfinite(cands), cands, lo[4]), lo[4], hi[4])
    total = (np.abs(_excess(b3[:, None] + c[:, None] * cands, lo[2], hi[2]))
             + np.abs(_excess(b2[:, None] + s[:, None] * cands, lo[1], hi[1])))
    best = total <= total.min(axis=1, keepdims=True) + 1e-9
    d5_fallback = np.where(best, cands, np.inf).min(axis=1)

    q5 = np.where(d5_ok, np.clip(t_lo, lo[4], hi[4]), d5_fallback)
    q = np.stack([q1, b2 + s * q5, b3 + c * q5, th4, q5], axis=1)
    viol = _excess(q, lo, hi)
    reachable = d5_ok & np.all(np.abs(viol[:, [0, 3]]) <= tol, axis=1)
    # round-off may leave a feasible value a hair outside: put it on the limit
    q = np.where(reachable[:, None], np.clip(q, lo, hi), q)
    viol[reachable] = 0.0
    return IKBatch(q=q, reachable=reachable, violation=viol)


def _describe(robot: RobotModel, q: np.ndarray, viol: np.ndarray) -> tuple[dict[str, float], str]:
    names, rev = robot.joint_names, robot.revolute_mask
    violations: dict[str, float] = {}
    parts = []
    for j, v in enumerate(viol):
        if v == 0.0:
            continue
        conv = np.rad2deg if rev[j] else (lambda x: x)
        unit = "deg" if rev[j] else "mm"
        amount = float(conv(v))
        violations[names[j]] = amount
        side, limit = ("above its upper", robot.upper[j]) if v > 0 else ("below its lower", robot.lower[j])
        parts.append(f"{names[j]} = {float(conv(q[j])):.3f} {unit} is {side} limit "
                     f"{float(conv(limit)):.3f} {unit} by {abs(amount):.3f} {unit}")
    if not parts:
        return {}, "reachable"
    j5 = robot.n_joints - 1
    return violations, ("unreachable: " + "; ".join(parts)
                        + f" (least-violation insertion {names[j5]} = {q[j5]:.3f} mm)")


def ik(tip, approach, robot: RobotModel) -> IKResult:
    """IK for one request: tip (3,) mm in the base frame, approach (3,)
    (horizontal; the direction the needle travels). Never raises for an
    unreachable pose — see `IKResult`; raises ValueError for bad input."""
    tip = np.asarray(tip, dtype=float).reshape(3)
    approach = np.asarray(approach, dtype=float).reshape(3)
    res = ik_batch(tip[None], approach[None], robot)
    q, viol = res.q[0], res.violation[0]
    violations, reason = _describe(robot, q, viol)
    return IKResult(q=q, reachable=bool(res.reachable[0]), violations=violations, reason=reason)
