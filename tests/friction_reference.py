"""An independent implementation of docs/model.md §12's needle law (stick–slip with state), for the tests.

Written from the model's text, not from `scissor_cli.insertion`: it uses
only the tissue's energy, gradient and stiffness (checked against finite
differences by tests/test_materials.py and tests/test_fem.py) and scipy's
sparse LU. The needle's hold is imposed by elimination (each captured
node's dofs rewritten in the needle's frame), where scissor's solver uses
Schur-complement rows on a kept factorisation; each active-set pass is
solved by a plain Newton loop to a tight residual, with none of scissor's
early decisions, predictors or step splitting. Slow, but short and plain.
2-D layers only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

#: Newton's relative residual for every pass (scissor's passes stop at 1e-5)
TOL = 1e-9
MAX_PASSES = 50


@dataclass
class Outcome:
    """Per step: depth (K,) mm, target (K, 2) mm, needle force (K,) mN, stuck / slipping counts (K,)."""

    depth_mm: np.ndarray
    target: np.ndarray
    force_mN: np.ndarray
    stuck: np.ndarray
    slipping: np.ndarray


def insert(tissue, entry, axis, target_rest, depth_mm, step_mm, fs, fk, tip_mN, tip_zone_mm, capture_mm) -> Outcome:
    """The needle from entry (2,) along axis (2,) to depth_mm in steps of step_mm, from rest with the cups at 0.

    target_rest (2,) mm is followed by its rest triangle's barycentric weights.
    """
    n = np.asarray(axis, float) / np.linalg.norm(axis)
    weights, corners = _barycentric(tissue, np.asarray(target_rest, float))
    needle = _Needle(tissue, np.asarray(entry, float), n, fs, fk, tip_mN, tip_zone_mm, capture_mm)
    x, depth, rows = tissue.rest.copy(), 0.0, []
    while depth < depth_mm - 1e-9:
        h = min(step_mm, depth_mm - depth)
        # a step whose start would invert an element (three nodes of a triangle captured in one step all
        # ride to the tip) is split in 2, 4, … parts, as §12 says
        for parts in (1, 2, 4, 8, 16, 32, 64):
            saved = needle.state()
            try:
                y = x
                for k in range(1, parts + 1):
                    y, force = needle.step(y, depth + h * k / parts, h / parts)
                break
            except _Inverted:
                needle.restore(saved)
        else:
            raise RuntimeError(f"the reference's step at depth {depth:.3f} mm inverts an element in 64 parts")
        x, depth = y, depth + h
        rows.append((depth, weights @ x[corners], force, int(needle.stuck.sum()), int((~needle.stuck).sum())))
    depth_k, y_k, f_k, st_k, sl_k = zip(*rows)
    return Outcome(np.array(depth_k), np.array(y_k), np.array(f_k), np.array(st_k), np.array(sl_k))


class _Inverted(Exception):
    """A pass's start inverts an element."""


class _Needle:
    """The captured nodes (P,), their states stuck (P,) and the kinetic friction's direction sign (P,)."""

    def __init__(self, tissue, entry, n, fs, fk, tip_mN, tip_zone_mm, capture_mm):
        self.tissue, self.entry, self.n = tissue, entry, n
        self.t = np.array([-n[1], n[0]])
        self.fs, self.fk, self.tip_mN, self.zone, self.capture = fs, fk, tip_mN, tip_zone_mm, capture_mm
        self.free = np.flatnonzero(np.all(tissue.free_index.reshape(-1, 2) >= 0, axis=1))
        self.captured, self.stuck, self.sign = np.zeros(0, int), np.zeros(0, bool), np.zeros(0)

    def state(self):
        return self.captured.copy(), self.stuck.copy(), self.sign.copy()

    def restore(self, saved):
        self.captured, self.stuck, self.sign = saved

    def step(self, x, depth, h):
        """The equilibrium (N, 2) after the tip reached depth (mm) by h, from x (N, 2); and the needle force (mN)."""
        n, entry, fk = self.n, self.entry, self.fk
        # capture: free nodes behind the tip, within the radius of the axis, not yet captured
        rel = x[self.free] - entry
        s, across = rel @ n, np.abs(rel @ self.t)
        new = self.free[(s >= -1e-9) & (s <= depth) & (across <= self.capture)]
        new = new[~np.isin(new, self.captured)]
        ride = np.concatenate([np.full(self.captured.size, h), np.clip(depth - (x[new] - entry) @ n, 0.0, h)])
        captured = np.concatenate([self.captured, new])
        stuck = np.concatenate([self.stuck, np.ones(new.size, bool)])
        sign = np.concatenate([self.sign, np.ones(new.size)])
        lengths = _shares((x[captured] - entry) @ n, depth)
        tip_load = _tip_load(self.tissue, x, self.free, entry + depth * n, n, self.tip_mN, self.zone)
        for _ in range(MAX_PASSES):
            loads = tip_load.copy()
            slip = ~stuck
            loads.reshape(-1, 2)[captured[slip]] += (fk * lengths[slip] * sign[slip])[:, None] * n
            y = _solve(self.tissue, x, captured, stuck, ride, n, loads)
            g = self.tissue.energy_gradient(y)[1] - loads
            axial = g.reshape(-1, 2)[captured] @ n  # what the needle supplies to each captured node
            advance = (y[captured] - x[captured]) @ n
            release = stuck & (np.abs(axial) > self.fs * lengths * (1 + 1e-9))
            catch_up = ~stuck & (sign * (advance - ride) > 1e-9 * h)
            if not (release.any() or catch_up.any()):
                break
            if release.any():  # catching up is judged once every stuck node holds within f_s
                sign[release] = np.sign(axial[release])
                stuck = stuck & ~release
            else:
                stuck = stuck | catch_up
        else:
            raise RuntimeError(f"the reference's active set did not settle at depth {depth:.3f} mm")
        self.captured, self.stuck, self.sign = captured, stuck, sign
        force = axial[stuck].sum() + (fk * lengths[~stuck] * sign[~stuck]).sum() + self.tip_mN
        return y, force


def _barycentric(tissue, p):
    """Weights (3,) and corner nodes (3,) of the rest triangle holding p."""
    X = tissue.rest
    tri = tissue.mesh.triangles
    a, b, c = X[tri[:, 0]], X[tri[:, 1]], X[tri[:, 2]]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    l1 = ((p[0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (p[1] - a[:, 1])) / det
    l2 = ((b[:, 0] - a[:, 0]) * (p[1] - a[:, 1]) - (p[0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
    w = np.stack([1 - l1 - l2, l1, l2], axis=1)
    k = int(np.argmax(w.min(axis=1)))
    return w[k], tri[k]


def _shares(axial, depth):
    """Half of each neighbouring gap along the axis; the first also to the entry, the last to the tip."""
    order = np.argsort(axial, kind="stable")
    s = np.clip(axial[order], 0.0, depth)
    bounds = np.concatenate([[0.0], (s[1:] + s[:-1]) / 2, [depth]])
    out = np.empty(axial.size)
    out[order] = np.diff(bounds)
    return out


def _tip_load(tissue, x, free, tip, n, tip_mN, zone):
    """F_tip along n as the consistent nodal loads of the kernel (1 − (r/R)²)² over the half-disc of radius R ahead of
    the tip: a midpoint rule on a polar grid, each point located in the deformed mesh by brute force; the shares of
    held nodes go to the free ones (else everything to the nearest free node)."""
    t = np.array([-n[1], n[0]])
    rho = (np.arange(40) + 0.5) / 40 * zone
    theta = (np.arange(48) + 0.5) / 48 * np.pi - np.pi / 2
    R, TH = np.meshgrid(rho, theta, indexing="ij")
    weight = ((1 - (R / zone) ** 2) ** 2 * R).ravel()
    p = tip + (R * np.cos(TH)).ravel()[:, None] * n + (R * np.sin(TH)).ravel()[:, None] * t
    tri = tissue.mesh.triangles
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    near = np.flatnonzero(np.linalg.norm((a + b + c) / 3 - tip, axis=1) < zone + 20.0)
    a, b, c, det, tri = a[near], b[near], c[near], det[near], tri[near]
    P = p[:, None, :]  # every point against every nearby triangle
    l1 = ((P[..., 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (P[..., 1] - a[:, 1])) / det
    l2 = ((b[:, 0] - a[:, 0]) * (P[..., 1] - a[:, 1]) - (P[..., 0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
    inside = (l1 >= -1e-12) & (l2 >= -1e-12) & (1 - l1 - l2 >= -1e-12)
    q = np.flatnonzero(inside.any(axis=1))
    k = np.argmax(inside[q], axis=1)  # the first triangle holding each point
    bary = np.stack([1 - l1[q, k] - l2[q, k], l1[q, k], l2[q, k]], axis=1)
    load = np.zeros(x.shape[0])
    np.add.at(load, tri[k].ravel(), (weight[q, None] * bary).ravel())
    held = np.ones(x.shape[0], bool)
    held[free] = False
    load[held] = 0.0
    if load.sum() <= 0:
        load[free[int(np.argmin(np.linalg.norm(x[free] - tip, axis=1)))]] = 1.0
    out = np.zeros(x.size)
    out.reshape(-1, 2)[:] = (tip_mN * load / load.sum())[:, None] * n
    return out


def _solve(tissue, x_prev, captured, stuck, ride, n, loads):
    """The equilibrium with the hold eliminated: stuck nodes at x_prev + ride·n, slipping ones free along n only."""
    return _solve_from(tissue, x_prev, x_prev, captured, stuck, ride, n, loads)


def _solve_from(tissue, x_start, x_prev, captured, stuck, ride, n, loads):
    """`_solve` for one part of the ride, from x_start (N, 2)."""
    base = x_start.copy()
    base[captured[stuck]] = x_prev[captured[stuck]] + ride[stuck, None] * n
    fdofs = tissue.free_dofs
    nf = fdofs.size
    # columns of T: every free dof of an uncaptured node, and n on each slipping node's two dofs
    held = np.zeros(x_prev.shape[0], bool)
    held[captured] = True
    plain = np.flatnonzero(~held[fdofs // 2])
    slip_nodes = captured[~stuck]
    rows = np.concatenate([plain, tissue.free_index[2 * slip_nodes], tissue.free_index[2 * slip_nodes + 1]])
    cols = np.concatenate([np.arange(plain.size), np.tile(plain.size + np.arange(slip_nodes.size), 2)])
    vals = np.concatenate([np.ones(plain.size), np.full(slip_nodes.size, n[0]), np.full(slip_nodes.size, n[1])])
    T = sp.csr_matrix((vals, (rows, cols)), shape=(nf, plain.size + slip_nodes.size))

    def objective(q):
        x = base.copy().ravel()
        x[fdofs] += T @ q
        U, g = tissue.energy_gradient(x.reshape(-1, 2), require_positive_J=True)
        if g is None or not np.isfinite(U):
            return np.inf, None, x
        return U - loads @ x, g - loads, x

    q = np.zeros(T.shape[1])
    phi, g, x = objective(q)
    if g is None:
        raise _Inverted
    scale = max(np.linalg.norm(tissue.energy_gradient(x.reshape(-1, 2))[1][tissue.dirichlet_dofs]),
                tissue.force_floor)
    for _ in range(100):
        gr = T.T @ g[fdofs]
        if np.linalg.norm(gr) <= TOL * scale:
            return x.reshape(-1, 2)
        K = T.T @ tissue.stiffness_free(x.reshape(-1, 2)) @ T
        dq = spsolve(K.tocsc(), -gr)
        if not gr @ dq < 0:  # not a descent direction far from equilibrium: the PSD-projected Hessian
            K = T.T @ tissue.stiffness_free(x.reshape(-1, 2), project=True) @ T
            dq = spsolve(K.tocsc(), -gr)
        step = 1.0
        while step > 1e-10:
            phi_new, g_new, x_new = objective(q + step * dq)
            if g_new is not None and phi_new <= phi + 1e-4 * step * (gr @ dq) + 1e-12 * abs(phi):
                break
            step /= 2
        else:
            raise RuntimeError("the reference's line search failed")
        q, phi, g, x = q + step * dq, phi_new, g_new, x_new
    raise RuntimeError("the reference's Newton loop did not converge")
