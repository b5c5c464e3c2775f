"""The slab's mesh: the layer's triangles extruded into tetrahedra (docs/model.md §13).

The 2-D mesh is repeated at the z levels of the slab; node (level k, 2-D
vertex v) is 3-D node k·N2 + v. Between two levels each triangle is a
prism, split into three tetrahedra by the vertex-index rule: with the
triangle's vertices sorted by global index, v0 < v1 < v2 (bottom) and
v0' < v1' < v2' (top),

    (v0, v1, v2, v0'), (v1, v2, v0', v1'), (v2, v0', v1', v2').

Every quadrilateral side face (vi, vj), i < j, is then cut along the
diagonal vj–vi' whichever prism it belongs to, so neighbouring prisms
share matching triangles and the mesh is conforming. Tetrahedra come out
of the rule with either orientation; the negative ones get two vertices
swapped, so every volume is positive.

The z levels are graded: prism layers start `first_mm` thick at the
simulated layer's height and grow by GROWTH per layer up to `max_layer_mm`,
on both sides; each side is then stretched uniformly to end exactly on
its face. The layer's height is always a level, so the layer's own
triangles are faces of the slab's tetrahedra.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scissor_cli.geometry import LEVEL_GROWTH as GROWTH  # noqa: F401 (shared with config's budget)


@dataclass(frozen=True)
class SlabMesh:
    """The extruded mesh; the same names as `mesh.Mesh` where a tissue reads them."""

    nodes: np.ndarray  # (N3, 3) mm, N3 = L·N2
    triangles: np.ndarray  # (M3, 4) int64: the tetrahedra, positive volume (named as in Mesh for Tissue)
    levels_mm: np.ndarray  # (L,) z of each level, increasing, 0 and H included
    layer_level: int  # index of the level at the simulated layer's height
    n_nodes_2d: int  # N2
    element_obstacle: np.ndarray  # (M3,) int64: the obstacle index of the triangle it came from, -1 none
    element_triangle: np.ndarray  # (M3,) int64: the 2-D triangle it came from
    #: the 2-D mesh that was extruded (`mesh.Mesh`): the layer's own, or a coarser one (`SlabSpec.plane`)
    plane: object = None

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_elements(self) -> int:
        return len(self.triangles)

    @property
    def tetrahedra(self) -> np.ndarray:
        return self.triangles

    @property
    def layer_nodes(self) -> np.ndarray:
        """The 3-D nodes (N2,) of the simulated layer, one per vertex of `plane`, in its order."""
        return self.node(self.layer_level, np.arange(self.n_nodes_2d))

    def node(self, level: int, vertex: np.ndarray) -> np.ndarray:
        """3-D node indices of 2-D vertices (any shape) at a level."""
        return level * self.n_nodes_2d + np.asarray(vertex)

    def column(self, vertex: np.ndarray) -> np.ndarray:
        """3-D nodes (K·L,) of 2-D vertices (K,) at every level."""
        vertex = np.asarray(vertex).ravel()
        return (np.arange(len(self.levels_mm))[:, None] * self.n_nodes_2d + vertex[None]).ravel()


def prism_tetrahedra(triangles: np.ndarray, n_nodes_2d: int, n_layers: int) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedra (3·M2·n_layers, 4) of the extruded triangles (M2, 3), and each one's triangle.

    Order: layer-major, then the three tetrahedra of each triangle. Not yet oriented.
    """
    v = np.sort(triangles, axis=1)  # v0 < v1 < v2: the vertex-index rule
    v0, v1, v2 = v[:, 0], v[:, 1], v[:, 2]
    n = n_nodes_2d
    one = np.stack([
        np.stack([v0, v1, v2, v0 + n], 1),
        np.stack([v1, v2, v0 + n, v1 + n], 1),
        np.stack([v2, v0 + n, v1 + n, v2 + n], 1),
    ], axis=1).reshape(-1, 4)  # (3·M2, 4) between levels 0 and 1
    offsets = (np.arange(n_layers) * n)[:, None, None]
    tets = (one[None] + offsets).reshape(-1, 4).astype(np.int64)
    tri = np.tile(np.repeat(np.arange(len(triangles)), 3), n_layers)
    return tets, tri


def orient(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Tetrahedra (M, 4) with the last two vertices swapped where the volume was negative."""
    X = nodes[tets]
    vol = np.einsum("ij,ij->i", np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), X[:, 3] - X[:, 0])
    out = tets.copy()
    neg = vol < 0
    out[neg, 2], out[neg, 3] = tets[neg, 3], tets[neg, 2]
    return out


def extrude(nodes_2d: np.ndarray, triangles: np.ndarray, element_obstacle: np.ndarray,
            levels_mm: np.ndarray, layer_level: int) -> SlabMesh:
    """The slab mesh of a 2-D mesh (nodes (N2, 2) mm, triangles (M2, 3)) over z levels (L,) mm."""
    levels_mm = np.asarray(levels_mm, float)
    n2, L = len(nodes_2d), len(levels_mm)
    nodes = np.empty((L * n2, 3))
    nodes[:, :2] = np.tile(nodes_2d, (L, 1))
    nodes[:, 2] = np.repeat(levels_mm, n2)
    tets, tri = prism_tetrahedra(np.asarray(triangles, np.int64), n2, L - 1)
    tets = orient(nodes, tets)
    return SlabMesh(nodes, tets, levels_mm, int(layer_level), n2, np.asarray(element_obstacle)[tri], tri)


def volumes(mesh: SlabMesh) -> np.ndarray:
    """Signed volumes (M3,) mm³ of the tetrahedra."""
    X = mesh.nodes[mesh.triangles]
    return np.einsum("ij,ij->i", np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), X[:, 3] - X[:, 0]) / 6.0
