"""The probe's pose on a 3-D body: the array's centre on the skin, the beam, the array, the elevation
(docs/ultrasound.md, "On the body (3-D)").

The probe frame has its origin at the centre of the array's face on the
skin; its axes are lateral (along the array), depth (the beam `axis`, into
the body) and elevation = lateral × axis (across the image plane). Points
in it are written (lateral, depth, elevation), in that column order; the
image plane is elevation 0 and its 2-D points (lateral, depth) are the
layer's probe frame (`transducer.ProbePose`), so the image grid, the fast
model and the tracking are the layer's own.

On the mesh the skin is the boundary triangles not on the held base
(`BodyMesh.boundary_triangles`, `boundary_base`): the configured position
is moved to its nearest point on them, and the default axis is the inward
normal there (the area-weighted normal of the skin faces within 2 mm,
`config.body_checks.skin_normals`). The config's checks ran on the body's
exact surface (the dome's spheroid); the mesh's faceted skin lies within
the facets' sagitta of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scissor_cli import geometry3d as g3
from scissor_cli.config.body_checks import MeshSurface, skin_normals
from scissor_cli.config.body_imaging import probe_axes


@dataclass(frozen=True, eq=False)
class BodyProbePose:
    """Where the probe sits on the body: origin_mm (3,) on the skin, unit axis (3,) and lateral (3,), orthogonal."""

    origin_mm: np.ndarray
    axis: np.ndarray
    lateral: np.ndarray

    def __post_init__(self) -> None:
        o, a, lat = (np.asarray(v, float).reshape(-1) for v in (self.origin_mm, self.axis, self.lateral))
        if o.shape != (3,) or a.shape != (3,) or lat.shape != (3,) or not np.all(np.isfinite(np.r_[o, a, lat])):
            raise ValueError(f"a body probe pose needs finite 3-vectors, got {self.origin_mm!r}, {self.axis!r}, "
                             f"{self.lateral!r}")
        na, nl = np.linalg.norm(a), np.linalg.norm(lat)
        if na < 1e-9 or nl < 1e-9 or abs(a @ lat) > 1e-6 * na * nl:
            raise ValueError("the probe's axis and lateral must be non-zero and perpendicular")
        object.__setattr__(self, "origin_mm", o)
        object.__setattr__(self, "axis", a / na)
        object.__setattr__(self, "lateral", lat / nl)

    @property
    def elevation(self) -> np.ndarray:
        """Unit elevation (3,): lateral × axis, across the image plane."""
        return np.cross(self.lateral, self.axis)

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3): rows lateral, axis, elevation in the body frame (body → probe)."""
        return np.stack([self.lateral, self.axis, self.elevation])

    def to_probe(self, points_mm: np.ndarray) -> np.ndarray:
        """Body points (..., 3) mm → probe frame (..., 3) mm as (lateral, depth, elevation)."""
        # einsum, not matmul: a (K, 3) x (3, 3) product through BLAS costs ten times more on a busy machine
        return np.einsum("...j,ij->...i", np.asarray(points_mm, float) - self.origin_mm, self.rotation)

    def to_body(self, probe_mm: np.ndarray) -> np.ndarray:
        """Probe-frame points (..., 2) (lateral, depth; elevation 0) or (..., 3) mm → body points (..., 3) mm."""
        q = np.asarray(probe_mm, float)
        return self.origin_mm + np.einsum("...i,ij->...j", q, self.rotation[: q.shape[-1]])

    def moved(self, offset_mm: np.ndarray, rotation_vector: np.ndarray) -> "BodyProbePose":
        """This pose shifted by offset_mm (3,) in its own frame (lateral, depth, elevation) and turned by the
        rotation vector (3,) rad, also in its frame (a calibration error)."""
        R = g3.rotation_matrix(np.asarray(rotation_vector, float) @ self.rotation)  # the vector in the body frame
        return BodyProbePose(self.origin_mm + np.asarray(offset_mm, float) @ self.rotation, R @ self.axis,
                             R @ self.lateral)


def skin_surface(mesh) -> MeshSurface:
    """The mesh's boundary as a `MeshSurface` whose held faces are the base's: its skin is the rest."""
    return MeshSurface(np.asarray(mesh.nodes, float), np.asarray(mesh.boundary_triangles),
                       np.asarray(mesh.boundary_base, bool))


def skin_pose(mesh, position_mm, axis=None, lateral=None, needle_direction=None) -> tuple[BodyProbePose, float]:
    """The probe's pose on the mesh's skin and how far (mm) the configured position was moved onto it.

    position_mm (3,): the config's; axis, lateral (3,) or None: the
    config's (None: the inward normal; in-plane guidance along
    needle_direction, `config.body_imaging.probe_axes`).
    """
    surface = skin_surface(mesh)
    p = np.asarray(position_mm, float).reshape(1, 3)
    on_skin, dist, _ = g3.nearest_on_surface(p, surface.nodes, surface.triangles[~surface.held])
    inward = -skin_normals(surface, on_skin)[0]
    a, lat = probe_axes(inward, axis, lateral, needle_direction)
    return BodyProbePose(on_skin[0], a, lat), float(dist[0])


def imaging_pose(mesh, im, needle_direction=None) -> BodyProbePose:
    """The pose of a 3-D scene's `imaging` section (`BodyImagingConfig`) on the mesh's skin."""
    return skin_pose(mesh, im.position_mm, im.axis, im.lateral_axis, needle_direction)[0]


__all__ = ["BodyProbePose", "imaging_pose", "skin_pose", "skin_surface"]
