"""The scene configuration's sections: one pydantic model per YAML section.

Every section of the normative example scene has a model here with its
defaults (docs/contract.md, "Config"). pydantic checks each field on its own:
type, range, allowed values, unknown keys. What needs several fields at once
lives in `checks`, the YAML reading and its messages in `loading`.

Units follow docs/model.md §0: mm, s, kPa, kg; angles in degrees in the config.
"""

from __future__ import annotations

from typing import Annotated, Literal, Optional

import numpy as np
from annotated_types import Len
from pydantic import BaseModel, ConfigDict, Field, field_validator

Side = Literal["bottom", "top", "left", "right"]
Vec2 = Annotated[list[float], Len(2, 2)]
Vec3 = Annotated[list[float], Len(3, 3)]
PositiveFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]


class _Section(BaseModel):
    # strict: a YAML string "10" is not silently a number; extra: typos fail.
    model_config = ConfigDict(extra="forbid", strict=True, validate_default=True)


class MeshConfig(_Section):
    max_edge_mm: PositiveFloat = 4.0
    min_edge_mm: PositiveFloat = 1.0
    min_angle_deg: Annotated[float, Field(gt=0, le=34)] = 28.0
    #: growth of the target edge length per mm of distance from a feature
    grading: PositiveFloat = 0.3
    #: false: a uniform mesh at min_edge_mm (the study's reference for grading)
    graded: bool = True
    #: multiplies both edge lengths (the study's refinement levels)
    scale: PositiveFloat = 1.0


class TissueConfig(_Section):
    shape: Literal["rectangle", "ellipse", "polygon"] = "rectangle"
    size_mm: Optional[Annotated[list[PositiveFloat], Len(2, 2)]] = [100.0, 60.0]
    polygon_mm: Optional[Annotated[list[Vec2], Len(3, None)]] = None
    thickness_mm: PositiveFloat = 10.0
    fixed: Annotated[list[Side], Len(1, 4)] = ["bottom"]
    mesh: MeshConfig = MeshConfig()


class MaterialConfig(_Section):
    model: Literal["linear", "neo_hookean", "neo_hookean_fiber"] = "neo_hookean_fiber"
    E_kPa: PositiveFloat = 10.0
    nu: Annotated[float, Field(gt=-1.0, lt=0.5)] = 0.45
    eta_kPa: NonNegFloat = 0.0
    fiber_angle_deg: float = 0.0
    fiber_tension_only: bool = False
    density_kg_per_mm3: PositiveFloat = 1.0e-6


class CupConfig(_Section):
    name: str
    contact_mm: Vec2
    axis: Vec2
    radius_mm: PositiveFloat = 5.0
    stroke_mm: Vec2 = [-15.0, 15.0]
    speed_mm_per_s: PositiveFloat = 5.0

    @field_validator("axis")
    @classmethod
    def _unit_axis(cls, v: list[float]) -> list[float]:
        n = float(np.hypot(*v))
        if abs(n - 1.0) > 1e-3:
            raise ValueError(f"must be a unit vector (length 1 ± 0.001); got length {n:.4g}")
        return [v[0] / n, v[1] / n]


class TargetConfig(_Section):
    name: str
    position_mm: Vec2
    desired_mm: Optional[Vec2] = None


class CircleConfig(_Section):
    center_mm: Vec2
    radius_mm: PositiveFloat


class ObstacleConfig(_Section):
    name: str
    circle: Optional[CircleConfig] = None
    polygon_mm: Optional[Annotated[list[Vec2], Len(3, None)]] = None
    stiffness_factor: PositiveFloat = 1.0


class NeedleConfig(_Section):
    diameter_mm: PositiveFloat = 1.2
    margin_mm: NonNegFloat = 1.0
    entry_sides: Annotated[list[Side], Len(1, 4)] = ["left", "right"]
    direction_range_deg: Vec2 = [0.0, 0.0]
    direction_step_deg: PositiveFloat = 5.0


class ControllerConfig(_Section):
    kp: NonNegFloat = 0.8
    ki: NonNegFloat = 0.1
    kd: NonNegFloat = 0.0
    tolerance_mm: PositiveFloat = 0.1
    max_iterations: Annotated[int, Field(ge=1)] = 50
    rate_hz: PositiveFloat = 10.0


class SolverConfig(_Section):
    kind: Literal["admm", "newton"] = "admm"
    #: relative tolerance of the chosen solver's residual
    tolerance: Annotated[float, Field(gt=0, lt=1)] = 1.0e-4
    max_iterations: Annotated[int, Field(ge=1)] = 2000
    #: implicit-Euler step; absent means quasi-static equilibrium
    dt_s: Optional[PositiveFloat] = None
    #: number of implicit-Euler steps taken to reach a forward case's strokes
    steps: Annotated[int, Field(ge=1)] = 20
    #: Newton: relative gradient norm of the exact reference
    newton_tolerance: Annotated[float, Field(gt=0, lt=1)] = 1.0e-10
    newton_max_iterations: Annotated[int, Field(ge=1)] = 100
    #: ADMM: Anderson acceleration memory (0 switches it off)
    anderson_memory: Annotated[int, Field(ge=0, le=50)] = 0
    #: target accuracy (mm): simulate calibrates on the scene and picks the cheapest
    #: mesh level, material model and solver predicted to meet it (None: use the config as is)
    accuracy_mm: Optional[PositiveFloat] = None
    #: start of a forward solve: the rest state, or (a stress test of the
    #: solvers' recovery) the rest state mirrored top-to-bottom, every element inverted
    initial_guess: Literal["rest", "mirrored"] = "rest"


class ForwardCase(_Section):
    name: str
    strokes: dict[str, float]


class CameraConfig(_Section):
    focal_mm: PositiveFloat = 8.0
    pixel_size_mm: Annotated[list[PositiveFloat], Len(2, 2)] = [0.0048, 0.0048]
    principal_point_px: Vec2 = [640.0, 512.0]
    position_mm: Vec3 = [50.0, 30.0, 400.0]
    pixel_noise_px: NonNegFloat = 0.5


class DHLinkConfig(_Section):
    alpha_deg: float
    a_mm: float
    theta_deg: float
    d_mm: float
    joint: Literal["revolute", "prismatic", "fixed"]
    limits: Optional[Vec2] = None


class BoxConfig(_Section):
    min: Vec3
    max: Vec3


class RobotConfig(_Section):
    #: modified-DH table; absent means the paper's Table 2 (docs/model.md §11)
    dh: Optional[list[DHLinkConfig]] = None
    layer_origin_mm: Vec3 = [60.0, 50.0, 250.0]
    layer_yaw_deg: float = 0.0
    breast_box_mm: BoxConfig = BoxConfig(min=[60.0, 50.0, 200.0], max=[210.0, 380.0, 300.0])
    voxel_mm: PositiveFloat = 5.0


class TrialsConfig(_Section):
    """Trials per target and the error sources they draw (docs/model.md §10).

    `profile` sets every distribution (see scissor_cli/experiments/profiles.py for the
    values and their sources); each field below, when given, overrides the
    profile's value. Spreads are standard deviations.
    """

    count: Annotated[int, Field(ge=0)] = 30
    profile: Literal["ideal", "prosthesis", "ex_vivo"] = "prosthesis"
    #: camera pixel noise σ (px); ideal: no camera error at all (no rounding)
    pixel_noise_px: Optional[NonNegFloat] = None
    #: per-trial bias of the target localisation, σ per axis (mm)
    localisation_error_mm: Optional[NonNegFloat] = None
    #: true E / model E is log-normal with this σ of its logarithm
    E_log_sd: Optional[NonNegFloat] = None
    #: true ν = model ν + N(0, σ), kept below 0.499
    nu_sd: Optional[NonNegFloat] = None
    #: true η / model η is log-normal with this σ of its logarithm
    eta_log_sd: Optional[NonNegFloat] = None
    #: true fiber angle = model angle + N(0, σ) (deg)
    fiber_angle_sd_deg: Optional[NonNegFloat] = None
    #: smooth random field of E across the layer: σ of log E (correlation length below)
    heterogeneity_log_sd: Optional[NonNegFloat] = None
    heterogeneity_length_mm: PositiveFloat = 20.0
    #: actuator resolution (mm; commands are quantised to it) and backlash (mm)
    actuator_resolution_mm: Optional[NonNegFloat] = None
    backlash_mm: Optional[NonNegFloat] = None
    #: slip of the tissue in the cup along the push axis after the loop stops,
    #: σ (mm): the prone position and vertical restraint the paper's bench lacked
    release_slip_mm: Optional[NonNegFloat] = None


ModelName = Literal["linear", "neo_hookean", "neo_hookean_fiber"]


class StudyConfig(_Section):
    """The solver study (`simulate --study`): speed against error (docs/model.md §9)."""

    #: size-field scale factors (×2 coarser … ×¼ finer than the config's mesh)
    levels: Annotated[list[PositiveFloat], Len(1, None)] = [2.0, 1.0, 0.5, 0.25]
    #: also uniform meshes at min_edge × level, the comparison for grading
    uniform: bool = True
    #: meshes with more elements are skipped (and said so)
    max_elements: Annotated[int, Field(ge=100)] = 60000
    models: Annotated[list[ModelName], Len(1, None)] = ["linear", "neo_hookean", "neo_hookean_fiber"]
    admm_tolerances: Annotated[list[Annotated[float, Field(gt=0, lt=1)]], Len(1, None)] = [1e-2, 1e-3, 1e-4, 1e-5, 1e-6]
    #: Anderson memory of the accelerated ADMM variant (0: no accelerated variant)
    anderson_memory: Annotated[int, Field(ge=0, le=50)] = 5
    admm_max_iterations: Annotated[int, Field(ge=1)] = 5000
    #: the ADMM sweep runs on meshes up to this size (its cost is iterations × elements)
    admm_max_elements: Annotated[int, Field(ge=100)] = 20000
    #: timing repeats (median); a solve slower than `repeat_below_s` runs once
    repeats: Annotated[int, Field(ge=1)] = 3
    repeat_below_s: PositiveFloat = 1.0
    #: forward cases to study (default: all)
    cases: Optional[list[str]] = None


class Config(_Section):
    name: str = "scene"
    seed: Annotated[int, Field(ge=0)] = 0
    tissue: TissueConfig = TissueConfig()
    material: MaterialConfig = MaterialConfig()
    cups: Annotated[list[CupConfig], Len(1, None)] = [
        CupConfig(name="cup", contact_mm=[50.0, 60.0], axis=[0.0, -1.0])
    ]
    targets: list[TargetConfig] = []
    obstacles: list[ObstacleConfig] = []
    needle: NeedleConfig = NeedleConfig()
    controller: ControllerConfig = ControllerConfig()
    solver: SolverConfig = SolverConfig()
    forward: list[ForwardCase] = []
    camera: CameraConfig = CameraConfig()
    robot: RobotConfig = RobotConfig()
    trials: TrialsConfig = TrialsConfig()
    study: Optional[StudyConfig] = None
