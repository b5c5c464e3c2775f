"""A mesh given as a file instead of meshed from the size field (`tissue.mesh.file`).

Meshing is not portable bit for bit: Triangle's refinement decisions rest on
floating-point comparisons, and another CPU can flip one of them (1377
nodes instead of 1380 for the example scene). A run that must give the same
numbers on every machine pins its mesh: the nodes and triangles of an
earlier run's results.h5 (`/mesh/nodes`, `/mesh/triangles`) or of an .npz
file with arrays `nodes` (N, 2) mm and `triangles` (M, 3). docs/contract.md
("Reproducibility") says what that guarantees.

This module reads and checks the file (the config layer: every problem is a
config problem, exit 2); `mesh.mesh.mesh_for_config` turns it into a `Mesh`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scissor_cli import geometry

#: the file types a mesh may come in, by suffix
SUFFIXES = (".npz", ".h5", ".hdf5")
#: what "this scene's layer" allows: the mesh's area within this fraction of the outline's
AREA_TOLERANCE = 0.01


class MeshFileError(ValueError):
    """The mesh file cannot be read or is not a usable mesh; the message says why."""


def read_mesh_arrays(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (N, 2) float64 mm and triangles (M, 3) int64 of a mesh file, checked; MeshFileError otherwise."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise MeshFileError("a mesh file is .npz (arrays nodes, triangles) or a scissor results .h5; "
                            f"got '{path.suffix}'")
    try:
        if path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as data:
                nodes, triangles = data["nodes"], data["triangles"]
        else:
            import h5py

            with h5py.File(path, "r") as h5:
                nodes, triangles = h5["mesh/nodes"][()], h5["mesh/triangles"][()]
    except KeyError as exc:
        raise MeshFileError(f"cannot find the mesh's arrays in {path} ({exc}); an .npz needs 'nodes' and "
                            f"'triangles', an .h5 '/mesh/nodes' and '/mesh/triangles'") from None
    except (OSError, ValueError, TypeError) as exc:
        raise MeshFileError(f"cannot read {path}: {exc}") from None
    return _checked(np.asarray(nodes), np.asarray(triangles))


def _checked(nodes: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if nodes.ndim != 2 or nodes.shape[1] != 2 or len(nodes) < 3 or nodes.dtype.kind not in "fiu":
        raise MeshFileError(f"nodes must be an (N, 2) array of numbers with N >= 3; got shape {nodes.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) < 1 or triangles.dtype.kind not in "iu":
        raise MeshFileError(f"triangles must be an (M, 3) array of node indices with M >= 1; got shape "
                            f"{triangles.shape}, type {triangles.dtype}")
    nodes = nodes.astype(np.float64)
    if not np.all(np.isfinite(nodes)):
        raise MeshFileError("nodes must be finite numbers (mm); the file holds NaN or infinity")
    triangles = triangles.astype(np.int64)
    if triangles.min() < 0 or triangles.max() >= len(nodes):
        raise MeshFileError(f"triangles must index nodes 0..{len(nodes) - 1}; the file has indices "
                            f"{triangles.min()}..{triangles.max()}")
    p = nodes[triangles]
    area = 0.5 * np.abs(geometry.cross2(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
    if not np.all(area > 1e-12 * max(float(np.ptp(nodes)), 1.0) ** 2):
        raise MeshFileError(f"{int(np.sum(~(area > 0)))} triangle(s) have no area (repeated or collinear corners)")
    return nodes, triangles


def mesh_file_problem(nodes: np.ndarray, triangles: np.ndarray, outline: np.ndarray, points: np.ndarray) -> str | None:
    """Why a mesh does not fit a scene's layer (outline (K, 2), points (P, 2) that must lie in it), or None."""
    p = nodes[triangles]
    area = 0.5 * np.abs(geometry.cross2(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])).sum()
    expected = abs(geometry.signed_area(outline))
    if abs(area - expected) > AREA_TOLERANCE * expected:
        return (f"the mesh covers {area:.6g} mm², the tissue's outline {expected:.6g} mm²: it is not a mesh of this "
                f"layer (within {AREA_TOLERANCE:.0%})")
    inside = _in_any_triangle(points, p)
    if not np.all(inside):
        return f"{int(np.sum(~inside))} of the scene's targets and cup contacts lie outside the mesh"
    return None


def _in_any_triangle(points: np.ndarray, p: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """(P,) whether each point lies in one of the triangles p (M, 3, 2), edges included."""
    out = np.zeros(len(points), bool)
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    det = geometry.cross2(b - a, c - a)
    for k, q in enumerate(points):  # a handful of targets and cups, each against all triangles at once
        l1 = geometry.cross2(q - a, c - a) / det
        l2 = geometry.cross2(b - a, q - a) / det
        out[k] = bool(np.any((l1 >= -tol) & (l2 >= -tol) & (l1 + l2 <= 1 + tol)))
    return out
