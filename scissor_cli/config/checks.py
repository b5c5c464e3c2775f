"""Checks that need several fields of a scene at once, and the outlines they use.

pydantic validates each field on its own (`sections`); `scene_problems`
then checks the scene as a whole: a target inside the tissue, a cup on the
boundary, obstacles inside and apart, forward strokes within the cups'
limits (docs/contract.md, "Config"). Each problem is a (location, message)
pair that `loading` turns into a message pointing into the YAML file.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from scissor_cli import geometry
from scissor_cli.config.sections import Config, ObstacleConfig, TissueConfig

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


