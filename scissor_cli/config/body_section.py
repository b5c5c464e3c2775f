"""The paper's reduction of a body: its section through a lesion as a 2-D layer scene (docs/model.md §19, "Control").

`controller.model: layer` gives a 3-D scene's controller the paper's model:
the 2-D layer of §1–5 on the body's section through the lesion.

* **The plane** goes through the lesion's rest position and holds the first
  cup's axis u and the scene's needle direction n (`needle.direction`, the
  axis of the allowed cone: one plane per lesion, whatever the planner turns
  within the cone). Its frame: e2 = −u, e1 = n made normal to u, the origin
  the body frame's origin projected onto the plane. The cup so sits at the
  top of the section and pushes down; on the paper's bench (cup and needle
  horizontal) the section is the horizontal plane through the lesion, and
  the layer's (x, y) are the body's.
* **The outline** is the zero level of the body's signed depth sampled on
  the plane (scikit-image's marching squares), the loop around the lesion,
  simplified to within 1/50 of the grid's step (Douglas–Peucker), so a
  face's edge stays straight and keeps its corners.
* **The layer** has the body's material with the fiber direction projected
  into the plane, and nothing else: lesions and obstacles are not in it (the
  paper's layer had none). It is meshed at the body's edge lengths, and has
  every cup the plane cuts (the contact within the cup's radius of the plane,
  the axis within AXIS_TOL_DEG of it) at the outline point nearest its
  contact; a cup the plane misses is refused, since the layer could not move it.
* **Held sides — the reduction's assumption.** A section of a body held at
  its base has no held edge of its own. `controller.section_fixed` names
  the sides of the section's frame that the layer holds (those whose outward
  normal is within 45° of the side's, as for any layer); the default [bottom]
  is the side opposite the cup, as the paper's rectangle was held.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import ValidationError

from scissor_cli import geometry
from scissor_cli.config.body_checks import Problem, body_apex, body_box, body_surface, skin_normals
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.config.checks import scene_problems
from scissor_cli.config.sections import Config

#: a cup's axis may leave the section's plane by this much, degrees (its push is then projected into the plane)
AXIS_TOL_DEG = 10.0
#: the layer's thickness, mm: the cups move their patches by strokes, so no displacement depends on it
SECTION_THICKNESS_MM = 10.0
#: the signed depth is sampled on a grid of at most this many points per side of the body's extent
GRID_POINTS = 240
#: the most outline points a layer polygon may have (`tissue.polygon_mm`)
MAX_OUTLINE_POINTS = 1000
#: the held sides when `controller.section_fixed` is absent: the side opposite the cup
DEFAULT_SECTION_FIXED = ("bottom",)


class SectionError(ValueError):
    """The section a layer model needs cannot be made (the message says why)."""


@dataclass(frozen=True)
class SectionPlane:
    """A plane in the body: origin (3,) mm and basis (3, 2) of orthonormal columns e1, e2."""

    origin: np.ndarray
    basis: np.ndarray

    @property
    def normal(self) -> np.ndarray:
        """(3,) the unit normal e1 × e2."""
        return np.cross(self.basis[:, 0], self.basis[:, 1])

    def to_plane(self, points: np.ndarray) -> np.ndarray:
        """Coordinates (K, 2) mm in the plane of points (K, 3) mm (projected onto it)."""
        return (np.atleast_2d(points) - self.origin) @ self.basis

    def to_body(self, points: np.ndarray) -> np.ndarray:
        """Points (K, 3) mm of the body at plane coordinates (K, 2) mm."""
        return self.origin + np.atleast_2d(points) @ self.basis.T


def section_plane(through: np.ndarray, cup_axis: np.ndarray, needle_direction: np.ndarray) -> SectionPlane:
    """The plane through `through` (3,) holding the cup's axis and the needle's direction (3,) (module doc)."""
    u = np.asarray(cup_axis, float) / np.linalg.norm(cup_axis)
    n = np.asarray(needle_direction, float) / np.linalg.norm(needle_direction)
    m = np.cross(u, n)
    if np.linalg.norm(m) < np.sin(np.deg2rad(AXIS_TOL_DEG)):
        raise SectionError(f"the cup's axis is within {AXIS_TOL_DEG:g}° of the needle's direction: the two span "
                           f"no plane to cut the body with")
    m /= np.linalg.norm(m)
    e2 = -u
    e1 = np.cross(e2, m)  # = n − (n·u) u, normalised
    return SectionPlane(np.dot(through, m) * m, np.column_stack([e1, e2]))


def section_outline(surface, plane: SectionPlane, inside: np.ndarray) -> np.ndarray:
    """The section's outline around the plane point `inside` (2,): a counter-clockwise polygon (P, 2) mm.

    The zero level of the surface's signed depth on a grid over the body's
    box (step h: GRID_POINTS across it), the closed loop that holds `inside`
    (the smallest, when loops nest), simplified (Douglas–Peucker) to within
    h/50 of it: a face's edge becomes one straight edge between its corners,
    a curve keeps its vertices dense (a cup's grip on a coarse polygon would
    not be symmetric about its contact). The mesher places its own boundary
    points along the edges.
    """
    from skimage.measure import approximate_polygon, find_contours  # (heavy: scipy.signal; only a body's section)

    lo, hi = body_box(surface)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    c2 = plane.to_plane(corners)
    h = float(np.max(c2.max(axis=0) - c2.min(axis=0))) / GRID_POINTS
    a = np.arange(c2[:, 0].min() - 2 * h, c2[:, 0].max() + 3 * h, h)
    b = np.arange(c2[:, 1].min() - 2 * h, c2[:, 1].max() + 3 * h, h)
    grid = np.stack(np.meshgrid(a, b, indexing="ij"), axis=-1).reshape(-1, 2)
    depth = surface.depth(plane.to_body(grid)).reshape(len(a), len(b))
    loops = []
    for c in find_contours(depth, 0.0):
        if len(c) < 4 or np.linalg.norm(c[0] - c[-1]) > 1e-9:
            continue  # (open: the grid's padding is outside the body, so only a degenerate loop is)
        poly = np.column_stack([a[0] + c[:, 0] * h, b[0] + c[:, 1] * h])
        if geometry.points_in_polygon(np.asarray(inside, float)[None], poly[:-1])[0]:
            loops.append(poly)
    if not loops:
        raise SectionError("the section does not hold the lesion: no outline loop surrounds it")
    closed = min(loops, key=lambda p: abs(geometry.signed_area(p[:-1])))
    tolerance = h / 50
    while True:
        poly = approximate_polygon(closed, tolerance)[:-1]
        if len(poly) <= MAX_OUTLINE_POINTS:
            return geometry.ccw(poly)
        tolerance *= 2


def section_config(cfg: BodyConfig, index: int, surface=None) -> tuple[Config, SectionPlane]:
    """The 2-D layer scene of the section through target `index` of a validated body config, and its plane.

    surface: the body's (`body_checks.body_surface`; read from the config when None). SectionError when the
    plane cannot be cut, misses a cup or the layer is not a valid scene.
    """
    if not cfg.cups:
        raise SectionError("the layer model needs a cup: its axis lays the section")
    surface = body_surface(cfg) if surface is None else surface
    lesion = cfg.targets[index]
    contacts, _ = surface.nearest_skin(np.array([c.contact_mm for c in cfg.cups], float))
    normals = skin_normals(surface, contacts)
    axes = np.array([-normals[i] if c.axis is None else np.asarray(c.axis, float) for i, c in enumerate(cfg.cups)])
    rest = np.asarray(lesion.position_mm, float)
    plane = section_plane(rest, axes[0], np.asarray(cfg.needle.direction, float))
    outline = section_outline(surface, plane, plane.to_plane(rest)[0])
    cups = []
    for i, c in enumerate(cfg.cups):
        off = float(abs((contacts[i] - plane.origin) @ plane.normal))
        if off > c.radius_mm:
            raise SectionError(f"cup {c.name!r} is {off:.1f} mm from the section through {lesion.name!r}, farther "
                               f"than its radius ({c.radius_mm:g} mm): the layer could not move it")
        tilt = float(np.degrees(np.arcsin(min(1.0, abs(axes[i] @ plane.normal)))))
        if tilt > AXIS_TOL_DEG:
            raise SectionError(f"cup {c.name!r}'s axis leaves the section through {lesion.name!r} by {tilt:.0f}° "
                               f"(at most {AXIS_TOL_DEG:g}°)")
        axis2 = axes[i] @ plane.basis
        contact2 = geometry.nearest_on_boundary(plane.to_plane(contacts[i]), outline)[0]
        cups.append({"name": c.name, "contact_mm": contact2.tolist(), "axis": (axis2 / np.linalg.norm(axis2)).tolist(),
                     "radius_mm": c.radius_mm, "stroke_mm": list(c.stroke_mm), "speed_mm_per_s": c.speed_mm_per_s})
    layer_data = {
        "name": cfg.name, "seed": cfg.seed,
        "tissue": {"shape": "polygon", "polygon_mm": outline.tolist(), "thickness_mm": SECTION_THICKNESS_MM,
                   "fixed": list(cfg.controller.section_fixed or DEFAULT_SECTION_FIXED),
                   "mesh": {"max_edge_mm": cfg.tissue.mesh.max_edge_mm, "min_edge_mm": cfg.tissue.mesh.min_edge_mm}},
        "material": cfg.material.model_dump() | {"fiber_angle_deg": _fiber_angle_deg(cfg, surface, plane, rest)},
        "cups": cups,
        "targets": [{"name": lesion.name, "position_mm": plane.to_plane(rest)[0].tolist()}],
        "controller": cfg.controller.model_dump(exclude={"model", "section_fixed", "mesh_scale"}),
        "solver": cfg.solver.model_dump(),
    }
    try:
        layer = Config.model_validate(layer_data)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        raise SectionError(f"its layer is not a valid scene: {'.'.join(map(str, first['loc']))}: {first['msg']}") \
            from None
    problems = scene_problems(layer)
    if problems:
        (where, what), *_ = problems
        raise SectionError(f"its layer is not a valid scene: {'.'.join(map(str, where))}: {what}")
    return layer, plane


def _fiber_angle_deg(cfg: BodyConfig, surface, plane: SectionPlane, rest: np.ndarray) -> float:
    """The fiber direction at the lesion projected into the plane, as the layer's angle from e1 (degrees)."""
    if cfg.tissue.fibers == "radial":
        f = body_apex(surface) - rest
    else:
        a = np.deg2rad(cfg.material.fiber_angle_deg)
        f = np.array([np.cos(a), np.sin(a), 0.0])
    f2 = f @ plane.basis
    return float(np.degrees(np.arctan2(f2[1], f2[0]))) if np.linalg.norm(f2) > 1e-12 else 0.0


def section_problems(cfg: BodyConfig) -> list[Problem]:
    """With `controller.model: layer`, each target's section must make a layer; `section_fixed` needs that model."""
    if cfg.controller.model != "layer":
        if cfg.controller.section_fixed is not None:
            return [(("controller", "section_fixed"), "the held sides of the layer's section: only with "
                     "controller.model layer")]
        return []
    problems, surface = [], body_surface(cfg)
    for k, t in enumerate(cfg.targets):
        try:
            section_config(cfg, k, surface)
        except SectionError as exc:
            problems.append((("controller", "model"), f"layer: the section through {t.name!r}: {exc}"))
    return problems
