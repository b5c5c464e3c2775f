"""The 3-D nodal element's energy and gradient in three compiled passes, split into parts (docs/model.md §21).

The needle's chord steps and every line search ask for this gradient
most. Each pass is a loop over one part of the elements or the nodes:

1. the elements: F_e, their own share of the deviatoric stress, and
   v_a = Σ_{e∋a} V_e det F_e / 4 and F̄_a = Σ_{e∋a} V_e F_e / (4 V_a)
   summed at the corners, each part into its own arrays;
2. the nodes: J_a, p_a and P̄_a from the parts' sums, added in order;
3. the elements again: each element's stress P_e + Σ_{a∈e} P̄_a / 4 +
   p̄_e cof F_e against ∇N, each part's forces into its own vector.

The parts are fixed (`runtime.MOST_THREADS` of them, the elements and the
nodes cut in equal runs of their numbering) and their sums are added in
order, so the numbers are the same whether the parts run one after another
or at once (`runtime.in_parts`, `runtime.set_threads`). Equal to the
term-by-term sum of `mechanics.nodal` to round-off. numba's on-disk cache
keys on this file alone: after editing `compiled3d`'s closed forms, touch
this file too.

Arrays: x (N, 3) mm; corners (4, M) and grad_rows (4, 3, M) as in
`fem.FEOperators`; volume (M,) mm³.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from scissor_cli import runtime
from scissor_cli.mechanics import compiled3d

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def element_pass(x, corners, grad_rows, volume, material, tension_only, e0, e1, F, S, Fbar, v):
    """Pass 1 over elements e0 ≤ e < e1: F_e and P_e (their deviatoric share) into F, S (M, 9), and V_e F_e / 4,
    V_e J_e / 4 added at the corners into Fbar (N, 9) and v (N,), zeroed first; returns their energy (µJ), or nan
    for an element it cannot take."""
    mu, _, eta, fiber = material
    f, c, P, a = np.empty(9), np.empty(9), np.empty(9), np.empty(3)
    Fbar[:] = 0.0
    v[:] = 0.0
    U = 0.0
    for e in range(e0, e1):
        compiled3d._deformation(x, corners, grad_rows, e, f)
        a[0], a[1], a[2] = fiber[e, 0], fiber[e, 1], fiber[e, 2]
        psi, J = compiled3d._stress(f, c, a, mu[e], 0.0, eta[e], tension_only, P)[:2]
        if not compiled3d._takes(psi, P, J):
            return math.nan
        V = volume[e]
        U += psi * V
        for p in range(9):
            F[e, p] = f[p]
            S[e, p] = P[p]
        share = 0.25 * V
        for k in range(4):
            node = corners[k, e]
            v[node] += share * J
            for p in range(9):
                Fbar[node, p] += share * f[p]
    return U


@njit(**_JIT)
def node_pass(rest_volume, kappa, material, tension_only, n0, n1, Fbar_parts, v_parts, stress, pressure):
    """Pass 2 over nodes n0 ≤ a < n1: F̄_a and J_a from the parts' sums (Fbar_parts (K, N, 9), v_parts (K, N),
    added in order), P̄_a V_a into stress (N, 9) and p_a = κ_a (J_a − 1) into pressure (N,); returns their energy
    (µJ), or nan for a node it cannot take."""
    mu, _, eta, fiber = material
    f, c, P, a = np.empty(9), np.empty(9), np.empty(9), np.empty(3)
    U = 0.0
    for node in range(n0, n1):
        Va = rest_volume[node]
        vol = 0.0
        for k in range(v_parts.shape[0]):
            vol += v_parts[k, node]
        Ja = vol / Va
        U += 0.5 * Va * kappa[node] * (Ja - 1.0) ** 2
        pressure[node] = kappa[node] * (Ja - 1.0)
        for p in range(9):
            s = 0.0
            for k in range(Fbar_parts.shape[0]):
                s += Fbar_parts[k, node, p]
            f[p] = s / Va
        a[0], a[1], a[2] = fiber[node, 0], fiber[node, 1], fiber[node, 2]
        psi, J = compiled3d._stress(f, c, a, mu[node], 0.0, eta[node], tension_only, P)[:2]
        if not compiled3d._takes(psi, P, J):
            return math.nan
        U += psi * Va
        for p in range(9):
            stress[node, p] = P[p]
    return U


@njit(**_JIT)
def force_pass(corners, grad_rows, volume, e0, e1, F, S, stress, pressure, out):
    """Pass 3 over elements e0 ≤ e < e1: their stress (P_e + Σ_a P̄_a / 4 + p̄_e cof F_e) against ∇N into out
    (3N,) mN, zeroed first."""
    f, c, P = np.empty(9), np.empty(9), np.empty(9)
    out[:] = 0.0
    for e in range(e0, e1):
        p_bar = 0.0
        for p in range(9):
            P[p] = S[e, p]
            f[p] = F[e, p]
        for k in range(4):
            node = corners[k, e]
            p_bar += 0.25 * pressure[node]
            for p in range(9):
                P[p] += 0.25 * stress[node, p]
        compiled3d._cofactor(f, c)
        for p in range(9):
            P[p] += p_bar * c[p]
        compiled3d._add_forces(out, P, volume[e], corners, grad_rows, e)
    return 0.0


def energy_gradient(ops, element_params, node_params, rest_volume: np.ndarray, kappa: np.ndarray,
                    x: np.ndarray) -> tuple[float, np.ndarray] | None:
    """U (µJ) and ∇U (3N,) mN of the 3-D nodal element in three compiled passes; None where the term-by-term path
    must answer: 2-D, the `linear` model, an element or node it cannot take. element_params / node_params: the
    deviatoric shares per element (M) and per node (N); rest_volume (N,) mm³, kappa (N,) kPa."""
    if ops.dim != 3 or element_params.model == "linear":
        return None
    M, N, K = ops.corners.shape[1], len(rest_volume), runtime.MOST_THREADS
    material, tension_only = compiled3d._material(element_params)
    node_material, _ = compiled3d._material(node_params)
    kappa = np.ascontiguousarray(kappa, float)
    x = np.ascontiguousarray(x, dtype=np.float64)
    F, S = np.empty((M, 9)), np.empty((M, 9))
    Fbar, v, out = np.empty((K, N, 9)), np.empty((K, N)), np.empty((K, 3 * N))
    stress, pressure = np.empty((N, 9)), np.empty(N)
    ec, nc = runtime.part_bounds(M), runtime.part_bounds(N)
    args = (ops.corners, ops.grad_rows, ops.volume)
    U = sum(runtime.in_parts(*[
        lambda k=k: element_pass(x, *args, material, tension_only, ec[k], ec[k + 1], F, S, Fbar[k], v[k])
        for k in range(K)]))
    U += sum(runtime.in_parts(*[
        lambda k=k: node_pass(rest_volume, kappa, node_material, tension_only, nc[k], nc[k + 1], Fbar, v, stress,
                              pressure) for k in range(K)]))
    if not math.isfinite(U):
        return None
    runtime.in_parts(*[lambda k=k: force_pass(*args, ec[k], ec[k + 1], F, S, stress, pressure, out[k])
                       for k in range(K)])
    return float(U), out.sum(axis=0)
