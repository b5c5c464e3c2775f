"""The scene configuration's sections: one pydantic model per YAML section.

Every section of the normative example scene has a model here with its
defaults (docs/contract.md, "Config"). pydantic checks each field on its own:
type, range, allowed values, unknown keys. What needs several fields at once
lives in `checks`, the element budget in `budget`, the YAML reading and its
messages in `loading`.

Every number has a finite range, written next to the field (`Num(lo, hi)`:
lo <= x <= hi; `gt`/`lt` for open ends); NaN and ±inf are refused everywhere.
The ranges are wide — they admit every physically sensible scene and refuse
values that would overflow, never finish, or fill the memory — and a value
outside one is an error naming the range. Lists have documented lengths.
Units follow docs/model.md §0: mm, s, kPa, kg; angles in degrees in the config.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Optional

import numpy as np
from annotated_types import Len
from pydantic import BaseModel, ConfigDict, Field, field_validator

#: Any position (layer or robot frame), in mm: ±10 m.
COORD_MM = 10_000.0
#: The largest tissue layer, mm per side.
MAX_TISSUE_MM = 1000.0
#: Names of cups, targets, obstacles and forward cases become HDF5 groups
#: and file names: letters, digits, '_', '.', '+', '-', starting with a letter
#: or digit, at most 64 characters.
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}$"
#: The scene's own name (a title in figures): the same characters and spaces.
SCENE_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9 _.+-]{0,127}$"


def Num(lo: float | None = None, hi: float | None = None, *, gt: float | None = None, lt: float | None = None):
    """A finite float in a range: lo <= x <= hi, or gt < x / x < lt for open ends."""
    return Annotated[float, Field(ge=lo, le=hi, gt=gt, lt=lt)]


def Int(lo: int, hi: int):
    """An integer lo <= n <= hi (a YAML float such as 5.0 is not an integer)."""
    return Annotated[int, Field(ge=lo, le=hi)]


def unit_2d(v: list[float], tol: float) -> list[float]:
    """A 2-D direction normalised, refused (ValueError) when its length is off 1 by more than tol."""
    n = float(np.hypot(*v))
    if abs(n - 1.0) > tol:
        raise ValueError(f"must be a unit vector (length 1 ± {tol:g}); got length {n:.4g}")
    return [v[0] / n, v[1] / n]


Side = Literal["bottom", "top", "left", "right"]
Name = Annotated[str, Field(pattern=NAME_PATTERN)]
Coord = Num(-COORD_MM, COORD_MM)
Vec2 = Annotated[list[Coord], Len(2, 2)]
Vec3 = Annotated[list[Coord], Len(3, 3)]
Angle = Num(-360.0, 360.0)
#: relative solver tolerances: below 1e-12 a residual is rounding noise (ADMM stalls near 1e-13)
Tolerance = Num(1e-12, lt=1.0)
Spread = Num(0.0, 3.0)  # σ of a logarithm: exp(3σ) ≈ 8100 at σ = 3


class _Section(BaseModel):
    # strict: a YAML string "10" is not silently a number; extra: typos fail;
    # allow_inf_nan=False: .nan and .inf are not numbers a scene can use.
    model_config = ConfigDict(extra="forbid", strict=True, validate_default=True, allow_inf_nan=False)


#: the finest element edge a mesh may ask for, mm (min_edge_mm × scale; checks)
MIN_EDGE_MM = 0.05
#: the largest `tissue.mesh.scale`
MAX_SCALE = 100.0


class MeshConfig(_Section):
    max_edge_mm: Num(MIN_EDGE_MM, 100.0) = 4.0
    min_edge_mm: Num(MIN_EDGE_MM, 100.0) = 1.0
    min_angle_deg: Num(gt=0.0, hi=34.0) = 28.0
    #: growth of the target edge length per mm of distance from a feature
    grading: Num(0.001, 100.0) = 0.3
    #: false: a uniform mesh at min_edge_mm (the study's reference for grading)
    graded: bool = True
    #: multiplies both edge lengths (the study's refinement levels)
    scale: Num(0.01, MAX_SCALE) = 1.0
    #: a mesh to use as it is instead of meshing (config.mesh_file): an .npz with `nodes` (N, 2) mm and
    #: `triangles` (M, 3), or a scissor results .h5 (its /mesh); relative to the config file's folder.
    #: Pins the mesh so that another machine gives the same numbers (docs/contract.md, "Reproducibility")
    file: Optional[Annotated[str, Field(min_length=1, max_length=4096)]] = None
    #: the element (docs/model.md §21): p1, linear simplices with every term per element (the paper's); nodal,
    #: the same simplices with the volumetric term on the nodes (averaged nodal volume), which does not lock
    #: at ν near 0.5; needs solver.kind newton; auto, the cheaper of the two that solver.accuracy_mm's
    #: selection predicts within the accuracy (which it needs; docs/model.md §9)
    element: Literal["p1", "nodal", "auto"] = "p1"


class TissueConfig(_Section):
    shape: Literal["rectangle", "ellipse", "polygon"] = "rectangle"
    #: rectangle and ellipse: width and height, 1 mm to MAX_TISSUE_MM
    size_mm: Optional[Annotated[list[Num(1.0, MAX_TISSUE_MM)], Len(2, 2)]] = [100.0, 60.0]
    #: polygon: 3 to 1000 vertices [x, y] (spanning at most MAX_TISSUE_MM, see checks)
    polygon_mm: Optional[Annotated[list[Vec2], Len(3, 1000)]] = None
    thickness_mm: Num(0.01, MAX_TISSUE_MM) = 10.0
    fixed: Annotated[list[Side], Len(1, 4)] = ["bottom"]
    mesh: MeshConfig = MeshConfig()


class MaterialConfig(_Section):
    model: Literal["linear", "neo_hookean", "neo_hookean_fiber"] = "neo_hookean_fiber"
    #: 1 Pa to 1 GPa: fat is ~1-5 kPa, tumours ~10-100 kPa, silicone phantoms below 1 MPa
    E_kPa: Num(0.001, 1.0e6) = 10.0
    nu: Num(gt=-1.0, lt=0.5) = 0.45
    eta_kPa: Num(0.0, 1.0e6) = 0.0
    fiber_angle_deg: Angle = 0.0
    fiber_tension_only: bool = False
    #: water is 1e-6 kg/mm³
    density_kg_per_mm3: Num(1.0e-12, 1.0e-3) = 1.0e-6


class CupConfig(_Section):
    name: Name
    contact_mm: Vec2
    axis: Vec2
    radius_mm: Num(0.1, MAX_TISSUE_MM) = 5.0
    stroke_mm: Annotated[list[Num(-MAX_TISSUE_MM, MAX_TISSUE_MM)], Len(2, 2)] = [-15.0, 15.0]
    speed_mm_per_s: Num(0.01, 1000.0) = 5.0

    @field_validator("axis")
    @classmethod
    def _unit_axis(cls, v: list[float]) -> list[float]:
        return unit_2d(v, 1e-3)


class TargetConfig(_Section):
    name: Name
    position_mm: Vec2
    desired_mm: Optional[Vec2] = None


class CircleConfig(_Section):
    center_mm: Vec2
    radius_mm: Num(0.05, MAX_TISSUE_MM)


class ObstacleConfig(_Section):
    name: Name
    circle: Optional[CircleConfig] = None
    #: 3 to 500 vertices [x, y]
    polygon_mm: Optional[Annotated[list[Vec2], Len(3, 500)]] = None
    stiffness_factor: Num(0.001, 1000.0) = 1.0


class NeedleConfig(_Section):
    diameter_mm: Num(0.05, 50.0) = 1.2
    margin_mm: Num(0.0, 100.0) = 1.0
    entry_sides: Annotated[list[Side], Len(1, 4)] = ["left", "right"]
    #: [min, max] tilt, -89 <= min <= max <= 89 (checks)
    direction_range_deg: Annotated[list[Angle], Len(2, 2)] = [0.0, 0.0]
    direction_step_deg: Num(0.5, 90.0) = 5.0


class SurrogateConfig(_Section):
    """The learned controller model's training design (docs/model.md §15)."""

    #: nominal slab solves in the space-filling design (at least SURROGATE_SAMPLES_PER_CUP per cup: checks);
    #: a quarter as many again (at least 4) are solved at other strokes to measure its error
    samples: Int(2, 512) = 16


#: the fewest training samples per cup a surrogate may have (its interpolant is linear plus a spline)
SURROGATE_SAMPLES_PER_CUP = 8


class MPCConfig(_Section):
    """The model-predictive law (docs/model.md §22): a QP over `horizon` frames on the controller's model."""

    #: frames the QP looks ahead
    horizon: Int(1, 100) = 10
    #: ρ on each frame's squared stroke step (mm²) beside the squared miss (mm²): well below the along-axis weight
    #: (0.01) of the stop rule's spare cups, else the law leaves the along part the stop waits for (docs/model.md §22)
    action_weight: Num(1.0e-8, 1.0e6) = 1.0e-3


#: "package.module:Class": a dotted module, a colon, a class name (docs/model.md §22)
CLASS_PATH = r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*$"


class ControllerConfig(_Section):
    #: pid: the built-in law (docs/model.md §6); mpc: the model-predictive QP; python: your class (docs/model.md §22)
    law: Literal["pid", "mpc", "python"] = "pid"
    mpc: MPCConfig = MPCConfig()
    #: law python: the controller class, "package.module:Class", imported from `class_folder`
    class_path: Optional[Annotated[str, Field(pattern=CLASS_PATH, max_length=300)]] = None
    #: law python: the class's keyword arguments
    init_args: dict[str, Any] = {}
    #: law python: the folder `class_path` is imported from; absent: the config file's folder (stored absolute)
    class_folder: Optional[Annotated[str, Field(max_length=4096)]] = None
    kp: Num(0.0, 100.0) = 0.8
    ki: Num(0.0, 100.0) = 0.1
    kd: Num(0.0, 100.0) = 0.0
    tolerance_mm: Num(1.0e-6, 1000.0) = 0.1
    #: camera frames whose mean decides a stop at tolerance (docs/model.md §6): 1 is the paper's single frame,
    #: which stops on a frame whose noise happens to fall within tolerance; more average the pixel noise out
    stop_frames: Int(1, 100) = 1
    #: each iteration is one solve of the tissue: 10 000 is hours on a fine mesh
    max_iterations: Int(1, 10_000) = 50
    rate_hz: Num(0.01, 1000.0) = 10.0
    #: miss: drive the error across the needle axis (docs/model.md §6); position: the full 2-D error (the paper)
    error: Literal["miss", "position"] = "miss"
    #: none: J is the model's; broyden: corrected online from each observed move (docs/model.md §15)
    jacobian_update: Literal["none", "broyden"] = "none"
    #: the controller's (and planner's) model of the tissue (docs/model.md §15): layer — the 2-D layer (the paper);
    #: calibrated — the layer with one stroke transmission per cup fitted to the nominal slab; surrogate — learned
    #: from nominal slab equilibria; slab — the nominal slab itself (reference, slow). All but layer need layer_check.
    model: Literal["layer", "calibrated", "surrogate", "slab"] = "layer"
    surrogate: SurrogateConfig = SurrogateConfig()
    #: a 3-D-aware model's plan leaves this fraction of each cup's stroke limit unused (on the side it moves),
    #: room for the loop to correct the true tissue's difference from the model (docs/model.md §15); the layer's
    #: plans (the paper's method) use the whole range
    stroke_reserve: Num(0.0, 0.9) = 0.1


class ManipulationPointsConfig(_Section):
    """Where the cups grip, chosen by the planner (docs/model.md §7)."""

    #: accessible sides for candidate contact points (never a fixed side: checks)
    sides: Annotated[list[Side], Len(1, 4)] = ["top"]
    #: spacing of the candidates along the boundary
    spacing_mm: Num(0.1, MAX_TISSUE_MM) = 2.0
    #: how many cups to place: the first `cups` entries of `cups` (1 <= cups <= len(cups): checks)
    cups: Int(0, 16) = 1


class SolverConfig(_Section):
    kind: Literal["admm", "newton"] = "admm"
    #: relative tolerance of the chosen solver's residual
    tolerance: Tolerance = 1.0e-4
    #: ADMM iterations per solve: a few thousand reach 1e-6; the cap bounds a solve that cannot
    #: converge (the cap's iterations take minutes on a fine mesh)
    max_iterations: Int(1, 50_000) = 2000
    #: implicit-Euler step; absent means quasi-static equilibrium
    dt_s: Optional[Num(1.0e-4, 10.0)] = None
    #: number of implicit-Euler steps taken to reach a forward case's strokes
    steps: Int(1, 10_000) = 20
    #: Newton: relative gradient norm of the exact reference
    newton_tolerance: Tolerance = 1.0e-10
    newton_max_iterations: Int(1, 1000) = 100
    #: ADMM: Anderson acceleration memory (0 switches it off)
    anderson_memory: Int(0, 50) = 0
    #: target accuracy (mm): simulate calibrates on the scene and picks the cheapest
    #: mesh level, material model and solver predicted to meet it (None: use the config as is)
    accuracy_mm: Optional[Num(1.0e-4, 1000.0)] = None
    #: start of a forward solve: the rest state, or (a stress test of the
    #: solvers' recovery) the rest state mirrored top-to-bottom, every element inverted
    initial_guess: Literal["rest", "mirrored"] = "rest"


class ForwardCase(_Section):
    name: Name
    #: cup name -> stroke (mm), within the cup's stroke_mm (checks)
    strokes: Annotated[dict[str, Num(-MAX_TISSUE_MM, MAX_TISSUE_MM)], Len(0, 16)]


class CameraConfig(_Section):
    focal_mm: Num(0.1, 1000.0) = 8.0
    pixel_size_mm: Annotated[list[Num(1.0e-5, 1.0)], Len(2, 2)] = [0.0048, 0.0048]
    principal_point_px: Annotated[list[Num(-1.0e5, 1.0e5)], Len(2, 2)] = [640.0, 512.0]
    position_mm: Vec3 = [50.0, 30.0, 400.0]
    pixel_noise_px: Num(0.0, 1000.0) = 0.5


class DHLinkConfig(_Section):
    alpha_deg: Angle
    a_mm: Coord
    theta_deg: Angle
    d_mm: Coord
    joint: Literal["revolute", "prismatic", "fixed"]
    #: [lo, hi] in mm (prismatic) or degrees (revolute), lo <= hi (checks)
    limits: Optional[Vec2] = None


class BoxConfig(_Section):
    min: Vec3
    max: Vec3


class RobotConfig(_Section):
    #: modified-DH table of 1 to 12 links; absent means the paper's Table 2 (docs/model.md §11)
    dh: Optional[Annotated[list[DHLinkConfig], Len(1, 12)]] = None
    layer_origin_mm: Vec3 = [60.0, 50.0, 250.0]
    layer_yaw_deg: Angle = 0.0
    breast_box_mm: BoxConfig = BoxConfig(min=[60.0, 50.0, 200.0], max=[210.0, 380.0, 300.0])
    #: coverage voxels; at most MAX_VOXELS of them in the box (checks)
    voxel_mm: Num(0.1, 1000.0) = 5.0


class TrialsConfig(_Section):
    """Trials per target and the error sources they draw (docs/model.md §10).

    `profile` sets every distribution (see scissor_cli/experiments/profiles.py for the
    values and their sources); each field below, when given, overrides the
    profile's value. Spreads are standard deviations.
    """

    count: Int(0, 10_000) = 30
    profile: Literal["ideal", "prosthesis", "ex_vivo"] = "prosthesis"
    #: the closed loop's true tissue: the 2-D layer, or the 3-D slab of `layer_check` (docs/model.md §13)
    truth: Literal["layer", "slab"] = "layer"
    #: camera pixel noise σ (px); ideal: no camera error at all (no rounding)
    pixel_noise_px: Optional[Num(0.0, 1000.0)] = None
    #: per-trial bias of the target localisation, σ per axis (mm)
    localisation_error_mm: Optional[Num(0.0, 100.0)] = None
    #: true E / model E is log-normal with this σ of its logarithm
    E_log_sd: Optional[Spread] = None
    #: true ν = model ν + N(0, σ), kept below 0.499
    nu_sd: Optional[Num(0.0, 0.5)] = None
    #: true η / model η is log-normal with this σ of its logarithm
    eta_log_sd: Optional[Spread] = None
    #: true fiber angle = model angle + N(0, σ) (deg)
    fiber_angle_sd_deg: Optional[Num(0.0, 180.0)] = None
    #: smooth random field of E across the layer: σ of log E (correlation length below)
    heterogeneity_log_sd: Optional[Spread] = None
    heterogeneity_length_mm: Num(0.1, COORD_MM) = 20.0
    #: actuator resolution (mm; commands are quantised to it) and backlash (mm)
    actuator_resolution_mm: Optional[Num(0.0, 100.0)] = None
    backlash_mm: Optional[Num(0.0, 100.0)] = None
    #: slip of the tissue in the cup along the push axis after the loop stops,
    #: σ (mm): the prone position and vertical restraint the paper's bench lacked
    release_slip_mm: Optional[Num(0.0, 100.0)] = None
    #: with `insertion`: σ of log of the factor on the config's friction, and on its tip force
    friction_log_sd: Optional[Spread] = None
    tip_force_log_sd: Optional[Spread] = None
    #: with `imaging`: σ (m/s) of the tissue's sound speed about imaging.sound_speed_m_per_s
    sound_speed_sd_m_per_s: Optional[Num(0.0, 200.0)] = None
    #: with `imaging`: the probe pose's calibration error, σ of its position per axis (mm) and of its angle (deg)
    probe_position_sd_mm: Optional[Num(0.0, 10.0)] = None
    probe_angle_sd_deg: Optional[Num(0.0, 10.0)] = None
    #: with `imaging`: the electronic noise's amplitude relative to imaging.snr_db's (1: that SNR; 0: no noise)
    electronic_noise_scale: Optional[Num(0.0, 10.0)] = None
    #: a 3-D scene's: the body's registration in the robot's frame, σ of its offset per axis (mm) and of its
    #: rotation about each axis (deg), about the body's origin: the needle goes in along the planned line moved so
    registration_mm: Optional[Num(0.0, 50.0)] = None
    registration_deg: Optional[Num(0.0, 30.0)] = None
    #: a 3-D scene's: the lesion's stiffness factor (its region's E) times a log-normal factor of this σ
    lesion_stiffness_log_sd: Optional[Spread] = None
    #: the error budget (docs/model.md §16): the trials again with one error source at a time
    budget: bool = False


class InsertionConfig(_Section):
    """Needle–tissue interaction during the insertion (docs/model.md §12).

    Friction is per unit length of inserted shaft (mN/mm), static ≥ kinetic
    (checks); the defaults and their sources are in docs/model.md §12.
    """

    #: needle advance per quasi-static step (mm); positive and at most the tissue's extent (checks)
    step_mm: Num(gt=0.0, hi=COORD_MM) = 0.5
    friction_static_mN_per_mm: Num(0.0, 1.0e6) = 15.0
    friction_kinetic_mN_per_mm: Num(0.0, 1.0e6) = 10.0
    tip_force_mN: Num(0.0, 1.0e7) = 100.0
    #: radius of the disc about the tip that the tip force is spread over (mm)
    tip_zone_mm: Num(gt=0.0, hi=COORD_MM) = 2.0
    #: a node this close to the axis is captured when the tip passes it (mm);
    #: None: half the mesh's coarsest edge (max_edge_mm × scale); in a body half the mean edge at each node
    capture_radius_mm: Optional[Num(gt=0.0, hi=COORD_MM)] = None
    strategies: Annotated[list[Literal["none", "depth", "loop"]], Len(1, 3)] = ["none", "depth", "loop"]


ModelName = Literal["linear", "neo_hookean", "neo_hookean_fiber"]
#: the study's and the selection's meshes stay within the element budget (see `budget`)
_STUDY_ELEMENTS = Int(100, 125_000)


class StudyConfig(_Section):
    """The solver study (`simulate --study`): speed against error (docs/model.md §9)."""

    #: size-field scale factors (×2 coarser … ×¼ finer than the config's mesh), 1 to 12 of them
    levels: Annotated[list[Num(0.01, 100.0)], Len(1, 12)] = [2.0, 1.0, 0.5, 0.25]
    #: also uniform meshes at min_edge × level, the comparison for grading
    uniform: bool = True
    #: meshes with more elements are skipped (and said so); at most half the element budget
    max_elements: _STUDY_ELEMENTS = 60000
    models: Annotated[list[ModelName], Len(1, 3)] = ["linear", "neo_hookean", "neo_hookean_fiber"]
    admm_tolerances: Annotated[list[Tolerance], Len(1, 12)] = [1e-2, 1e-3, 1e-4, 1e-5, 1e-6]
    #: Anderson memory of the accelerated ADMM variant (0: no accelerated variant)
    anderson_memory: Int(0, 50) = 5
    admm_max_iterations: Int(1, 50_000) = 5000
    #: the ADMM sweep runs on meshes up to this size (its cost is iterations × elements)
    admm_max_elements: _STUDY_ELEMENTS = 20000
    #: timing repeats (median); a solve slower than `repeat_below_s` runs once
    repeats: Int(1, 100) = 3
    repeat_below_s: Num(gt=0.0, hi=3600.0) = 1.0
    #: forward cases to study (default: all)
    cases: Optional[Annotated[list[Name], Len(1, 64)]] = None


class LayerCheckConfig(_Section):
    """The 3-D slab around the layer that checks the layer assumption (docs/model.md §13).

    z runs from the chest wall (0) to height_mm; the simulated layer lies at
    layer_z_mm. Prism layers are thinnest (the 2-D mesh's finest edge) at the
    layer and at most max_layer_mm thick away from it.
    """

    height_mm: Num(0.01, MAX_TISSUE_MM) = 40.0
    layer_z_mm: Num(0.0, MAX_TISSUE_MM) = 20.0
    chest_wall_fixed: bool = True
    cup_holds_z: bool = True
    max_layer_mm: Num(0.01, MAX_TISSUE_MM) = 5.0
    #: the thinnest prism layer, at the layer (null: the 2-D mesh's finest edge)
    first_layer_mm: Optional[Num(0.01, MAX_TISSUE_MM)] = None
    #: the slab's 2-D mesh: tissue.mesh's edge lengths times this (1: the layer's own mesh; docs/model.md §13)
    in_plane_scale: Num(1.0, 10.0) = 1.0
    #: the coarsest slab (z grading and in-plane scale) whose targets stay within this (mm) of the finest's over
    #: the forward cases (docs/model.md §13, §18); null pins the slab as set by the fields above
    accuracy_mm: Optional[Num(1.0e-4, 100.0)] = 0.1


#: the linear arrays the ultrasound sensor simulates, `sensing.ultrasound.LINEAR_PROBES` (config does not import
#: sensing: tests/test_ultrasound_loop.py holds the two equal)
LINEAR_PROBE_NAMES = ("L11-5v", "L12-3v", "P4-2v")


class ImagingConfig(_Section):
    """Ultrasound in the loop (docs/ultrasound.md, docs/model.md §17): a linear probe on the skin images the layer's
    plane and the lesion is localised and tracked on its frames; absent, the camera measures the target.

    The probe's face is centred at position_mm on the tissue's outline,
    its beam along `axis` into the tissue (lateral: axis turned +90°); the
    image reaches depth_mm. The scanner converts echo time to depth with
    assumed_sound_speed_m_per_s, the tissue has sound_speed_m_per_s. The
    lesion is a disc (in the slab a sphere) of lesion_radius_mm about each
    target's rest position; echogenicities are in dB relative to the
    background tissue (obstacles: by their names' kind, or
    obstacle_echogenicity_db). Checks: `config.imaging_checks`.
    """

    probe: Literal[LINEAR_PROBE_NAMES] = "L11-5v"
    position_mm: Vec2 = [0.0, 30.0]
    #: the beam's direction, a unit vector (length 1 ± 0.01, normalised)
    axis: Vec2 = [1.0, 0.0]
    depth_mm: Num(5.0, 250.0) = 70.0
    assumed_sound_speed_m_per_s: Num(1000.0, 2000.0) = 1540.0
    sound_speed_m_per_s: Num(1000.0, 2000.0) = 1540.0
    lesion_radius_mm: Num(gt=0.0, hi=100.0) = 2.0
    #: not 0: a lesion like the background cannot be seen (checks)
    lesion_echogenicity_db: Num(-100.0, 40.0) = -10.0
    #: electronic noise: signal-to-noise ratio (dB) of a frame of background speckle; null: none
    snr_db: Optional[Num(-20.0, 120.0)] = 30.0
    #: fast: the fast model, validated against SIMUS; simus: the PyMUST reference (minutes per trial)
    model: Literal["fast", "simus"] = "fast"
    #: per obstacle name: its echogenicity (dB), overriding the kind its name says (docs/ultrasound.md §6)
    obstacle_echogenicity_db: Optional[Annotated[dict[str, Num(-100.0, 40.0)], Len(0, 64)]] = None

    @field_validator("axis")
    @classmethod
    def _unit_axis(cls, v: list[float]) -> list[float]:
        return unit_2d(v, 1e-2)


class Config(_Section):
    name: Annotated[str, Field(pattern=SCENE_NAME_PATTERN)] = "scene"
    #: stored in results.h5 as a signed 64-bit integer
    seed: Int(0, 2**63 - 1) = 0
    tissue: TissueConfig = TissueConfig()
    material: MaterialConfig = MaterialConfig()
    cups: Annotated[list[CupConfig], Len(1, 16)] = [
        CupConfig(name="cup", contact_mm=[50.0, 60.0], axis=[0.0, -1.0])
    ]
    targets: Annotated[list[TargetConfig], Len(0, 64)] = []
    obstacles: Annotated[list[ObstacleConfig], Len(0, 64)] = []
    needle: NeedleConfig = NeedleConfig()
    controller: ControllerConfig = ControllerConfig()
    solver: SolverConfig = SolverConfig()
    forward: Annotated[list[ForwardCase], Len(0, 64)] = []
    camera: CameraConfig = CameraConfig()
    robot: RobotConfig = RobotConfig()
    trials: TrialsConfig = TrialsConfig()
    study: Optional[StudyConfig] = None
    manipulation_points: Optional[ManipulationPointsConfig] = None
    insertion: Optional[InsertionConfig] = None
    layer_check: Optional[LayerCheckConfig] = None
    #: ultrasound in the loop instead of the camera (docs/model.md §17)
    imaging: Optional[ImagingConfig] = None
