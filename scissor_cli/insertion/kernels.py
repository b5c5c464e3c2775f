"""Compiled (numba) small loops of the needle's chord steps (docs/model.md §12, "Speed").

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

    x (N, 2) positions, captured (P,) nodes, base (P, 2) their positions at
    the last equilibrium, frame (2, 2) the unit vectors (t, n) as columns,
    ride (P,) mm, rows (m,) each constraint's coordinate in [t₀ n₀ t₁ n₁ …].
    """
    largest = 0.0
    for j in range(rows.size):
        k, c = rows[j] // 2, rows[j] % 2
        node = captured[k]
        value = (x[node, 0] - base[k, 0]) * frame[0, c] + (x[node, 1] - base[k, 1]) * frame[1, c]
        out[j] = (ride[k] if c == 1 else 0.0) - value
        largest = max(largest, abs(out[j]))
    return largest


@njit(**_JIT)
def frame_compliance(block, frame):
    """Qᵀ block Q (2P, 2P), Q = I ⊗ frame, made exactly symmetric (`ChordSolver.compliance`).

    block (2P, 2P) a symmetric matrix on the captured nodes' (x, y) dofs
    [x₀ y₀ x₁ y₁ …], frame (2, 2) the unit vectors (t, n) as columns.
    """
    m = block.shape[0]
    out = np.empty((m, m))
    for i in range(0, m, 2):
        for j in range(0, i + 2, 2):
            for a in range(2):
                for b in range(2):
                    v = 0.0
                    for c in range(2):
                        for d in range(2):
                            v += frame[c, a] * frame[d, b] * 0.5 * (block[i + c, j + d] + block[j + d, i + c])
                    out[i + a, j + b] = v
                    out[j + b, i + a] = v
    return out


@njit(**_JIT)
def held_residual(g, free, held, idx, n, stuck, dirichlet, force_floor):
    """`Hold.residual`: ‖g_f‖ with the hold's held components left out, over the force scale.

    g (2N,) mN; free (Nf,) the free dofs, held (Nf,) bool marking the
    captured nodes' ones, idx (2P,) those as [x₀ y₀ x₁ y₁ …] (into free);
    n (2,) the axis; stuck (P,) bool. Across the axis a captured node is
    always held, along it while stuck: so of its two components only a
    slipping node's along one counts. The force scale is ‖g at the
    Dirichlet dofs‖ (the reactions), floored at force_floor mN
    (`Tissue.force_scale`).
    """
    s = 0.0
    for i in range(free.size):
        if not held[i]:
            s += g[free[i]] * g[free[i]]
    for k in range(stuck.size):
        if not stuck[k]:
            along = g[free[idx[2 * k]]] * n[0] + g[free[idx[2 * k + 1]]] * n[1]
            s += along * along
    r = 0.0
    for i in range(dirichlet.size):
        r += g[dirichlet[i]] * g[dirichlet[i]]
    return math.sqrt(s) / max(math.sqrt(r), force_floor)


@njit(**_JIT)
def captured_step(d0, idx, frame, rows, S_upper, A_rows, gap, mu, d_captured):
    """μ (m,) and the captured nodes' step (P, 2) of a chord step (`ChordSolver.predict`), written into mu, d_captured.

    d0 (Nf,) = −K⁻¹g; in the captured nodes' frame (`ChordSolver.compliance`)
    with S = A[rows, rows] = UᵀU (S_upper: U in its upper triangle, LAPACK's
    dpotrf): μ = S⁻¹ (d0[rows] − gap), and the captured step d0 − A[:, rows] μ
    back in (x, y).
    """
    p2, m = idx.size, rows.size
    d0_frame = np.empty(p2)
    for k in range(p2 // 2):
        dx, dy = d0[idx[2 * k]], d0[idx[2 * k + 1]]
        d0_frame[2 * k] = dx * frame[0, 0] + dy * frame[1, 0]
        d0_frame[2 * k + 1] = dx * frame[0, 1] + dy * frame[1, 1]
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
    for k in range(p2 // 2):
        ft = d0_frame[2 * k]
        fn = d0_frame[2 * k + 1]
        for j in range(m):
            ft -= A_rows[2 * k, j] * mu[j]
            fn -= A_rows[2 * k + 1, j] * mu[j]
        d_captured[k, 0] = frame[0, 0] * ft + frame[0, 1] * fn
        d_captured[k, 1] = frame[1, 0] * ft + frame[1, 1] * fn


@njit(**_JIT)
def chord_direction(d0, rows, mu, frame, responses):
    """The chord step on the free dofs (Nf,): d0 − K⁻¹Cᵀμ (`ChordSolver.complete`).

    With the hold's forces μ (m,) on their rows' coordinates in the captured
    nodes' frame, turned to each node's (x, y), and the nodes' kept
    responses K⁻¹e (2P, Nf) (`ChordSolver.responses`).
    """
    p2 = responses.shape[0]
    force = np.zeros(p2)
    for j in range(rows.size):
        force[rows[j]] = mu[j]
    d = d0.copy()
    for k in range(p2 // 2):
        fx = frame[0, 0] * force[2 * k] + frame[0, 1] * force[2 * k + 1]
        fy = frame[1, 0] * force[2 * k] + frame[1, 1] * force[2 * k + 1]
        rx, ry = responses[2 * k], responses[2 * k + 1]
        for i in range(d.size):
            d[i] -= fx * rx[i] + fy * ry[i]
    return d


@njit(**_JIT)
def moved(x, free, d):
    """x + d on the free dofs: the trial (N, 2) for positions x (N, 2) and a step d (Nf,); and whether d is finite."""
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
    captured node's across row, then the stuck ones' along rows): a stuck
    node's reaction is −μ of its along row, a slipping one's 0. The lag is
    how far a node's predicted position x + d_captured has moved along n
    from base, less the ride.
    """
    p = captured.size
    j = p
    for k in range(p):
        if stuck[k]:
            axial[k] = -mu[j]
            j += 1
        else:
            axial[k] = 0.0
        node = captured[k]
        lag[k] = ((x[node, 0] + d_captured[k, 0] - base[k, 0]) * n[0]
                  + (x[node, 1] + d_captured[k, 1] - base[k, 1]) * n[1]) - ride[k]


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
