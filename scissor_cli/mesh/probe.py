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
    1); tri_idx (K,) the element, for reference.
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
