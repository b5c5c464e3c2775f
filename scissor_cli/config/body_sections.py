"""The sections of a 3-D scene: a breast body, lesions, vessels and cups on its skin (docs/model.md §19).

A scene whose `tissue.shape` is `dome` or `surface` is a 3-D scene: every
position is a 3-vector and the sections that differ from a 2-D layer's have
their own models here (`BodyConfig`); the rest (material, solver, forward
cases, robot, trials …) are the 2-D scene's own (`sections`). Ranges and
strictness as there: every number finite and inside a documented range,
unknown keys refused (a 2-D field in a 3-D scene is named as such by
`messages`). What needs several fields at once is in `body_checks`.
"""

from __future__ import annotations

from typing import Annotated, Literal, Optional, Union

import numpy as np
from annotated_types import Len
from pydantic import Field, field_validator, model_validator

from scissor_cli.config.body_imaging import BodyImagingConfig
from scissor_cli.config.sections import (
    MAX_TISSUE_MM,
    MIN_EDGE_MM,
    SCENE_NAME_PATTERN,
    CameraConfig,
    ControllerConfig,
    ForwardCase,
    InsertionConfig,
    Int,
    MaterialConfig,
    Name,
    Num,
    RobotConfig,
    Side,
    SolverConfig,
    TrialsConfig,
    Vec3,
    _Section,
)

#: the 3-D shapes; every other shape is a 2-D layer
BODY_SHAPES = ("dome", "surface")


def unit_3d(v: list[float], tol: float) -> list[float]:
    """A 3-D direction normalised, refused (ValueError) when its length is off 1 by more than tol."""
    n = float(np.linalg.norm(v))
    if abs(n - 1.0) > tol:
        raise ValueError(f"must be a unit vector (length 1 ± {tol:g}); got length {n:.4g}")
    return [float(c) / n for c in v]


class BodyMeshConfig(_Section):
    """The tetrahedral mesh's size field (docs/model.md §19, "Mesh")."""

    #: coarsest tetrahedron edge, far from every feature
    max_edge_mm: Num(MIN_EDGE_MM, 100.0) = 6.0
    #: at the lesions, obstacles and cup patches
    min_edge_mm: Num(MIN_EDGE_MM, 100.0) = 1.5
    #: growth of the edge length per mm of distance from a feature; coarser than a layer's 0.3 because the default
    #: element does not lock: the coarsest grading on which `nodal` meets the refinement bound (docs/model.md §21,
    #: "The body's default")
    grading: Num(0.001, 100.0) = 0.5
    #: multiplies both edge lengths (the accuracy ladder's levels)
    scale: Num(0.01, 100.0) = 1.0
    #: a mesh used as it is (docs/contract.md, "Reproducibility"): an .npz with nodes (N, 3) mm, tetrahedra (M, 4)
    #: and region (M,), or a scissor results.h5 of a 3-D scene; relative to the config file's folder
    file: Optional[Annotated[str, Field(min_length=1, max_length=4096)]] = None
    #: the element (docs/model.md §21): p1, linear simplices with every term per element (the paper's); nodal,
    #: the same simplices with the volumetric term on the nodes (averaged nodal volume), which does not lock
    #: at ν near 0.5 (the default: p1 locks on a body at any ν a breast has); auto, the cheaper of the two that
    #: meets tissue.accuracy_mm (which it needs; p1 when p1 does, docs/model.md §21)
    element: Literal["p1", "nodal", "auto"] = "nodal"


class SkinConfig(_Section):
    """A shell of its own material over the body's free surface (in vivo: skin ≈ 56 kPa, fat ≈ 3 kPa)."""

    thickness_mm: Num(0.1, 50.0) = 1.5
    E_kPa: Num(0.001, 1.0e6) = 56.0


class PlaneConfig(_Section):
    point_mm: Vec3
    #: the plane's normal (any length but zero: normalised)
    normal: Vec3

    @field_validator("normal")
    @classmethod
    def _nonzero(cls, v: list[float]) -> list[float]:
        n = float(np.linalg.norm(v))
        if n < 1e-9:
            raise ValueError("must not be the zero vector")
        return [float(c) / n for c in v]


class HeldPlaneConfig(_Section):
    plane: PlaneConfig


class BodyTissueConfig(_Section):
    shape: Literal["dome", "surface"]
    #: dome: the base's radius on the platform z = 0 (the body's frame: base centred at the origin, z up)
    radius_mm: Optional[Num(1.0, MAX_TISSUE_MM)] = None
    #: dome: the apex's height; the dome is the half-spheroid x²/r² + y²/r² + z²/h² ≤ 1, z ≥ 0
    height_mm: Optional[Num(1.0, MAX_TISSUE_MM)] = None
    #: surface: a closed manifold triangulation in mm (STL, OBJ, PLY, VTK), relative to the config file's folder
    surface_file: Optional[Annotated[str, Field(min_length=1, max_length=4096)]] = None
    #: dome: [base] (glued to the platform); surface: the faces on one or more planes, [{plane: {point_mm, normal}}]
    fixed: Annotated[list[Union[Literal["base"], HeldPlaneConfig]], Len(1, 8)] = ["base"]
    skin: Optional[SkinConfig] = None
    #: uniform: every element's fiber along material.fiber_angle_deg in the platform's plane; radial: towards the
    #: apex (the dome's top, the surface's highest point), as the ducts and Cooper's ligaments run
    fibers: Literal["uniform", "radial"] = "uniform"
    #: the coarsest mesh whose targets stay this close to a finer one's over the forward cases (docs/model.md §19)
    accuracy_mm: Optional[Num(1.0e-3, 100.0)] = None
    mesh: BodyMeshConfig = BodyMeshConfig()


class LesionConfig(_Section):
    name: Name
    position_mm: Vec3
    radius_mm: Num(0.1, 100.0) = 2.0
    #: the lesion's E over the tissue's (carcinomas are 3–13× stiffer than fat)
    stiffness_factor: Num(0.001, 1000.0) = 1.0
    #: where the cups should move the lesion's centre (else the planner chooses)
    desired_mm: Optional[Vec3] = None


class SphereConfig(_Section):
    center_mm: Vec3
    radius_mm: Num(0.05, MAX_TISSUE_MM)


class SkinRegionConfig(_Section):
    """A ball whose skin holds the candidate grips (docs/model.md §20, "Where to grip")."""

    center_mm: Vec3
    radius_mm: Num(0.5, MAX_TISSUE_MM)


class BodyManipulationPointsConfig(_Section):
    """Where the cups grip a body, chosen by the planner over the skin (docs/model.md §20, "Where to grip")."""

    #: the candidates: the skin's mesh nodes within this ball (at least a cup's radius from the held base)
    skin: SkinRegionConfig
    #: one candidate per cube of this edge
    spacing_mm: Num(0.5, 50.0) = 4.0
    #: how many cups to place: the first `cups` entries of `cups` (≤ len(cups): checks); two control the miss
    #: across the needle, three the lesion's 3-D position
    cups: Int(1, 16) = 2


class TubeConfig(_Section):
    """A vessel: a polyline and its radius."""

    points_mm: Annotated[list[Vec3], Len(2, 200)]
    radius_mm: Num(0.05, 100.0)


class BodyObstacleConfig(_Section):
    name: Name
    sphere: Optional[SphereConfig] = None
    tube: Optional[TubeConfig] = None
    stiffness_factor: Num(0.001, 1000.0) = 1.0

    @model_validator(mode="after")
    def _one_shape(self):
        if (self.sphere is None) == (self.tube is None):
            raise ValueError("give exactly one of sphere: {center_mm, radius_mm} or tube: {points_mm, radius_mm}")
        return self


class BodyCupConfig(_Section):
    name: Name
    #: moved to the nearest skin point (refused farther than radius_mm from the skin)
    contact_mm: Vec3
    #: a positive stroke's direction; absent: the inward normal at the contact
    axis: Optional[Vec3] = None
    radius_mm: Num(0.1, MAX_TISSUE_MM) = 5.0
    stroke_mm: Annotated[list[Num(-MAX_TISSUE_MM, MAX_TISSUE_MM)], Len(2, 2)] = [-15.0, 15.0]
    speed_mm_per_s: Num(0.01, 1000.0) = 5.0

    @field_validator("axis")
    @classmethod
    def _unit_axis(cls, v: list[float] | None) -> list[float] | None:
        return None if v is None else unit_3d(v, 1e-3)


class BodyNeedleConfig(_Section):
    diameter_mm: Num(0.05, 50.0) = 1.2
    margin_mm: Num(0.0, 100.0) = 1.0
    #: the allowed insertion directions: this axis (a unit vector, normalised) …
    direction: Vec3 = [1.0, 0.0, 0.0]
    #: … within this half-angle (0: exactly it)
    cone_deg: Num(0.0, 89.0) = 0.0

    @field_validator("direction")
    @classmethod
    def _unit_direction(cls, v: list[float]) -> list[float]:
        return unit_3d(v, 1e-3)


class BodyControllerConfig(ControllerConfig):
    #: the controller's model of the body (docs/model.md §19): body — the body at a coarser accuracy; surrogate —
    #: learned from it; layer — the paper's 2-D section through the lesion
    model: Literal["body", "surrogate", "layer"] = "body"
    #: model layer: the sides of the section the layer holds, in the section's frame (the cup at the top, pushing
    #: down; `config.body_section`); absent: [bottom], the side opposite the cup, as the paper's rectangle was held
    section_fixed: Optional[Annotated[list[Side], Len(1, 4)]] = None
    #: the model's body (the run's plans and forward cases, and the controller's model with body or surrogate)
    #: meshed with tissue.mesh's edge bounds times this (its grading kept); the trials' truth is tissue.mesh
    #: itself, so above 1 the controller knows a coarser body than the one it moves (docs/model.md §19, "Control");
    #: tissue.accuracy_mm sets it
    mesh_scale: Num(1.0, 8.0) = 1.0


class BodyCameraConfig(CameraConfig):
    #: the point the optical axis goes through; absent: straight down −z from position_mm (the paper's CCD)
    look_at_mm: Optional[Vec3] = None


class BodyConfig(_Section):
    name: Annotated[str, Field(pattern=SCENE_NAME_PATTERN)] = "scene"
    seed: Int(0, 2**63 - 1) = 0
    tissue: BodyTissueConfig
    material: MaterialConfig = MaterialConfig()
    cups: Annotated[list[BodyCupConfig], Len(0, 16)] = []
    targets: Annotated[list[LesionConfig], Len(0, 64)] = []
    obstacles: Annotated[list[BodyObstacleConfig], Len(0, 64)] = []
    needle: BodyNeedleConfig = BodyNeedleConfig()
    controller: BodyControllerConfig = BodyControllerConfig()
    solver: SolverConfig = SolverConfig(kind="newton")
    forward: Annotated[list[ForwardCase], Len(0, 64)] = []
    camera: BodyCameraConfig = BodyCameraConfig(position_mm=[0.0, 0.0, 400.0])
    #: two or more cameras that triangulate the lesion's 3-D position; absent: `camera` alone (it does not see
    #: depth along its view)
    cameras: Optional[Annotated[list[BodyCameraConfig], Len(2, 8)]] = None
    robot: RobotConfig = RobotConfig()
    trials: TrialsConfig = TrialsConfig()
    #: the cups' grips chosen over the skin (docs/model.md §20): the first `cups` entries move there
    manipulation_points: Optional[BodyManipulationPointsConfig] = None
    #: the needle inserted along each lesion's plan after its manipulation (docs/model.md §20, §12)
    insertion: Optional[InsertionConfig] = None
    #: ultrasound with the probe on the skin instead of the camera(s) (docs/ultrasound.md, "On the body (3-D)")
    imaging: Optional[BodyImagingConfig] = None

    @property
    def dim(self) -> int:
        return 3


__all__ = ["BODY_SHAPES", "BodyCameraConfig", "BodyConfig", "BodyControllerConfig", "BodyCupConfig",
           "BodyManipulationPointsConfig", "BodyMeshConfig", "BodyNeedleConfig", "BodyObstacleConfig",
           "BodyTissueConfig", "HeldPlaneConfig", "LesionConfig", "PlaneConfig", "SkinConfig", "SkinRegionConfig",
           "SphereConfig", "TubeConfig"]
