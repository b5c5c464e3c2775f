"""The scene configuration: pydantic models, YAML loading and error messages.

Every section of the normative example scene has a model here with its
defaults. Validation happens in two passes: pydantic checks each field on its
own (types, ranges, allowed values, unknown keys), then `scene_problems`
checks what needs several fields at once (a target inside the tissue, a cup
on the boundary, obstacles that do not overlap). Both report through
`ConfigError`, whose message names the file, the dotted field, the YAML line
and what is allowed.

Units follow MODEL.md §0: mm, s, kPa, kg; angles in degrees in the config.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Optional

import numpy as np
import yaml
from annotated_types import Len
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from scissor_cli import geometry

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
    #: modified-DH table; absent means the paper's Table 2 (MODEL.md §11)
    dh: Optional[list[DHLinkConfig]] = None
    layer_origin_mm: Vec3 = [60.0, 50.0, 250.0]
    layer_yaw_deg: float = 0.0
    breast_box_mm: BoxConfig = BoxConfig(min=[60.0, 50.0, 200.0], max=[210.0, 380.0, 300.0])
    voxel_mm: PositiveFloat = 5.0


class TrialsConfig(_Section):
    """Trials per target and the error sources they draw (MODEL.md §10).

    `profile` sets every distribution (see scissor_cli/trials.py for the
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
    """The solver study (`simulate --study`): speed against error (MODEL.md §9)."""

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


# --------------------------------------------------------------------------
# Geometry that several fields define together


def tissue_outline(tissue: TissueConfig, n_curve: int = 256) -> np.ndarray:
    """The layer's outline (K, 2), counter-clockwise, in mm.

    A rectangle or ellipse spans `size_mm` from the origin at its lower-left
    corner (MODEL.md §1); an ellipse is sampled at `n_curve` points.
    """
    if tissue.shape == "rectangle":
        w, h = tissue.size_mm
        return np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    if tissue.shape == "ellipse":
        w, h = tissue.size_mm
        return geometry.ellipse_polygon((w / 2, h / 2), (w / 2, h / 2), n_curve)
    return geometry.ccw(np.asarray(tissue.polygon_mm, dtype=float))


def obstacle_outline(obstacle: ObstacleConfig, n_curve: int = 64) -> np.ndarray:
    """An obstacle's outline (K, 2), counter-clockwise, in mm."""
    if obstacle.circle is not None:
        return geometry.circle_polygon(obstacle.circle.center_mm, obstacle.circle.radius_mm, n_curve)
    return geometry.ccw(np.asarray(obstacle.polygon_mm, dtype=float))


Problem = tuple[tuple[Any, ...], str]


def _unique(items, section: str) -> list[Problem]:
    seen: dict[str, int] = {}
    out = []
    for i, item in enumerate(items):
        if item.name in seen:
            out.append(((section, i, "name"), f"duplicate name {item.name!r} (also {section}[{seen[item.name]}])"))
        seen.setdefault(item.name, i)
    return out


def scene_problems(cfg: Config) -> list[Problem]:
    """Cross-field checks pydantic cannot do field by field: [(location, message)]."""
    problems: list[Problem] = []
    t = cfg.tissue
    if t.shape == "polygon":
        if t.polygon_mm is None:
            return [(("tissue", "polygon_mm"), "required when shape is 'polygon': a list of [x, y] vertices")]
        if not geometry.is_simple(np.asarray(t.polygon_mm, float)):
            problems.append((("tissue", "polygon_mm"), "must be a simple polygon (its edges cross)"))
            return problems
    elif t.polygon_mm is not None:
        problems.append((("tissue", "polygon_mm"), f"only allowed with shape 'polygon' (shape is {t.shape!r})"))
    m = t.mesh
    if m.min_edge_mm > m.max_edge_mm:
        problems.append(
            (("tissue", "mesh", "min_edge_mm"), f"must be <= max_edge_mm ({m.max_edge_mm}); got {m.min_edge_mm}")
        )
    outline = tissue_outline(t)
    scale = float(np.ptp(outline, axis=0).max())
    on_boundary_tol = 1e-6 * scale + 1e-9

    def inside(p) -> bool:
        p = np.asarray(p, float)[None]
        return bool(geometry.points_in_polygon(p, outline)[0]) and geometry.distance_to_boundary(p, outline)[0] > 0

    problems += _unique(cfg.cups, "cups") + _unique(cfg.targets, "targets")
    problems += _unique(cfg.obstacles, "obstacles") + _unique(cfg.forward, "forward")

    for i, cup in enumerate(cfg.cups):
        d = geometry.distance_to_boundary(np.asarray(cup.contact_mm)[None], outline)[0]
        if d > max(on_boundary_tol, 1e-3):
            problems.append(
                (("cups", i, "contact_mm"), f"must lie on the tissue boundary; {cup.contact_mm} is {d:.3g} mm from it")
            )
        lo, hi = cup.stroke_mm
        if not lo < hi:
            problems.append((("cups", i, "stroke_mm"), f"must be [min, max] with min < max; got {cup.stroke_mm}"))

    for i, target in enumerate(cfg.targets):
        if not inside(target.position_mm):
            problems.append((("targets", i, "position_mm"), f"must be inside the tissue; got {target.position_mm}"))
        if target.desired_mm is not None and not inside(target.desired_mm):
            problems.append((("targets", i, "desired_mm"), f"must be inside the tissue; got {target.desired_mm}"))

    outlines = []
    for i, obs in enumerate(cfg.obstacles):
        if (obs.circle is None) == (obs.polygon_mm is None):
            problems.append((("obstacles", i), "give exactly one of 'circle' or 'polygon_mm'"))
            outlines.append(None)
            continue
        poly = obstacle_outline(obs)
        if obs.polygon_mm is not None and not geometry.is_simple(poly):
            problems.append((("obstacles", i, "polygon_mm"), "must be a simple polygon (its edges cross)"))
            outlines.append(None)
            continue
        field = "circle" if obs.circle is not None else "polygon_mm"
        if not all(inside(p) for p in poly):
            problems.append((("obstacles", i, field), f"obstacle {obs.name!r} must lie inside the tissue"))
        outlines.append(poly)
    for i in range(len(outlines)):
        for j in range(i + 1, len(outlines)):
            if outlines[i] is not None and outlines[j] is not None and geometry.polygons_overlap(outlines[i], outlines[j]):
                problems.append(
                    (("obstacles", j), f"obstacle {cfg.obstacles[j].name!r} overlaps {cfg.obstacles[i].name!r}")
                )

    cups = {c.name: c for c in cfg.cups}
    for i, case in enumerate(cfg.forward):
        for name, stroke in case.strokes.items():
            if name not in cups:
                problems.append(
                    (("forward", i, "strokes", name), f"unknown cup {name!r}; cups are {sorted(cups)}")
                )
            elif not cups[name].stroke_mm[0] <= stroke <= cups[name].stroke_mm[1]:
                problems.append(
                    (
                        ("forward", i, "strokes", name),
                        f"stroke {stroke} mm is outside cup {name!r}'s stroke_mm {cups[name].stroke_mm}",
                    )
                )
    if cfg.study is not None and cfg.study.cases is not None:
        names = {c.name for c in cfg.forward}
        for i, case in enumerate(cfg.study.cases):
            if case not in names:
                problems.append((("study", "cases", i), f"unknown forward case {case!r}; cases are {sorted(names)}"))
    lo, hi = cfg.needle.direction_range_deg
    if lo > hi or lo < -89 or hi > 89:
        problems.append(
            (("needle", "direction_range_deg"), f"must be [min, max] with -89 <= min <= max <= 89; got {[lo, hi]}")
        )
    if cfg.camera.position_mm[2] <= 0:
        problems.append((("camera", "position_mm"), "the camera must be above the layer (z > 0)"))
    return problems


# --------------------------------------------------------------------------
# Loading, with messages that point into the YAML file


class ConfigError(Exception):
    """A bad config: the message names the file, field, YAML line and what is allowed."""


@dataclass(frozen=True)
class LoadedConfig:
    config: Config
    path: Optional[Path]


def _node_at(root: Optional[yaml.Node], loc: tuple) -> tuple[Optional[yaml.Node], bool]:
    """The YAML node at a field location and True, or its nearest ancestor and False."""
    node = root
    for key in loc:
        child = None
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if k.value == str(key):
                    child = v
                    break
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            child = node.value[key]
        if child is None:
            return node, False
        node = child
    return node, True


def _loc_text(loc: tuple) -> str:
    out = ""
    for key in loc:
        out += f"[{key}]" if isinstance(key, int) else (f".{key}" if out else str(key))
    return out or "(top level)"


def _allowed_fields(loc: tuple) -> list[str]:
    model: Any = Config
    for key in loc:
        if isinstance(key, int):
            continue
        field = model.model_fields.get(key)
        if field is None:
            return []
        ann = field.annotation
        nested = [a for a in _flatten_annotation(ann) if isinstance(a, type) and issubclass(a, BaseModel)]
        if not nested:
            return []
        model = nested[0]
    return list(model.model_fields)


def _flatten_annotation(ann) -> list:
    args = getattr(ann, "__args__", None)
    if not args:
        return [ann]
    out = []
    for a in args:
        out += _flatten_annotation(a)
    return out


def _message(source: str, root, loc: tuple, what: str) -> str:
    node, exact = _node_at(root, loc)
    where = f" (line {node.start_mark.line + 1})" if node is not None else ""
    if not exact and node is not None:
        where = f" (in the block at line {node.start_mark.line + 1})"
    return f"{source}: {_loc_text(loc)}{where}: {what}"


def _pydantic_message(err: dict) -> tuple[tuple, str]:
    loc = tuple(err["loc"])
    kind = err["type"]
    if kind == "extra_forbidden":
        allowed = _allowed_fields(loc[:-1])
        return loc, f"unknown key {loc[-1]!r}; allowed keys: {', '.join(allowed)}"
    if kind == "missing":
        return loc, "required field is missing"
    got = err.get("input")
    if kind.endswith("_type") or kind in ("literal_error", "too_short", "too_long"):
        return loc, f"{err['msg']}; got {got!r}"
    return loc, f"{err['msg']}; got {got!r}"


def _duplicate_keys(node, path=()) -> list[tuple[tuple, yaml.Node]]:
    out = []
    if isinstance(node, yaml.MappingNode):
        seen = set()
        for k, v in node.value:
            if k.value in seen:
                out.append((path + (k.value,), k))
            seen.add(k.value)
            out += _duplicate_keys(v, path + (k.value,))
    elif isinstance(node, yaml.SequenceNode):
        for i, v in enumerate(node.value):
            out += _duplicate_keys(v, path + (i,))
    return out


def parse_config(text: str, source: str = "<config>") -> Config:
    """Validate YAML text into a Config, or raise ConfigError with one clear message."""
    try:
        root = yaml.compose(text)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" (line {mark.line + 1})" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{source}{line}: not valid YAML: {problem}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the top level must be a mapping of sections, got {type(data).__name__}")
    dups = _duplicate_keys(root)
    if dups:
        loc, node = dups[0]
        raise ConfigError(f"{source}: {_loc_text(loc)} (line {node.start_mark.line + 1}): key given twice")
    try:
        cfg = Config.model_validate(data)
    except ValidationError as exc:
        errors = exc.errors(include_url=False)
        msgs = [_message(source, root, *_pydantic_message(e)) for e in errors]
        extra = f"\n  (and {len(msgs) - 1} more problem(s))" if len(msgs) > 1 else ""
        raise ConfigError(msgs[0] + extra) from None
    problems = scene_problems(cfg)
    if problems:
        msgs = [_message(source, root, loc, what) for loc, what in problems]
        extra = f"\n  (and {len(msgs) - 1} more problem(s))" if len(msgs) > 1 else ""
        raise ConfigError(msgs[0] + extra)
    return cfg


def load_config(path: Path | str) -> Config:
    """Read and validate a YAML scene file (ConfigError on any problem)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the config file: {exc.strerror or exc}") from None
    return parse_config(text, str(path))


def resolved_yaml(cfg: Config) -> str:
    """The config with every default filled in, as YAML text."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False, default_flow_style=None, width=1000)
