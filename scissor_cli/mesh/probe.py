"""Points carried by the mesh: targets and markers follow their rest triangles (docs/model.md §1).

A point p inside the mesh keeps the barycentric coordinates of the triangle
that contains it at rest; its deformed position is the same combination of
the deformed vertices. The same weights map nodal vectors (a Jacobian's
columns, a displacement) to the point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scissor_cli.mesh.mesh import Mesh, locate


@dataclass(frozen=True)
class TargetProbe:
    """K points carried by their rest triangles (docs/model.md §1).

    nodes (K, d + 1) int: the containing triangle's (tetrahedron's)
    vertices; bary (K, d + 1): the barycentric weights at rest (rows sum to
    1); tri_idx (K,) the element, for reference. A body's lesion is the mean
    of its region (`LinearSimplex.mean_probe`): its row holds the region's
    nodes, P columns (P ≥ d + 1; a narrower row of the same probe is padded
    with weight 0), and every use reads the columns as weights of nodes.
    """

    tri_idx: np.ndarray
    nodes: np.ndarray
    bary: np.ndarray

    @property
    def n_targets(self) -> int:
        return len(self.tri_idx)


def probe_targets(mesh: Mesh, points: np.ndarray) -> TargetProbe:
    """The probe of rest points (K, 2) mm; ValueError if one lies outside the mesh."""
    tri_idx, bary = locate(mesh, np.atleast_2d(np.asarray(points, float)))
    return TargetProbe(tri_idx=tri_idx, nodes=mesh.triangles[tri_idx], bary=bary)


def target_positions(probe: TargetProbe, x: np.ndarray) -> np.ndarray:
    """Deformed target positions (K, d) mm for node positions x (N, d) mm."""
    return np.einsum("kj,kjd->kd", probe.bary, np.asarray(x, float)[probe.nodes])


def stacked_probes(probes: list[TargetProbe]) -> TargetProbe:
    """One probe of every row of `probes`, in order: rows with fewer nodes than the widest are padded with their
    last node at weight 0 (a point's d + 1 corners beside a region's mean, `LinearSimplex.mean_probe`)."""
    width = max(p.nodes.shape[1] for p in probes)
    pad = [(np.pad(p.nodes, ((0, 0), (0, width - p.nodes.shape[1])), mode="edge"),
            np.pad(p.bary, ((0, 0), (0, width - p.bary.shape[1])))) for p in probes]
    return TargetProbe(tri_idx=np.concatenate([p.tri_idx for p in probes]),
                       nodes=np.concatenate([n for n, _ in pad]), bary=np.concatenate([w for _, w in pad]))


def apply_probe(probe: TargetProbe, D: np.ndarray, d: int = 2) -> np.ndarray:
    """S_t D: nodal vectors D (dN, C) → target vectors (dK, C), rows [t0x, t0y, (t0z,) t1x, ...]; d = 2 or 3."""
    D3 = D.reshape(-1, d, D.shape[1])  # (N, d, C)
    return np.einsum("kj,kjdc->kdc", probe.bary, D3[probe.nodes]).reshape(d * probe.n_targets, D.shape[1])


def locate_in_simplices(nodes: np.ndarray, cells: np.ndarray, points: np.ndarray,
                        tol: float = 1e-9, extrapolate: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Containing cell (K,) and barycentric coordinates (K, d + 1) of points (K, d) in simplices (M, d + 1) of
    nodes (N, d), any d; ValueError naming the first point outside, or with `extrapolate` the cell whose smallest
    coordinate is largest and its coordinates (some negative: the point follows that cell's affine map). Every
    cell is tried for every point (targets and markers: a few dozen points)."""
    points = np.atleast_2d(np.asarray(points, float))
    X = nodes[cells]  # (M, d + 1, d)
    inv = np.linalg.inv(np.transpose(X[:, 1:] - X[:, :1], (0, 2, 1)))  # (M, d, d): Dm⁻¹, edges as columns
    cell = np.empty(len(points), np.int64)
    bary = np.empty((len(points), cells.shape[1]))
    for lo in range(0, len(points), 64):  # chunks bound the (k, M, d) temporaries
        rel = points[lo:lo + 64, None, :] - X[None, :, 0, :]
        lam = np.einsum("mij,kmj->kmi", inv, rel)
        full = np.concatenate([1.0 - lam.sum(axis=2, keepdims=True), lam], axis=2)  # (k, M, d + 1)
        worst = full.min(axis=2)
        best = np.argmax(worst, axis=1)
        rows = np.arange(len(best))
        if not extrapolate and np.any(worst[rows, best] < -tol):
            bad = lo + int(np.flatnonzero(worst[rows, best] < -tol)[0])
            raise ValueError(f"point {np.round(points[bad], 6).tolist()} mm is outside the mesh")
        cell[lo:lo + 64] = best
        bary[lo:lo + 64] = full[rows, best]
    return cell, bary


def probe_points(nodes: np.ndarray, cells: np.ndarray, points: np.ndarray, extrapolate: bool = False) -> TargetProbe:
    """The probe of rest points (K, d) mm carried by the simplices (M, d + 1) of nodes (N, d) holding them (a point
    outside the mesh: ValueError, or with `extrapolate` carried by the affine map of the cell whose smallest
    barycentric coordinate is largest there)."""
    cell, bary = locate_in_simplices(nodes, cells, points, extrapolate=extrapolate)
    return TargetProbe(tri_idx=cell, nodes=cells[cell], bary=bary)


#: points per chunk of `locate_in_tetrahedra`: bounds its temporaries (about 10 candidate tetrahedra per point)
_LOCATE_CHUNK = 32768
#: the location's voxel, per mm of the mean tetrahedron's edge: smaller voxels list each tetrahedron in more of
#: them, larger ones test each point against more tetrahedra
_VOXEL_PER_EDGE = 0.5
#: a point on a tetrahedron's face (barycentric coordinate this far below 0) still counts as inside it
_BARY_TOL = 1e-9


def _tetra_inverses(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First vertices (M, 3) and the inverses (M, 3, 3) of the edge matrices [x1 - x0, x2 - x0, x3 - x0]."""
    X = nodes[tets]
    return X[:, 0], np.linalg.inv(np.transpose(X[:, 1:] - X[:, :1], (0, 2, 1)))


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(owner (T,), rank (T,)) of T = Σ counts items: item t belongs to group owner[t], the rank-th in it."""
    owner = np.repeat(np.arange(len(counts)), counts)
    return owner, np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)


def locate_in_tetrahedra(nodes_mm: np.ndarray, tets: np.ndarray, points_mm: np.ndarray,
                         cell_mm: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Containing tetrahedron (K,) (-1: outside the mesh) and barycentric weights (K, 4) of points (K, 3) mm: for
    many points (a body's scatterers), where `locate_in_simplices` tries every cell for every point.

    Voxels of cell_mm (default: _VOXEL_PER_EDGE x the mean tetrahedron's edge) over the
    points' bounding box; each tetrahedron is listed in every voxel its
    bounding box touches, each point tested against its voxel's list.
    """
    nodes = np.asarray(nodes_mm, float)
    tets = np.asarray(tets, np.int64)
    p = np.asarray(points_mm, float).reshape(-1, 3)
    K = len(p)
    cell = np.full(K, -1, np.int64)
    bary = np.zeros((K, 4))
    if K == 0 or len(tets) == 0:
        return cell, bary
    X = nodes[tets]
    t_lo, t_hi = X.min(axis=1), X.max(axis=1)
    lo, hi = p.min(axis=0), p.max(axis=0)
    keep = np.flatnonzero(np.all((t_hi >= lo) & (t_lo <= hi), axis=1))  # tetrahedra the points can lie in
    if len(keep) == 0:
        return cell, bary
    # the regular tetrahedron's edge of the mean volume: V = h^3 / (6 sqrt 2)
    mean_edge = float((np.sqrt(2.0) * np.mean(np.abs(np.linalg.det(X[keep, 1:] - X[keep, :1])))) ** (1.0 / 3.0))
    h = float(cell_mm) if cell_mm is not None else _VOXEL_PER_EDGE * mean_edge
    n = np.maximum(1, np.ceil((hi - lo) / h).astype(np.int64) + 1)
    i0 = np.clip(np.floor((t_lo[keep] - lo) / h).astype(np.int64), 0, n - 1)
    i1 = np.clip(np.floor((t_hi[keep] - lo) / h).astype(np.int64), 0, n - 1)
    ext = i1 - i0 + 1  # (m, 3) voxels per axis
    owner, rank = _expand(np.prod(ext, axis=1))
    e = ext[owner]
    v = i0[owner] + np.stack([rank % e[:, 0], (rank // e[:, 0]) % e[:, 1], rank // (e[:, 0] * e[:, 1])], axis=1)
    voxel = (v[:, 0] * n[1] + v[:, 1]) * n[2] + v[:, 2]
    order = np.argsort(voxel, kind="stable")
    voxel, listed = voxel[order], keep[owner[order]]
    x0, inv = _tetra_inverses(nodes, tets[keep])
    slot = np.full(len(tets), -1, np.int64)
    slot[keep] = np.arange(len(keep))
    for s in range(0, K, _LOCATE_CHUNK):
        q = p[s:s + _LOCATE_CHUNK]
        iv = np.clip(np.floor((q - lo) / h).astype(np.int64), 0, n - 1)
        pv = (iv[:, 0] * n[1] + iv[:, 1]) * n[2] + iv[:, 2]
        a, b = np.searchsorted(voxel, pv, "left"), np.searchsorted(voxel, pv, "right")
        who, r = _expand(b - a)
        cand = listed[a[who] + r]
        k = slot[cand]
        lam = np.einsum("kij,kj->ki", inv[k], q[who] - x0[k])
        full = np.concatenate([1.0 - lam.sum(axis=1, keepdims=True), lam], axis=1)
        ok = full.min(axis=1) >= -_BARY_TOL
        first_who, first = np.unique(who[ok], return_index=True)
        hit = np.flatnonzero(ok)[first]
        cell[s + first_who] = cand[hit]
        bary[s + first_who] = np.clip(full[hit], 0.0, None) / np.clip(full[hit], 0.0, None).sum(axis=1,
                                                                                              keepdims=True)
    return cell, bary
