"""Tetrahedra as arrays: orientation, compact numbering, the outer boundary and the dihedral angles.

Every function is vectorised over all elements; nothing here knows gmsh.
"""

from __future__ import annotations

import numpy as np

#: the faces of a positively oriented tetrahedron (0, 1, 2, 3), each with its normal pointing out
OUTWARD_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def signed_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume (M,) of every tetrahedron: positive when corner 3 lies on the side of (1-0)×(2-0)."""
    p = nodes[tets]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


def oriented(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The tetrahedra with two corners swapped wherever the signed volume is negative."""
    flip = signed_volumes(nodes, tets) < 0
    out = tets.copy()
    out[flip, 2], out[flip, 3] = tets[flip, 3], tets[flip, 2]
    return out


def compacted(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Only the nodes some tetrahedron uses, in their old order, and the tetrahedra renumbered to them."""
    used, inverse = np.unique(tets, return_inverse=True)
    return nodes[used], inverse.reshape(tets.shape).astype(np.int64)


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Faces (S, 3) that belong to one tetrahedron only, ordered so their normals point out of the mesh.

    The tetrahedra must be positively oriented. Faces keep the order of
    their elements (element by element, then OUTWARD_FACES's order), so the
    result depends only on the tetrahedra.
    """
    faces = tets[:, OUTWARD_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    n = int(tets.max()) + 1 if len(tets) else 1
    if n < 2**21:  # three node numbers fit one int64
        code = (key[:, 0] * n + key[:, 1]) * n + key[:, 2]
        _, inverse, count = np.unique(code, return_inverse=True, return_counts=True)
    else:
        _, inverse, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[count[inverse.reshape(-1)] == 1]


def dihedral_angles_deg(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The six dihedral angles (M, 6) of every tetrahedron in degrees: π minus the angle between outward normals."""
    p = nodes[tets]
    f = OUTWARD_FACES
    normals = np.cross(p[:, f[:, 1]] - p[:, f[:, 0]], p[:, f[:, 2]] - p[:, f[:, 0]])
    length = np.linalg.norm(normals, axis=2, keepdims=True)
    normals = normals / np.where(length > 0, length, 1.0)
    pairs = np.array([[i, j] for i in range(4) for j in range(i + 1, 4)])
    cos = np.einsum("mkj,mkj->mk", normals[:, pairs[:, 0]], normals[:, pairs[:, 1]])
    return 180.0 - np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def min_dihedral_deg(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The smallest dihedral angle (M,) of every tetrahedron, degrees."""
    return dihedral_angles_deg(nodes, tets).min(axis=1)
