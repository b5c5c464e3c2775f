"""Scatterers in a 3-D body: drawn in a band about the image plane, carried by the tetrahedra
(docs/ultrasound.md, "On the body (3-D)").

**The band.** As in the slab (`scatter_scene`), the scatterers fill an
elevation band about the image plane: at each depth, where the two-way
elevation amplitude falls to -20 dB, plus 0.5 mm (`scatter_scene.
ELEVATION_EDGE_NEPER`, `ELEVATION_MARGIN_MM`); the volume density is the
slab's (`band_density`: the beam holds as many scatterers per resolution
cell as the layer's plane).

**The draw** (`draw_body_scatterers`) is made in the tetrahedra: each one
whose probe-frame bounding box meets the region gets a Poisson count of
its volume's worth at uniform barycentric weights; those outside the
region or the band are dropped, the rest sorted by 1 mm tiles of the plane
(the fast model's splatting then stays in cache).

**Echogenicity.** Background 0 dB (Gaussian amplitudes); then the obstacles
in their order (a sphere, or a tube: within its radius of its polyline),
then every lesion: the sphere of its echo radius about its rest centre (the
lesion's tagged region is that sphere, faceted).

**Carriage.** Each scatterer keeps the barycentric weights of its rest
tetrahedron; its deformed position is the same combination of the
deformed nodes, x_s = Σ_j w_sj x[n_sj] (`mesh.probe`'s carriage), written
as one sparse (S, N) matrix so a frame's positions are one sparse product.
On another mesh than the one drawn on, the rest points are located in its
tetrahedra (`locate_in_tetrahedra`: the tetrahedra bucketed by the voxels
their bounding boxes touch, each point tested against its voxel's list;
exact and vectorised) and those outside it dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from scissor_cli import geometry3d as g3
from scissor_cli.mesh.probe import locate_in_tetrahedra
from scissor_cli.sensing.ultrasound.body_pose import BodyProbePose
from scissor_cli.sensing.ultrasound.scatterers import _gain

#: points per chunk: bounds the temporaries of the regions' distances
_CHUNK = 32768


@dataclass(frozen=True, eq=False)
class Echo:
    """A region of its own echogenicity: segments a→b (S, 3) mm (a sphere: one of length 0) within radius_mm; dB."""

    a_mm: np.ndarray
    b_mm: np.ndarray
    radius_mm: float
    db: float


def sphere_echo(center_mm, radius_mm: float, db: float) -> Echo:
    """A sphere (a lesion, a cyst) of radius_mm about center_mm (3,)."""
    c = np.asarray(center_mm, float).reshape(1, 3)
    return Echo(c, c.copy(), float(radius_mm), float(db))


def tube_echo(points_mm, radius_mm: float, db: float) -> Echo:
    """A tube (a vessel): within radius_mm of the polyline points_mm (P, 3)."""
    p = np.asarray(points_mm, float).reshape(-1, 3)
    return Echo(p[:-1], p[1:], float(radius_mm), float(db))


def echo_gains(points_mm: np.ndarray, echoes: Sequence[Echo]) -> np.ndarray:
    """(K,) amplitude factors of points (K, 3) mm: 1, then each region's 10^(dB/20) where it holds them, later
    regions over earlier ones."""
    p = np.asarray(points_mm, float)
    gain = np.ones(len(p))
    for e in echoes:
        lo = np.minimum(e.a_mm, e.b_mm).min(axis=0) - e.radius_mm
        hi = np.maximum(e.a_mm, e.b_mm).max(axis=0) + e.radius_mm
        near = np.flatnonzero(np.all((p >= lo) & (p <= hi), axis=1))  # only where its bounding box allows
        for s in range(0, len(near), _CHUNK):
            idx = near[s:s + _CHUNK]
            inside = g3.point_segment_distance(p[idx], e.a_mm, e.b_mm).min(axis=1) <= e.radius_mm
            gain[idx[inside]] = _gain(e.db)
    return gain


@dataclass(frozen=True, eq=False)
class BodyScatterers:
    """Scatterers at rest in the body: positions_mm (S, 3), amplitude (S,) float32, and where they were drawn:
    tetrahedron (S,) of `mesh` and barycentric weights (S, 4) there (module docstring)."""

    positions_mm: np.ndarray
    amplitude: np.ndarray
    tetrahedron: np.ndarray
    bary: np.ndarray
    mesh: object

    def __len__(self) -> int:
        return len(self.amplitude)


def _tile_order(probe_mm: np.ndarray) -> np.ndarray:
    """The order of points (S, 3) (lateral, depth, ...) mm by 1 mm tiles of the plane, raster (depth rows, lateral
    within a row): neighbours in the arrays are neighbours in the image, which keeps the splatting in cache."""
    t = np.floor(probe_mm[:, :2] - probe_mm[:, :2].min(axis=0)).astype(np.int64)
    return np.lexsort((t[:, 0], t[:, 1]))


def draw_body_scatterers(rng: np.random.Generator, mesh, pose: BodyProbePose, box_mm: np.ndarray,
                         density_per_mm3: float, band_profile, echoes: Sequence[Echo] = ()) -> BodyScatterers:
    """Scatterers drawn in the tetrahedra of `mesh` (nodes (N, 3), tetrahedra (M, 4)) where they meet the band.

    A homogeneous Poisson process of density_per_mm3: each tetrahedron
    whose probe-frame bounding box meets the box [[lateral0, depth0],
    [lateral1, depth1]] mm (true depth) × ± the widest band gets a Poisson
    count of its volume's worth, at uniform barycentric weights (normalised
    exponentials: the flat Dirichlet law); a scatterer outside the box or
    farther across the plane than the band at its depth (band_profile:
    true depths (R,) increasing and half-widths (R,) mm, interpolated,
    clamped at the ends) is dropped. Amplitudes: standard normals times the
    echoes' gains (the obstacles, then the lesions; `echo_gains`). The
    random numbers drawn depend on the mesh, the pose and the box only.
    """
    nodes = np.asarray(mesh.nodes, float)
    tets = np.asarray(mesh.tetrahedra, np.int64)
    depths, half = (np.asarray(v, float) for v in band_profile)
    box = np.asarray(box_mm, float)
    q = pose.to_probe(nodes)[tets]  # (M, 4, 3)
    lo, hi = q.min(axis=1), q.max(axis=1)
    b = float(half.max())
    meets = np.all((hi >= [box[0, 0], box[0, 1], -b]) & (lo <= [box[1, 0], box[1, 1], b]), axis=1)
    cand = np.flatnonzero(meets)
    X = q[cand]
    volume = np.abs(np.linalg.det(X[:, 1:] - X[:, :1])) / 6.0
    counts = rng.poisson(density_per_mm3 * volume)
    owner = np.repeat(np.arange(len(cand)), counts)
    e = rng.exponential(size=(len(owner), 4))
    w = e / e.sum(axis=1, keepdims=True)
    p = np.einsum("sj,sjd->sd", w, X[owner])  # probe frame
    keep = ((p[:, 0] >= box[0, 0]) & (p[:, 0] <= box[1, 0]) & (p[:, 1] >= box[0, 1]) & (p[:, 1] <= box[1, 1])
            & (np.abs(p[:, 2]) <= np.interp(p[:, 1], depths, half)))
    idx = np.flatnonzero(keep)
    idx = idx[_tile_order(p[idx])]
    points = pose.to_body(p[idx])
    amplitude = (rng.standard_normal(len(idx)) * echo_gains(points, echoes)).astype(np.float32)
    return BodyScatterers(points, amplitude, cand[owner[idx]], w[idx], mesh)


@dataclass(frozen=True, eq=False)
class CarriedBodyScatterers:
    """Scatterers as material points of one tetrahedral mesh: carry (S, N) sparse, rows the barycentric weights;
    kept (S0,) bool: which of the scatterers handed in lie in the mesh; amplitude (S,) float32."""

    carry: sp.csr_matrix
    kept: np.ndarray
    amplitude: np.ndarray

    def __len__(self) -> int:
        return self.carry.shape[0]

    def to_probe(self, x_mm: np.ndarray, pose: BodyProbePose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lateral, true depth, elevation) (S,) mm in pose's frame for the nodes at x (N, 3) mm."""
        q = pose.to_probe(self.carry @ np.asarray(x_mm, float))
        return (np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1]), np.ascontiguousarray(q[:, 2]))


def carry_in_body(mesh, scatterers: BodyScatterers) -> CarriedBodyScatterers:
    """The scatterers as material points of `mesh` (nodes (N, 3), tetrahedra (M, 4)): their own tetrahedra when
    drawn on it, else located in it (`locate_in_tetrahedra`; those outside are dropped)."""
    nodes = np.asarray(mesh.nodes, float)
    if scatterers.mesh is mesh:
        tet, bary = scatterers.tetrahedron, scatterers.bary
    else:
        tet, bary = locate_in_tetrahedra(nodes, mesh.tetrahedra, scatterers.positions_mm)
    kept = tet >= 0
    S = int(kept.sum())
    cols = np.asarray(mesh.tetrahedra, np.int64)[tet[kept]].ravel()
    carry = sp.csr_matrix((bary[kept].ravel(), cols, np.arange(0, 4 * S + 1, 4)), shape=(S, len(nodes)))
    return CarriedBodyScatterers(carry, kept, np.ascontiguousarray(scatterers.amplitude[kept]))


def band_density(base_density_per_mm2: float, band_mm: float, fwhm_mm: float) -> float:
    """Volume density (1/mm³) of a band ±band_mm: the slab's in-plane density, the base raised by
    2 band / the beam's -6 dB thickness (so the beam holds as many scatterers per resolution cell as the layer's
    plane), over the band's thickness 2 band."""
    if not (band_mm > 0 and math.isfinite(band_mm)):
        raise ValueError(f"the elevation band must be positive, got {band_mm!r} mm")
    raised = max(1.0, 2.0 * band_mm / fwhm_mm) if math.isfinite(fwhm_mm) and fwhm_mm > 0 else 1.0
    return float(base_density_per_mm2) * raised / (2.0 * band_mm)


__all__ = ["BodyScatterers", "CarriedBodyScatterers", "Echo", "band_density", "carry_in_body",
           "draw_body_scatterers", "echo_gains", "sphere_echo", "tube_echo"]
