"""Which nodes the shaft holds, and each one's share of it (docs/model.md §12 "Capture", §20 "The capture radius").

A node is captured when its deformed position projects onto the axis
behind the tip and lies within the capture radius of the axis. The radius
is numerical — one row of nodes on the shaft — so it follows the mesh: a
configured radius (mm) is the same for every node; without one, the layer
and the slab take half the coarsest edge and a body half the mean length of
the edges meeting at each node (`capture_radii`): a body's mesh is graded
fourfold, and half its coarsest edge held a tube of tissue five needle
diameters wide where the needle passes through the fine mesh about a lesion.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.mechanics.tissue import Tissue


def free_nodes(tissue: Tissue) -> np.ndarray:
    """Nodes (F,) whose every dof (2 or 3, `tissue.dim`) is free: the only ones a needle can capture or push."""
    return np.flatnonzero(np.all(tissue.free_index.reshape(-1, tissue.dim) >= 0, axis=1))


def node_edges(nodes_mm: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, longest) (N,) mm: the mean and the longest length of the edges meeting at each node.

    nodes_mm (N, d) positions, corners (d + 1, M) the elements' vertices (an
    edge shared by several elements counts once per element: the mean is
    weighted by how many elements hold an edge).
    """
    n = nodes_mm.shape[0]
    total, count, longest = np.zeros(n), np.zeros(n), np.zeros(n)
    for a in range(corners.shape[0]):  # (d + 1 choose 2) edges of an element, each vectorised over all elements
        for b in range(a):
            length = np.linalg.norm(nodes_mm[corners[a]] - nodes_mm[corners[b]], axis=1)
            for end in (corners[a], corners[b]):
                total += np.bincount(end, length, n)
                count += np.bincount(end, None, n)
                np.maximum.at(longest, end, length)
    return total / np.maximum(count, 1.0), longest


def capture_radii(tissue: Tissue, radius_mm: float | None) -> np.ndarray:
    """Each node's capture radius (N,) mm: radius_mm for all, or (None) half the mean edge at the node at rest."""
    if radius_mm is not None:
        return np.full(tissue.mesh.n_nodes, float(radius_mm))
    return 0.5 * node_edges(tissue.mesh.nodes, tissue.ops.corners)[0]


def shaft_lengths(axial: np.ndarray, depth_mm: float) -> np.ndarray:
    """Shares l_i (P,) mm of the inserted length for captured nodes at axial positions (P,) mm.

    Half of each neighbouring gap along the axis; the first node also takes
    the gap to the entry, the last the gap to the tip, so Σ l_i = depth.
    """
    p = axial.size
    if p == 0:
        return np.zeros(0)
    order = np.argsort(axial, kind="stable")
    s = np.clip(axial[order], 0.0, depth_mm)
    bounds = np.concatenate([[0.0], 0.5 * (s[1:] + s[:-1]), [depth_mm]])
    lengths = np.empty(p)
    lengths[order] = np.diff(bounds)
    return lengths


def capture(x: np.ndarray, candidates: np.ndarray, entry: np.ndarray, direction: np.ndarray, depth_mm: float,
            captured: np.ndarray, radii_mm: np.ndarray) -> np.ndarray:
    """Newly captured nodes (Q,): not in captured (P,), projecting behind the tip and within their radius of the axis.

    x (N, d) mm, candidates (F,) the nodes that may be captured, the axis
    from entry (d,) along the unit direction (d,), the tip at depth_mm,
    radii_mm (N,) each node's capture radius (`capture_radii`).
    """
    rel = x[candidates] - entry
    s = rel @ direction
    distance = np.linalg.norm(rel - s[:, None] * direction, axis=1)  # to the axis: every component across it
    new = (s >= -1e-9) & (s <= depth_mm) & (distance <= radii_mm[candidates])
    new_nodes = candidates[new]
    held = np.zeros(x.shape[0], bool)  # membership by lookup (np.isin sorts both arrays)
    held[captured] = True
    return new_nodes[~held[new_nodes]]
