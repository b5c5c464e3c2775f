"""A 3-D scene's mesh given as a file instead of meshed (`tissue.mesh.file` of a dome or surface scene).

gmsh's meshes, like Triangle's, are not portable bit for bit across CPUs;
a run that must give the same numbers everywhere pins its tetrahedra: an
.npz with `nodes` (N, 3) mm, `tetrahedra` (M, 4), `region` (M,) and
`region_names` (the mesh's regions, as `mesh.body_mesh.BodyMesh` names
them), or a 3-D run's results.h5 (`/mesh/nodes`, `/mesh/tetrahedra`,
`/mesh/region`, the `/mesh` attribute `regions`). Read here, in the config
layer: every problem is a config problem (exit 2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scissor_cli.config.mesh_file import SUFFIXES, MeshFileError


def read_body_mesh_arrays(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
    """Nodes (N, 3) float64 mm, tetrahedra (M, 4) int64 of positive volume, region (M,) int64 and the region
    names of a 3-D mesh file, checked; MeshFileError otherwise."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise MeshFileError(f"a mesh file is .npz (arrays nodes, tetrahedra, region, region_names) or a scissor "
                            f"results .h5; got '{path.suffix}'")
    try:
        if path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as data:
                nodes, tets, region = data["nodes"], data["tetrahedra"], data["region"]
                names = tuple(str(n) for n in data["region_names"])
        else:
            import h5py  # noqa: PLC0415 (only for a results file)

            with h5py.File(path, "r") as h5:
                nodes, tets, region = h5["mesh/nodes"][()], h5["mesh/tetrahedra"][()], h5["mesh/region"][()]
                names = tuple(n.decode() if isinstance(n, bytes) else str(n) for n in h5["mesh"].attrs["regions"])
    except KeyError as exc:
        raise MeshFileError(f"cannot find the mesh's arrays in {path} ({exc}); an .npz needs 'nodes', "
                            f"'tetrahedra', 'region' and 'region_names', an .h5 a 3-D run's /mesh") from None
    except (OSError, ValueError, TypeError) as exc:
        raise MeshFileError(f"cannot read {path}: {exc}") from None
    return (*_checked(np.asarray(nodes), np.asarray(tets), np.asarray(region), len(names)), names)


def _checked(nodes, tets, region, n_regions):
    if nodes.ndim != 2 or nodes.shape[1] != 3 or len(nodes) < 4 or nodes.dtype.kind not in "fiu":
        raise MeshFileError(f"nodes must be an (N, 3) array of numbers with N >= 4; got shape {nodes.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) < 1 or tets.dtype.kind not in "iu":
        raise MeshFileError(f"tetrahedra must be an (M, 4) array of node indices; got shape {tets.shape}, "
                            f"type {tets.dtype}")
    nodes, tets = nodes.astype(np.float64), tets.astype(np.int64)
    if not np.all(np.isfinite(nodes)):
        raise MeshFileError("nodes must be finite numbers (mm); the file holds NaN or infinity")
    if tets.min() < 0 or tets.max() >= len(nodes):
        raise MeshFileError(f"tetrahedra must index nodes 0..{len(nodes) - 1}; the file has indices "
                            f"{tets.min()}..{tets.max()}")
    p = nodes[tets]
    volume = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0
    if not np.all(volume > 1e-12 * max(float(np.ptp(nodes)), 1.0) ** 3):
        raise MeshFileError(f"{int(np.sum(~(volume > 0)))} tetrahedra have no volume or a negative one "
                            f"(their corners must be ordered to a positive volume)")
    if region.shape != (len(tets),) or region.dtype.kind not in "iu" or region.min() < 0 or region.max() >= n_regions:
        raise MeshFileError(f"region must be an (M,) array of indices into the {n_regions} region names")
    return nodes, tets, region.astype(np.int64)
