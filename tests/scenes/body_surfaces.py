"""Closed triangulated surfaces for the 3-D body tests, made here instead of stored as files.

`python3 tests/scenes/body_surfaces.py DIR` writes them as STL files into DIR
to look at; the tests call the functions and write into their tmp_path.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def icosphere(radius: float = 1.0, center=(0.0, 0.0, 0.0), subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and outward triangles (T, 3) of a sphere: an icosahedron split `subdivisions` times."""
    t = (1 + 5**0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = len(v) + inverse.reshape(3, -1).T  # midpoints of edges 01, 12, 20 of every face
        v = np.vstack([v, 0.5 * (v[unique[:, 0]] + v[unique[:, 1]])])
        a, b, c = f.T
        ab, bc, ca = mid.T
        f = np.concatenate([np.column_stack(x) for x in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    return radius * v + np.asarray(center, float), f


def box(lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and outward triangles (12, 3) of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corner = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)])
    v = lo + corner * (hi - lo)
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    f = np.array([t for q in quads for t in ([q[0], q[1], q[2]], [q[0], q[2], q[3]])])
    return v, f


def write_stl(path, vertices: np.ndarray, triangles: np.ndarray, binary: bool = True) -> Path:
    """The surface as an STL file (every triangle stores its own three corners, as STL does)."""
    import meshio

    meshio.write(path, meshio.Mesh(vertices, [("triangle", triangles)]), file_format="stl", binary=binary)
    return Path(path)


if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
    out.mkdir(parents=True, exist_ok=True)
    write_stl(out / "icosphere.stl", *icosphere(30.0, subdivisions=3))
    write_stl(out / "box.stl", *box((0, 0, 0), (80, 60, 40)))
