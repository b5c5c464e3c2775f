"""Compiled (numba) small loops of the needle's chord steps (docs/model.md §12, "The chord step's arithmetic").

Beyond its triangular solve and its gradient, a chord step of the needle's
solver (`chord.ChordSolver`) is a few dozen operations on arrays of a few
thousand entries (the free dofs) or a few dozen (the captured nodes). As
numpy calls, their overhead was more than half of an insertion step's time;
each loop here does one of them in one pass over its data. Each has a plain
numpy definition it replaces (named in its docstring), and the tests compare
the two.

Compiled on first use and cached on disk (numba's `cache=True`), like
`mechanics.compiled`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def hold_gap(x, captured, base, frame, ride, rows, out):
    """The hold's gap into out (m,) (`Hold.gap`), and its largest magnitude.

    x (N, d) positions, captured (P,) nodes, base (P, d) their positions at
    the last equilibrium, frame (d, d) the unit vectors (t₁ … t_{d−1}, n) as
    columns, ride (P,) mm, rows (m,) each constraint's coordinate in
    [t₀ … n₀ t₁ … n₁ …] (d per node, n last).
    """
    d = frame.shape[0]
    largest = 0.0
    for j in range(rows.size):
        k, c = rows[j] // d, rows[j] % d
        node = captured[k]
        value = 0.0
        for a in range(d):
            value += (x[node, a] - base[k, a]) * frame[a, c]
        out[j] = (ride[k] if c == d - 1 else 0.0) - value
        largest = max(largest, abs(out[j]))
    return largest


@njit(**_JIT)
def frame_compliance(block, frame):
    """Qᵀ block Q (dP, dP), Q = I ⊗ frame, made exactly symmetric (`ChordSolver.compliance`).

    block (dP, dP) a symmetric matrix on the captured nodes' dofs
    [x₀ y₀ (z₀) x₁ …], frame (d, d) the unit vectors (t₁ … t_{d−1}, n) as columns.
    """
    m, d = block.shape[0], frame.shape[0]
    out = np.empty((m, m))
    for i in range(0, m, d):
        for j in range(0, i + d, d):
            for a in range(d):
                for b in range(d):
                    v = 0.0
                    for c in range(d):
                        for e in range(d):
                            v += frame[c, a] * frame[e, b] * 0.5 * (block[i + c, j + e] + block[j + e, i + c])
                    out[i + a, j + b] = v
                    out[j + b, i + a] = v
    return out


@njit(**_JIT)
def held_residual(g, free, held, idx, n, stuck, dirichlet, force_floor):
    """`Hold.residual`: ‖g_f‖ with the hold's held components left out, over the force scale.

    g (dN,) mN; free (Nf,) the free dofs, held (Nf,) bool marking the
    captured nodes' ones, idx (dP,) those as [x₀ y₀ (z₀) x₁ …] (into free);
    n (d,) the axis; stuck (P,) bool. Across the axis a captured node is
    always held, along it while stuck: so of its d components only a
    slipping node's along one counts. The force scale is ‖g at the
    Dirichlet dofs‖ (the reactions), floored at force_floor mN
    (`Tissue.force_scale`).
    """
    d = n.size
    s = 0.0
    for i in range(free.size):
        if not held[i]:
            s += g[free[i]] * g[free[i]]
    for k in range(stuck.size):
        if not stuck[k]:
            along = 0.0
            for c in range(d):
                along += g[free[idx[d * k + c]]] * n[c]
            s += along * along
    r = 0.0
    for i in range(dirichlet.size):
        r += g[dirichlet[i]] * g[dirichlet[i]]
    return math.sqrt(s) / max(math.sqrt(r), force_floor)


@njit(**_JIT)
def captured_step(d0, idx, frame, rows, S_upper, A_rows, gap, mu, d_captured):
    """μ (m,) and the captured nodes' step (P, d) of a chord step (`ChordSolver.predict`), written into mu, d_captured.

    d0 (Nf,) = −K⁻¹g; in the captured nodes' frame (`ChordSolver.compliance`)
    with S = A[rows, rows] = UᵀU (S_upper: U in its upper triangle, LAPACK's
    dpotrf): μ = S⁻¹ (d0[rows] − gap), and the captured step d0 − A[:, rows] μ
    back in (x, y(, z)).
    """
    pd, m, d = idx.size, rows.size, frame.shape[0]
    d0_frame = np.empty(pd)
    for k in range(pd // d):
        for a in range(d):
            v = 0.0
            for c in range(d):
                v += d0[idx[d * k + c]] * frame[c, a]
            d0_frame[d * k + a] = v
    # Uᵀ y = b, then U μ = y
    for i in range(m):
        v = d0_frame[rows[i]] - gap[i]
        for k in range(i):
            v -= S_upper[k, i] * mu[k]
        mu[i] = v / S_upper[i, i]
    for i in range(m - 1, -1, -1):
        v = mu[i]
        for k in range(i + 1, m):
            v -= S_upper[i, k] * mu[k]
        mu[i] = v / S_upper[i, i]
    f = np.empty(d)
    for k in range(pd // d):
        for a in range(d):
            v = d0_frame[d * k + a]
            for j in range(m):
                v -= A_rows[d * k + a, j] * mu[j]
            f[a] = v
        for c in range(d):
            v = 0.0
            for a in range(d):
                v += frame[c, a] * f[a]
            d_captured[k, c] = v


@njit(**_JIT)
def chord_direction(d0, rows, mu, frame, responses):
    """The chord step on the free dofs (Nf,): d0 − K⁻¹Cᵀμ (`ChordSolver.complete`).

    With the hold's forces μ (m,) on their rows' coordinates in the captured
    nodes' frame (d, d), turned to each node's (x, y(, z)), and the nodes'
    kept responses K⁻¹e (dP, Nf) (`ChordSolver.responses`). The loop over
    the free dofs is written out per dimension: a loop over d inside it
    would keep numba from vectorising the pass that dominates the kernel.
    """
    pd, d = responses.shape[0], frame.shape[0]
    force = np.zeros(pd)
    for j in range(rows.size):
        force[rows[j]] = mu[j]
    out = d0.copy()
    f = np.empty(d)
    for k in range(pd // d):
        for c in range(d):
            v = 0.0
            for a in range(d):
                v += frame[c, a] * force[d * k + a]
            f[c] = v
        if d == 2:
            fx, fy = f[0], f[1]
            rx, ry = responses[2 * k], responses[2 * k + 1]
            for i in range(out.size):
                out[i] -= fx * rx[i] + fy * ry[i]
        else:
            fx, fy, fz = f[0], f[1], f[2]
            rx, ry, rz = responses[3 * k], responses[3 * k + 1], responses[3 * k + 2]
            for i in range(out.size):
                out[i] -= fx * rx[i] + fy * ry[i] + fz * rz[i]
    return out


@njit(**_JIT)
def moved(x, free, d):
    """x + d on the free dofs: the trial (N, d) for positions x (N, d) and a step d (Nf,); and whether d is finite."""
    trial = x.copy()
    flat = trial.reshape(-1)
    total = 0.0
    for i in range(free.size):
        flat[free[i]] += d[i]
        total += d[i]
    return trial, math.isfinite(total)


@njit(**_JIT)
def predicted_reactions(mu, stuck, d_captured, x, captured, base, n, ride, axial, lag):
    """The converged state's axial reactions (P,) mN and lags (P,) mm as one chord step predicts them, into axial, lag.

    μ (m,) the step's constraint forces in the hold's row order (every
    captured node's d − 1 across rows, then the stuck ones' along rows): a
    stuck node's reaction is −μ of its along row, a slipping one's 0. The
    lag is how far a node's predicted position x + d_captured has moved
    along n (d,) from base, less the ride.
    """
    p, d = captured.size, n.size
    j = (d - 1) * p
    for k in range(p):
        if stuck[k]:
            axial[k] = -mu[j]
            j += 1
        else:
            axial[k] = 0.0
        node = captured[k]
        v = 0.0
        for c in range(d):
            v += (x[node, c] + d_captured[k, c] - base[k, c]) * n[c]
        lag[k] = v - ride[k]


@njit(**_JIT)
def friction_rule(axial, lag, limit, free, slip, sign, lag_tol, force_error, position_error, release, against):
    """The active-set rule (`needle._Rule.apply`) into release, against (P,) bool; whether a decision is unclear.

    axial (P,) mN the needle's axial reactions, lag (P,) mm each node's lag
    behind the needle; limit (P,) mN f_s l_i; free (P,) stuck nodes that may
    be released, slip (P,) slipping ones; sign (P,) the kinetic friction's
    direction; lag_tol mm. A stuck node whose reaction exceeds its limit is
    released; a slipping node that moves against its friction (sign · lag >
    lag_tol) is flagged. Returns how many nodes are released or flagged, or
    −1 when a decision is unclear: its quantity lies within force_error mN
    or position_error mm of its threshold.
    """
    unclear = False
    changed = 0
    for k in range(axial.size):
        over = abs(axial[k]) - limit[k]
        ahead = sign[k] * lag[k] - lag_tol
        release[k] = free[k] and over > 0.0
        against[k] = slip[k] and ahead > 0.0
        changed += release[k] or against[k]
        if (free[k] and abs(over) <= force_error) or (slip[k] and abs(ahead) <= position_error):
            unclear = True
    return -1 if unclear else changed


@njit(**_JIT)
def best_elements(inv, origin, ok, points, best, worst, bary):
    """Each point's element: the one whose smallest barycentric coordinate is the largest (the first on ties).

    inv (E, d, d) the inverses of the elements' edge matrices (columns
    x_a − x_0), origin (E, d) their first vertices, ok (E,) whether the
    inverse exists (an element without one is never chosen), points (Q, d).
    Into best (Q,) the element, worst (Q,) its smallest coordinate (−inf if
    none is ok) and bary (Q, d + 1) its coordinates: the arg-max over every
    element that `tip_zone._consistent_loads` took with numpy arrays of
    Q × E × (d + 1).
    """
    n_points, d = points.shape
    lam = np.empty(d + 1)
    for q in range(n_points):
        top, arg = -np.inf, 0
        for e in range(inv.shape[0]):
            if not ok[e]:
                continue
            total, beaten = 0.0, False
            for i in range(d):
                value = 0.0
                for j in range(d):
                    value += inv[e, i, j] * (points[q, j] - origin[e, j])
                if value <= top:  # its smallest coordinate cannot beat the best: the common case, decided early
                    beaten = True
                    break
                lam[i + 1] = value
                total += value
            if beaten or 1.0 - total <= top:
                continue
            lam[0] = 1.0 - total
            top, arg = lam.min(), e
            bary[q] = lam
        best[q], worst[q] = arg, top
    return best
