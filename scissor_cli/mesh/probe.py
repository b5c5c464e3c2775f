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

    nodes (K, 3) int: the containing triangle's vertices; bary (K, 3): the
    barycentric weights at rest (rows sum to 1); tri_idx (K,) for reference.
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
    """Deformed target positions (K, 2) mm for node positions x (N, 2) mm."""
    return np.einsum("kj,kjd->kd", probe.bary, np.asarray(x, float)[probe.nodes])


def apply_probe(probe: TargetProbe, D: np.ndarray) -> np.ndarray:
    """S_t D: nodal vectors D (2N, C) → target vectors (2K, C), rows [t0x, t0y, t1x, ...]."""
    D3 = D.reshape(-1, 2, D.shape[1])  # (N, 2, C)
    return np.einsum("kj,kjdc->kdc", probe.bary, D3[probe.nodes]).reshape(2 * probe.n_targets, D.shape[1])
