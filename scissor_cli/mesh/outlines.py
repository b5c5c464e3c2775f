"""Outlines carried by the mesh: obstacle and skin outlines through the deformation (docs/model.md §1, §7).

An outline point keeps the barycentric coordinates of the rest triangle that
contains it, like a target (`mesh.probe`), so the deformed outline is the
same combination of the deformed vertices. Obstacle outlines are mesh
segments, so each carried outline follows its obstacle exactly. The skin is
the mesh's own boundary loop, read off the node positions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from scissor_cli import geometry
from scissor_cli.mesh.mesh import Mesh, interpolate, locate


@dataclass(frozen=True)
class Embedding:
    """Points embedded in the rest mesh: triangle (P,) and barycentric coordinates (P, 3).

    `splits` cuts the P points back into the outlines they came from.
    """

    triangles: np.ndarray  # (M, 3) the mesh's
    tri_idx: np.ndarray  # (P,)
    bary: np.ndarray  # (P, 3)
    splits: tuple[int, ...]  # cumulative ends of each outline in the P points


def embed_outlines(mesh: Mesh, outlines: Sequence[np.ndarray]) -> Embedding:
    """Locate the points of rest outlines (K_i, 2) mm once, in the rest mesh: their `Embedding`."""
    pts = np.vstack([np.asarray(o, float).reshape(-1, 2) for o in outlines]) if outlines else np.zeros((0, 2))
    tri_idx, bary = locate(mesh, pts) if len(pts) else (np.zeros(0, np.int64), np.zeros((0, 3)))
    return Embedding(mesh.triangles, tri_idx, bary, tuple(np.cumsum([len(o) for o in outlines]).tolist()))


def deformed_outlines(embedding: Embedding, x: np.ndarray) -> list[np.ndarray]:
    """The embedded outlines carried to node positions x (N, 2): a list of (K_i, 2) mm."""
    if not embedding.splits:
        return []
    pts = interpolate(x, embedding.triangles, embedding.tri_idx, embedding.bary)
    return np.split(pts, embedding.splits[:-1])


def boundary_loop(mesh: Mesh) -> np.ndarray:
    """Node indices (B,) of the mesh's outer boundary in counter-clockwise order.

    At rest it traces the scene outline; under load, the deformed skin, which
    is where the needle actually enters.
    """
    nxt = {int(a): int(b) for a, b in mesh.boundary_edges}
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, n = [start], nxt[start]
        seen.add(start)
        while n != start and n not in seen:
            loop.append(n)
            seen.add(n)
            n = nxt[n]
        loops.append(np.array(loop))
    # Boundary edges keep the domain on their left, so the outer loop has the largest positive area.
    return max(loops, key=lambda loop: geometry.signed_area(mesh.nodes[loop]))
