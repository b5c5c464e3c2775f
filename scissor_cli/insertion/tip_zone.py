"""The tip's cutting force spread over the tissue just ahead of the tip (docs/model.md §12, "Tip force").

F_tip acts along the axis n on the tissue being cut: the half-disc (2-D) or
half-ball (3-D) of radius R = `tip_zone_mm` ahead of the tip, with the
smooth kernel k(p) = (1 − (r/R)²)², r = |p − tip|. Its nodal loads are the
kernel integrated against the elements' linear shape functions (consistent
loads), f_i = F_tip ∫ φ_i k / ∫ k, by a fixed quadrature of the zone (rings
× directions) located in the deformed mesh. So the loads move continuously
with the tip whatever the mesh: a node that the tip passes keeps the share
its elements give it instead of dropping it at once (the kernel evaluated
at the nodes did: with one or two nodes in a zone finer than the mesh the
whole force jumped to the next node ahead at every capture, a jump that no
step size resolves). Shares falling on a Dirichlet node (the zone
reaching a fixed face or a cup) are given to the free ones, so they sum to
F_tip; a zone outside the tissue (the tip at the skin) integrates over the
part inside.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from scissor_cli.insertion import kernels
from scissor_cli.insertion.capture import node_edges
from scissor_cli.mechanics.tissue import Tissue

#: Gauss–Legendre points across the zone's radius, and directions over its half circle (2-D) or, per polar
#: ring, the azimuths of its half sphere (3-D)
RINGS = 5
DIRECTIONS_2D = 12
POLAR_3D, AZIMUTHS_3D = 4, 10
#: a quadrature point lies in an element when its barycentric coordinates are all ≥ −this
INSIDE_TOL = 1e-9


@lru_cache(maxsize=None)
def unit_stencil(d: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature of the kernel over the unit half-disc / half-ball along the first axis.

    Returns points (Q, d) in the frame (n, t₁ … t_{d−1}) and weights (Q,)
    summing to 1 (∫ k over the half zone is normalised away).
    """
    g, gw = np.polynomial.legendre.leggauss(RINGS)
    rho, rho_w = 0.5 * (g + 1.0), 0.5 * gw
    radial = (1.0 - rho ** 2) ** 2 * rho ** (d - 1) * rho_w  # kernel × the area (volume) element's ρ^{d−1}
    if d == 2:
        theta = (np.arange(DIRECTIONS_2D) + 0.5) / DIRECTIONS_2D * np.pi - 0.5 * np.pi
        dirs = np.stack([np.cos(theta), np.sin(theta)], axis=1)
        dir_w = np.full(theta.size, 1.0)
    else:  # equal-area polar rings (uniform in cos θ over the half sphere), uniform azimuths
        cos_t = 1.0 - (np.arange(POLAR_3D) + 0.5) / POLAR_3D
        phi = (np.arange(AZIMUTHS_3D) + 0.5) / AZIMUTHS_3D * 2.0 * np.pi
        ct, ph = np.meshgrid(cos_t, phi, indexing="ij")
        st = np.sqrt(1.0 - ct ** 2)
        dirs = np.stack([ct.ravel(), (st * np.cos(ph)).ravel(), (st * np.sin(ph)).ravel()], axis=1)
        dir_w = np.full(dirs.shape[0], 1.0)
    points = (rho[:, None, None] * dirs[None]).reshape(-1, d)
    weights = (radial[:, None] * dir_w[None]).ravel()
    return points, weights / weights.sum()


@dataclass(frozen=True)
class ZoneMesh:
    """What the search for the zone's elements needs of a mesh, made once per insertion.

    reach (N,) mm: twice the longest rest edge at each node (a point inside
    an element lies within that of the element's corner with the longest
    edge, unless the element is stretched to twice its size);
    elements_of: node → its elements, as CSR (indptr (N + 1,), indices).
    """

    reach: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray


def zone_mesh(tissue: Tissue) -> ZoneMesh:
    """The `ZoneMesh` of the tissue's rest mesh."""
    corners = tissue.ops.corners  # (d + 1, M)
    n_nodes, m = tissue.mesh.n_nodes, corners.shape[1]
    reach = node_edges(tissue.mesh.nodes, corners)[1]
    order = np.argsort(corners.ravel(), kind="stable")
    indptr = np.concatenate([[0], np.cumsum(np.bincount(corners.ravel(), minlength=n_nodes))])
    return ZoneMesh(2.0 * reach, indptr, (order % m).astype(np.int64))


def tip_weights(tissue: Tissue, x: np.ndarray, tip: np.ndarray, frame: np.ndarray, zone_mm: float,
                candidates: np.ndarray, zone: ZoneMesh) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (Z,) and their shares (Z,) summing to 1 of the tip force; the nearest candidate if the zone holds none.

    x (N, d) mm positions, tip (d,) mm, frame (d, d) rows (n, t₁ … t_{d−1})
    with n the axis, zone_mm R, candidates (F,) the nodes that may take a
    share (the free ones), zone the mesh's `ZoneMesh`.
    """
    d = x.shape[1]
    unit, w = unit_stencil(d)
    points = tip + zone_mm * unit @ frame  # (Q, d)
    close = np.flatnonzero(np.linalg.norm(x - tip, axis=1) <= zone_mm + zone.reach)
    starts, counts = zone.indptr[close], zone.indptr[close + 1] - zone.indptr[close]
    first = np.cumsum(counts) - counts  # where each node's run starts in the gathered list
    near = np.unique(zone.indices[np.repeat(starts - first, counts) + np.arange(counts.sum())])
    sub = tissue.ops.corners[:, near]
    xe = x[sub]  # (d + 1, E, d)
    overlap = np.all((xe.max(axis=0) >= tip - zone_mm) & (xe.min(axis=0) <= tip + zone_mm), axis=1)
    nodes, shares = _consistent_loads(xe[:, overlap], sub[:, overlap], points, w)
    free = np.zeros(x.shape[0], bool)
    free[candidates] = True
    keep = free[nodes] & (shares > 0.0)
    if not np.any(keep):
        k = int(np.argmin(np.linalg.norm(x[candidates] - tip, axis=1)))
        return candidates[k:k + 1], np.ones(1)
    nodes, shares = nodes[keep], shares[keep]
    return nodes, shares / shares.sum()


def _consistent_loads(xe: np.ndarray, corners: np.ndarray, points: np.ndarray, w: np.ndarray):
    """Each point's weight (Q,) spread over the corners of the element (of xe (d + 1, E, d), corners (d + 1, E))
    holding it by its barycentric coordinates: (nodes (Z,), summed shares (Z,)); points in no element drop out."""
    if corners.shape[1] == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    edges = np.transpose(xe[1:] - xe[0], (1, 2, 0))  # (E, d, d): columns x_a − x_0
    det = np.linalg.det(edges)
    ok = np.abs(det) > 1e-300
    inv = np.zeros_like(edges)
    inv[ok] = np.linalg.inv(edges[ok])
    n_points = points.shape[0]
    best, worst, bary = np.empty(n_points, np.int64), np.empty(n_points), np.zeros((n_points, points.shape[1] + 1))
    kernels.best_elements(inv, np.ascontiguousarray(xe[0]), ok, points, best, worst, bary)
    q = np.flatnonzero(worst >= -INSIDE_TOL)
    if q.size == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    e = best[q]
    b = np.clip(bary[q], 0.0, None)
    b /= b.sum(axis=1, keepdims=True)
    node_ids = corners[:, e].T.ravel()  # (q · (d + 1),)
    contributions = (b * w[q, None]).ravel()
    nodes, inverse = np.unique(node_ids, return_inverse=True)
    return nodes, np.bincount(inverse, contributions, minlength=nodes.size)
