"""Checks that need several fields of a scene at once, and the outlines they use.

pydantic validates each field on its own (`sections`); `scene_problems`
then checks the scene as a whole: a target inside the tissue, a cup on the
boundary, obstacles inside and apart, forward strokes within the cups'
limits (docs/contract.md, "Config"). Each problem is a (location, message)
pair that `loading` turns into a message pointing into the YAML file.

Besides geometry, two checks bound the work a scene can ask for:
`MAX_TIME_STEPS` implicit-Euler steps per forward case (with `solver.dt_s`)
and `MAX_VOXELS` coverage voxels in the robot's breast box.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from scissor_cli import geometry
from scissor_cli.config.imaging_checks import imaging_problems
from scissor_cli.config.mesh_file import MeshFileError, mesh_file_problem, read_mesh_arrays
from scissor_cli.config.sections import (
    MAX_TISSUE_MM,
    MIN_EDGE_MM,
    SURROGATE_SAMPLES_PER_CUP,
    Config,
    ObstacleConfig,
    TissueConfig,
)

#: implicit-Euler steps (ramp + settling) one forward case may take with solver.dt_s
MAX_TIME_STEPS = 10_000
#: voxels of robot.voxel_mm in robot.breast_box_mm (the paper's box at 5 mm has 39 600)
MAX_VOXELS = 2_000_000
#: outline vertices of all obstacles together (a circle counts 64): bounds the pairwise overlap test
MAX_OBSTACLE_VERTICES = 5000
#: the smallest area of the tissue polygon and of an obstacle, mm²
MIN_TISSUE_AREA_MM2 = 1.0
MIN_OBSTACLE_AREA_MM2 = 0.01
#: the fewest straight edges the mesher follows an ellipse with (scissor_cli/scene/scene.py);
#: every such inscribed polygon holds the ellipse scaled by cos(pi / n) about its centre
ELLIPSE_MIN_POINTS = 32

def tissue_outline(tissue: TissueConfig, n_curve: int = 256) -> np.ndarray:
    """The layer's outline (K, 2), counter-clockwise, in mm.

    A rectangle or ellipse spans `size_mm` from the origin at its lower-left
    corner (docs/model.md §1); an ellipse is sampled at `n_curve` points.
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


def _polygon_problem(poly: np.ndarray, min_area: float) -> str | None:
    """Why a user-given polygon cannot be meshed, or None."""
    if np.any(np.linalg.norm(np.roll(poly, -1, axis=0) - poly, axis=1) < 1e-6):
        return "must have distinct consecutive vertices (an edge has length 0)"
    if not geometry.is_simple(poly):
        return "must be a simple polygon (its edges cross)"
    area = abs(geometry.signed_area(poly))
    if area < min_area:
        return f"must enclose at least {min_area:g} mm²; encloses {area:.3g} mm²"
    return None


def _tissue_problems(cfg: Config) -> tuple[list[Problem], np.ndarray | None]:
    """Problems of the layer itself and, when it has none that stop the rest, its outline."""
    t = cfg.tissue
    problems: list[Problem] = []
    if t.shape == "polygon":
        if t.polygon_mm is None:
            return [(("tissue", "polygon_mm"), "required when shape is 'polygon': a list of [x, y] vertices")], None
        poly = np.asarray(t.polygon_mm, float)
        why = _polygon_problem(poly, MIN_TISSUE_AREA_MM2)
        if why is None and np.ptp(poly, axis=0).max() > MAX_TISSUE_MM:
            why = f"must span at most {MAX_TISSUE_MM:g} mm; spans {np.ptp(poly, axis=0).max():.4g} mm"
        if why is not None:
            return [(("tissue", "polygon_mm"), why)], None
    else:
        if t.size_mm is None:
            return [(("tissue", "size_mm"), f"required when shape is {t.shape!r}: [width, height] in mm")], None
        if t.polygon_mm is not None:
            problems.append((("tissue", "polygon_mm"), f"only allowed with shape 'polygon' (shape is {t.shape!r})"))
    m = t.mesh
    if m.min_edge_mm > m.max_edge_mm:
        problems.append(
            (("tissue", "mesh", "min_edge_mm"), f"must be <= max_edge_mm ({m.max_edge_mm}); got {m.min_edge_mm}")
        )
    if m.min_edge_mm * m.scale < MIN_EDGE_MM * (1 - 1e-12):
        problems.append((("tissue", "mesh", "scale"), (
            f"min_edge_mm × scale = {m.min_edge_mm * m.scale:.3g} mm; the finest edge a mesh may ask for is "
            f"{MIN_EDGE_MM:g} mm")))
    return problems, tissue_outline(t)


def _inside(points, outline: np.ndarray, tissue: TissueConfig) -> np.ndarray:
    """(K,) True where points (K, 2) are strictly inside the tissue (not on its outline).

    An ellipse is meshed as an inscribed polygon of ELLIPSE_MIN_POINTS or more
    edges, so a point counts as inside only within the ellipse scaled by
    cos(pi / ELLIPSE_MIN_POINTS), which every such polygon holds.
    """
    p = np.asarray(points, float).reshape(-1, 2)
    if tissue.shape == "ellipse":
        a, b = tissue.size_mm[0] / 2, tissue.size_mm[1] / 2
        q = ((p[:, 0] - a) / a) ** 2 + ((p[:, 1] - b) / b) ** 2
        return q < np.cos(np.pi / ELLIPSE_MIN_POINTS) ** 2 * (1 - 1e-9)
    return geometry.points_in_polygon(p, outline) & (geometry.distance_to_boundary(p, outline) > 0)


def _inside_text(tissue: TissueConfig) -> str:
    if tissue.shape != "ellipse":
        return "inside the tissue"
    return (f"inside the tissue (of an ellipse, the part within {np.cos(np.pi / ELLIPSE_MIN_POINTS):.4f} of its "
            f"semi-axes: the mesh follows the outline with {ELLIPSE_MIN_POINTS} or more straight edges)")


def _obstacle_problems(cfg: Config, outline: np.ndarray) -> list[Problem]:
    problems: list[Problem] = []
    outlines: list[np.ndarray | None] = []
    for i, obs in enumerate(cfg.obstacles):
        if (obs.circle is None) == (obs.polygon_mm is None):
            problems.append((("obstacles", i), "give exactly one of 'circle' or 'polygon_mm'"))
            outlines.append(None)
            continue
        why = (None if obs.polygon_mm is None
               else _polygon_problem(np.asarray(obs.polygon_mm, float), MIN_OBSTACLE_AREA_MM2))
        if why is not None:
            problems.append((("obstacles", i, "polygon_mm"), why))
            outlines.append(None)
            continue
        poly = obstacle_outline(obs)
        field = "circle" if obs.circle is not None else "polygon_mm"
        if obs.circle is not None:  # the 64-gon pushed out to hold the circle, and so any polygon inscribed in it
            c = np.asarray(obs.circle.center_mm)
            poly = c + (poly - c) / np.cos(np.pi / len(poly))
        if not _inside(poly, outline, cfg.tissue).all():
            problems.append((("obstacles", i, field), f"obstacle {obs.name!r} must lie {_inside_text(cfg.tissue)}"))
        outlines.append(poly)
    total = sum(len(o) for o in outlines if o is not None)
    if total > MAX_OBSTACLE_VERTICES:
        problems.append((("obstacles",), (f"{total} outline vertices in all (a circle counts 64); at most "
                                          f"{MAX_OBSTACLE_VERTICES}: use fewer or simpler obstacles")))
        return problems
    boxes = [None if o is None else (o.min(axis=0), o.max(axis=0)) for o in outlines]
    for i in range(len(outlines)):
        for j in range(i + 1, len(outlines)):
            if boxes[i] is None or boxes[j] is None:
                continue
            if np.any(boxes[i][1] < boxes[j][0]) or np.any(boxes[j][1] < boxes[i][0]):
                continue  # bounding boxes apart: no overlap to test
            if geometry.polygons_overlap(outlines[i], outlines[j]):
                problems.append(
                    (("obstacles", j), f"obstacle {cfg.obstacles[j].name!r} overlaps {cfg.obstacles[i].name!r}")
                )
                continue
            # outlines are mesh segments: coincident or touching ones are not a mesh (Triangle fails on them)
            gap = _outline_gap(outlines[i], outlines[j])
            if gap < MIN_EDGE_MM:
                problems.append((("obstacles", j), (
                    f"obstacle {cfg.obstacles[j].name!r} is {gap:.3g} mm from {cfg.obstacles[i].name!r}; obstacles "
                    f"must be at least {MIN_EDGE_MM:g} mm apart (the finest mesh edge) or merged into one")))
    return problems


def _outline_gap(p: np.ndarray, q: np.ndarray) -> float:
    """The smallest distance (mm) between two closed outlines' edges (0 where they touch or coincide)."""
    pa, pb = geometry.edges(p)
    qa, qb = geometry.edges(q)
    return float(min(geometry.point_segment_distance(p, qa, qb).min(),
                     geometry.point_segment_distance(q, pa, pb).min()))


def _cup_and_target_problems(cfg: Config, outline: np.ndarray) -> list[Problem]:
    problems: list[Problem] = []
    on_boundary_tol = max(1e-6 * float(np.ptp(outline, axis=0).max()) + 1e-9, 1e-3)
    fixed = np.zeros(len(outline), bool)
    for side in cfg.tissue.fixed:
        facing = geometry.side_edge_mask(outline, side)
        if not facing.any():
            problems.append((("tissue", "fixed"), f"the outline has no edge facing {side!r} to hold"))
        fixed |= facing
    a, b = geometry.edges(outline)
    for i, cup in enumerate(cfg.cups):
        d = geometry.distance_to_boundary(np.asarray(cup.contact_mm)[None], outline)[0]
        if d > on_boundary_tol:
            problems.append(
                (("cups", i, "contact_mm"), f"must lie on the tissue boundary; {cup.contact_mm} is {d:.3g} mm from it")
            )
            continue
        if fixed.any():
            reach = geometry.point_segment_distance(np.asarray(cup.contact_mm)[None], a[fixed], b[fixed]).min()
            if reach <= cup.radius_mm:
                problems.append((("cups", i, "radius_mm"), (
                    f"the grip ({cup.radius_mm:g} mm around the contact) reaches a fixed side "
                    f"({', '.join(cfg.tissue.fixed)}) {reach:.3g} mm away; move the cup or shrink radius_mm")))
        lo, hi = cup.stroke_mm
        if not lo < hi:
            problems.append((("cups", i, "stroke_mm"), f"must be [min, max] with min < max; got {cup.stroke_mm}"))
    for i, target in enumerate(cfg.targets):
        if not _inside(target.position_mm, outline, cfg.tissue)[0]:
            problems.append((("targets", i, "position_mm"),
                             f"must be {_inside_text(cfg.tissue)}; got {target.position_mm}"))
        if target.desired_mm is not None and not _inside(target.desired_mm, outline, cfg.tissue)[0]:
            problems.append((("targets", i, "desired_mm"),
                             f"must be {_inside_text(cfg.tissue)}; got {target.desired_mm}"))
    return problems


def surrogate_samples_problems(controller, n_cups: int) -> list[Problem]:
    """A surrogate's design must have SURROGATE_SAMPLES_PER_CUP samples per cup (a layer's or a body's)."""
    need = SURROGATE_SAMPLES_PER_CUP * n_cups
    if controller.model != "surrogate" or controller.surrogate.samples >= need:
        return []
    return [(("controller", "surrogate", "samples"), (
        f"a surrogate of {n_cups} cup(s) needs at least {need} samples "
        f"({SURROGATE_SAMPLES_PER_CUP} per cup); got {controller.surrogate.samples}"))]


def _forward_problems(cfg: Config) -> list[Problem]:
    problems: list[Problem] = []
    cups = {c.name: c for c in cfg.cups}
    for i, case in enumerate(cfg.forward):
        for name, stroke in case.strokes.items():
            if name not in cups:
                problems.append((("forward", i, "strokes", name), f"unknown cup {name!r}; cups are {sorted(cups)}"))
            elif not cups[name].stroke_mm[0] <= stroke <= cups[name].stroke_mm[1]:
                problems.append((("forward", i, "strokes", name),
                                 f"stroke {stroke} mm is outside cup {name!r}'s stroke_mm {cups[name].stroke_mm}"))
    dt = cfg.solver.dt_s
    if dt is not None and cfg.forward and not problems:
        speed = {c.name: c.speed_mm_per_s for c in cfg.cups}
        ramp_s = max((abs(v) / speed[k] for case in cfg.forward for k, v in case.strokes.items()), default=0.0)
        steps = max(int(np.ceil(ramp_s / dt)), 1) + cfg.solver.steps
        if steps > MAX_TIME_STEPS:
            problems.append((("solver", "dt_s"), (
                f"a forward case would take {steps} implicit-Euler steps (ramp {ramp_s:.4g} s at the cups' speed, "
                f"plus solver.steps {cfg.solver.steps}); at most {MAX_TIME_STEPS} — use a larger dt_s or faster cups")))
    return problems


def _run_problems(cfg: Config) -> list[Problem]:
    """What the solver study and the accuracy selection need of the scene."""
    problems: list[Problem] = []
    if cfg.study is not None:
        if not cfg.targets:
            problems.append((("study",), "the study measures target errors: the scene needs at least one target"))
        if not cfg.forward:
            problems.append((("study",), "the study solves the forward cases: the scene needs at least one"))
        names = {c.name for c in cfg.forward}
        for i, case in enumerate(cfg.study.cases or []):
            if case not in names:
                problems.append((("study", "cases", i), f"unknown forward case {case!r}; cases are {sorted(names)}"))
    if cfg.solver.accuracy_mm is not None and not cfg.targets:
        problems.append((("solver", "accuracy_mm"),
                         "the accuracy is measured at the targets: the scene needs at least one"))
    # (with solver.accuracy_mm the selection picks the solver: ADMM only on p1)
    if cfg.tissue.mesh.element == "nodal" and cfg.solver.kind == "admm" and cfg.solver.accuracy_mm is None:
        # ADMM's local step is one element's energy; the nodal volume term couples the elements around a node
        problems.append((("solver", "kind"), "'admm' needs every energy term per element; element 'nodal' puts "
                         "the volumetric term on the nodes (docs/model.md §21): use solver.kind newton, or "
                         "tissue.mesh.element p1"))
    if cfg.tissue.mesh.element == "auto" and cfg.solver.accuracy_mm is None:
        problems.append((("tissue", "mesh", "element"), "auto picks the element by the accuracy asked for: give "
                         "solver.accuracy_mm, or name the element (p1 or nodal)"))
    return problems


def _robot_problems(cfg: Config) -> list[Problem]:
    problems: list[Problem] = []
    r = cfg.robot
    lo, hi = np.asarray(r.breast_box_mm.min), np.asarray(r.breast_box_mm.max)
    if not np.all(hi > lo):
        problems.append((("robot", "breast_box_mm"), f"max must exceed min on every axis; "
                                                     f"got min {r.breast_box_mm.min}, max {r.breast_box_mm.max}"))
    else:
        voxels = float(np.prod(np.maximum(1, np.ceil((hi - lo) / r.voxel_mm - 1e-9))))
        if voxels > MAX_VOXELS:
            problems.append((("robot", "voxel_mm"), (f"the breast box holds {voxels:.3g} voxels of {r.voxel_mm:g} mm; "
                                                     f"at most {MAX_VOXELS} — use larger voxels")))
    if r.dh is not None:
        if all(row.joint == "fixed" for row in r.dh):
            problems.append((("robot", "dh"), "a robot needs at least one revolute or prismatic joint"))
        for i, row in enumerate(r.dh):
            if row.joint == "fixed":
                continue
            if row.limits is None:
                problems.append((("robot", "dh", i, "limits"), f"required for a {row.joint} joint: [lo, hi]"))
            elif not row.limits[0] <= row.limits[1]:
                problems.append((("robot", "dh", i, "limits"), f"must be [lo, hi] with lo <= hi; got {row.limits}"))
    return problems


def _manipulation_point_problems(cfg: Config) -> list[Problem]:
    """Candidate sides must be free, and there must be cups to place (docs/model.md §7)."""
    mp = cfg.manipulation_points
    if mp is None:
        return []
    problems: list[Problem] = []
    for i, side in enumerate(mp.sides):
        if side in cfg.tissue.fixed:
            problems.append((("manipulation_points", "sides", i), (
                f"side {side!r} is fixed (tissue.fixed {list(cfg.tissue.fixed)}): a cup cannot grip a held side")))
    if mp.cups == 0:
        problems.append((("manipulation_points", "cups"),
                         "0 cups to place: ask for at least 1, or leave out the manipulation_points section"))
    elif mp.cups > len(cfg.cups):
        problems.append((("manipulation_points", "cups"), (
            f"{mp.cups} cups to place but the scene lists {len(cfg.cups)} in `cups`; the chosen points replace "
            f"contact_mm and axis of the first entries, so add entries or place fewer")))
    return problems


def _layer_check_problems(cfg: Config) -> list[Problem]:
    """The slab of docs/model.md §13: the layer inside it, room for one prism layer; truth: slab needs it."""
    problems: list[Problem] = []
    lc = cfg.layer_check
    if lc is None:
        if cfg.trials.truth == "slab":
            problems.append((("trials", "truth"),
                             "truth 'slab' is the 3-D slab of layer_check: add a layer_check section"))
        if cfg.controller.model != "layer":
            problems.append((("controller", "model"), (
                f"model {cfg.controller.model!r} is made from the 3-D slab of layer_check: add a layer_check section, "
                f"or use model 'layer'")))
        return problems
    problems += surrogate_samples_problems(cfg.controller, len(cfg.cups))
    if lc.layer_z_mm > lc.height_mm:
        problems.append((("layer_check", "layer_z_mm"),
                         f"the layer must lie inside the slab: 0 <= layer_z_mm <= height_mm {lc.height_mm:g}; "
                         f"got {lc.layer_z_mm:g}"))
    finest = cfg.tissue.mesh.min_edge_mm * cfg.tissue.mesh.scale
    if lc.height_mm < finest:
        problems.append((("layer_check", "height_mm"), (
            f"the slab is too thin for one prism layer: height_mm {lc.height_mm:g} is below the layer's finest edge "
            f"(tissue.mesh.min_edge_mm × scale = {finest:g} mm)")))
    if lc.first_layer_mm is not None and lc.first_layer_mm > lc.max_layer_mm:
        problems.append((("layer_check", "first_layer_mm"), (
            f"the thinnest prism layer cannot be thicker than the thickest: first_layer_mm {lc.first_layer_mm:g} "
            f"> max_layer_mm {lc.max_layer_mm:g}")))
    return problems


def scene_problems(cfg: Config) -> list[Problem]:
    """Cross-field checks pydantic cannot do field by field: [(location, message)]."""
    problems, outline = _tissue_problems(cfg)
    if outline is None:
        return problems
    problems += _unique(cfg.cups, "cups") + _unique(cfg.targets, "targets")
    problems += _unique(cfg.obstacles, "obstacles") + _unique(cfg.forward, "forward")
    problems += _cup_and_target_problems(cfg, outline)
    problems += _obstacle_problems(cfg, outline)
    problems += _forward_problems(cfg)
    problems += _run_problems(cfg)
    lo, hi = cfg.needle.direction_range_deg
    if lo > hi or lo < -89 or hi > 89:
        problems.append(
            (("needle", "direction_range_deg"), f"must be [min, max] with -89 <= min <= max <= 89; got {[lo, hi]}")
        )
    if cfg.camera.position_mm[2] <= 0:
        problems.append((("camera", "position_mm"), "the camera must be above the layer (z > 0)"))
    problems += _robot_problems(cfg)
    problems += _manipulation_point_problems(cfg)
    problems += insertion_problems(cfg.insertion, float(np.max(outline.max(axis=0) - outline.min(axis=0))))
    problems += _layer_check_problems(cfg)
    problems += imaging_problems(cfg, outline, lambda p, o: _inside(p, o, cfg.tissue))
    problems += _point_spacing_problems(cfg)
    if cfg.trials.budget and cfg.trials.count == 0:
        problems.append((("trials", "budget"), "the error budget reruns the trials: it needs trials.count >= 1"))
    for name in ("registration_mm", "registration_deg", "lesion_stiffness_log_sd"):
        if getattr(cfg.trials, name):
            problems.append((("trials", name), "a 3-D scene's error source (the body's registration, the lesion's "
                             "stiffness; docs/model.md §20): a layer has none, leave it out"))
    if not problems:  # reading a mesh file is worth it only for an otherwise sound scene
        problems += _mesh_file_problems(cfg, outline)
    return problems


def _point_spacing_problems(cfg: Config) -> list[Problem]:
    """Targets are mesh vertices: two closer than the finest edge a mesh may have cannot both be meshed."""
    problems: list[Problem] = []
    for j, b in enumerate(cfg.targets):
        for a in cfg.targets[:j]:
            d = float(np.hypot(*np.subtract(a.position_mm, b.position_mm)))
            if d < MIN_EDGE_MM:
                problems.append((("targets", j, "position_mm"), (
                    f"target {b.name!r} is {d:.3g} mm from target {a.name!r}; targets must be at least "
                    f"{MIN_EDGE_MM:g} mm apart (the finest mesh edge; each target is a mesh vertex)")))
    return problems


def _mesh_file_problems(cfg: Config, outline: np.ndarray) -> list[Problem]:
    """A `tissue.mesh.file` must be a readable mesh of this scene's layer (config.mesh_file)."""
    m = cfg.tissue.mesh
    if m.file is None:
        return []
    where = ("tissue", "mesh", "file")
    if cfg.solver.accuracy_mm is not None:
        return [(where, "a mesh file pins the mesh, solver.accuracy_mm chooses one: give one of the two")]
    if m.scale != 1.0:
        return [(where, f"a mesh file is used as it is: tissue.mesh.scale must be 1 with it; got {m.scale:g}")]
    try:
        nodes, triangles = read_mesh_arrays(m.file)
    except MeshFileError as exc:
        return [(where, f"{m.file}: {exc}")]
    points = np.array([t.position_mm for t in cfg.targets] + [c.contact_mm for c in cfg.cups], float).reshape(-1, 2)
    why = mesh_file_problem(nodes, triangles, outline, points)
    return [] if why is None else [(where, f"{m.file}: {why}")]


def insertion_problems(ins, extent_mm: float) -> list[Problem]:
    """Kinetic friction at most static, a step shorter than the tissue (`extent_mm` across), strategies once each
    (docs/model.md §12); a layer's or a body's `insertion` section, or None."""
    if ins is None:
        return []
    problems: list[Problem] = []
    if ins.friction_kinetic_mN_per_mm > ins.friction_static_mN_per_mm:
        problems.append((("insertion", "friction_kinetic_mN_per_mm"), (
            f"kinetic friction {ins.friction_kinetic_mN_per_mm:g} mN/mm exceeds the static friction "
            f"{ins.friction_static_mN_per_mm:g} mN/mm; it must be at most the static one")))
    if ins.step_mm > extent_mm:
        problems.append((("insertion", "step_mm"),
                         f"a step of {ins.step_mm:g} mm is longer than the tissue ({extent_mm:g} mm across)"))
    if len(set(ins.strategies)) != len(ins.strategies):
        problems.append((("insertion", "strategies"), f"each strategy at most once; got {ins.strategies}"))
    return problems
