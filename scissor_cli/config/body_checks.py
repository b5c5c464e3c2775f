"""Checks of a 3-D scene that need several fields at once (docs/model.md §19; docs/contract.md, "3-D scenes").

The body's surface for the checks: the dome exactly (its half-spheroid and
its base), a surface body as its file (`surface_file.read_surface`, which
refuses a surface that is open, non-manifold, self-intersecting or
unreadable). Then: every lesion inside
the body and under the skin shell, every obstacle at least partly inside,
no obstacle over a lesion nor over another obstacle, each cup within its
radius of the skin and its patch clear of the held faces and of the other
patches, forward strokes within the cups' limits. Each problem is a
(location, message) pair, as in `checks`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scissor_cli import geometry3d as g3
from scissor_cli.config.body_imaging import body_imaging_problems
from scissor_cli.config.body_mesh_file import read_body_mesh_arrays
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.config.checks import (
    Problem,
    _forward_problems,
    _unique,
    insertion_problems,
    surrogate_samples_problems,
)
from scissor_cli.config.mesh_file import MeshFileError
from scissor_cli.config.surface_file import SurfaceFileError, read_surface

#: a face of a surface body is on a held plane when its corners are this close to it, mm (× the body's size)
PLANE_TOL = 1e-6
#: region names the mesh uses for itself: no target or obstacle may take them
RESERVED_NAMES = ("body", "skin")


@dataclass(frozen=True)
class DomeSurface:
    """The dome's surface, exactly: the half-spheroid's curved skin and its held base on z = 0."""

    radius_mm: float
    height_mm: float

    def depth(self, points: np.ndarray) -> np.ndarray:
        """Signed depth (K,) mm of points under the surface: the distance to it, negative outside."""
        p = np.atleast_2d(points)
        _, to_skin = g3.spheroid_cap_nearest(p, self.radius_mm, self.height_mm)
        inside = g3.inside_spheroid_cap(p, self.radius_mm, self.height_mm)
        return np.where(inside, np.minimum(to_skin, p[:, 2]), -to_skin)

    def nearest_skin(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nearest skin points (K, 3) to points (K, 3) and their distances (K,) mm."""
        return g3.spheroid_cap_nearest(points, self.radius_mm, self.height_mm)

    def to_held(self, points: np.ndarray) -> np.ndarray:
        """Distance (K,) mm from points on the skin to the held base."""
        return np.atleast_2d(points)[:, 2]


@dataclass(frozen=True)
class MeshSurface:
    """A surface body's triangulation (nodes (V, 3) mm, outward triangles (T, 3)) and its held faces (T,) bool."""

    nodes: np.ndarray
    triangles: np.ndarray
    held: np.ndarray

    def depth(self, points: np.ndarray) -> np.ndarray:
        _, dist, _ = g3.nearest_on_surface(points, self.nodes, self.triangles)
        return np.where(g3.inside_surface(points, self.nodes, self.triangles), dist, -dist)

    def nearest_skin(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q, dist, _ = g3.nearest_on_surface(points, self.nodes, self.triangles[~self.held])
        return q, dist

    def to_held(self, points: np.ndarray) -> np.ndarray:
        return g3.nearest_on_surface(points, self.nodes, self.triangles[self.held])[1]


def body_surface(cfg: BodyConfig) -> DomeSurface | MeshSurface:
    """The scene's body surface; SurfaceFileError (a ValueError) for an unusable surface file."""
    t = cfg.tissue
    if t.shape == "dome":
        return DomeSurface(t.radius_mm, t.height_mm)
    nodes, triangles = read_surface(t.surface_file)
    size = float(np.ptp(nodes, axis=0).max())
    held = np.zeros(len(triangles), bool)
    for f in t.fixed:
        if isinstance(f, str):
            continue
        normal, point = np.asarray(f.plane.normal), np.asarray(f.plane.point_mm)
        held |= np.all(np.abs((nodes[triangles] - point) @ normal) <= PLANE_TOL * size, axis=1)
    return MeshSurface(nodes, triangles, held)


def body_apex(surface: DomeSurface | MeshSurface) -> np.ndarray:
    """(3,) mm: the body's top (the dome's apex; a surface body's highest vertex), where radial fibers point."""
    if isinstance(surface, DomeSurface):
        return np.array([0.0, 0.0, surface.height_mm])
    return surface.nodes[int(np.argmax(surface.nodes[:, 2]))].copy()


def skin_normals(surface: DomeSurface | MeshSurface, points: np.ndarray) -> np.ndarray:
    """Outward unit normals (K, 3) of the skin at points (K, 3) on it: the spheroid's exactly; on a triangulation
    the area-weighted normal of the skin faces within 2 mm (the face holding the point when none is that near)."""
    if len(points) == 0:
        return np.zeros((0, 3))
    if isinstance(surface, DomeSurface):
        return g3.spheroid_cap_normal(points, surface.radius_mm, surface.height_mm)
    tris = surface.triangles[~surface.held]
    a, b, c = (surface.nodes[tris[:, i]] for i in range(3))
    area_normal = 0.5 * np.cross(b - a, c - a)  # (S, 3)
    q = g3.closest_on_triangles(points[:, None, :], a, b, c)  # (K, S, 3)
    near = np.linalg.norm(q - points[:, None, :], axis=-1)
    weights = np.where(near <= 2.0, 1.0, 0.0)
    weights[np.arange(len(points)), np.argmin(near, axis=1)] = 1.0
    n = weights @ area_normal
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def body_box(surface) -> tuple[np.ndarray, np.ndarray]:
    """The body's bounding box: lo (3,), hi (3,) mm."""
    if isinstance(surface, DomeSurface):
        r = surface.radius_mm
        return np.array([-r, -r, 0.0]), np.array([r, r, surface.height_mm])
    return surface.nodes.min(axis=0), surface.nodes.max(axis=0)


def body_problems(cfg: BodyConfig) -> list[Problem]:
    """Cross-field checks of a 3-D scene: [(location, message)]."""
    problems = _shape_problems(cfg)
    if problems:
        return problems
    try:
        surface = body_surface(cfg)
    except SurfaceFileError as exc:
        return [(("tissue", "surface_file"), f"{cfg.tissue.surface_file}: {exc}")]
    problems += _held_problems(cfg, surface)
    problems += _unique(cfg.cups, "cups") + _unique(cfg.targets, "targets") + _unique(cfg.obstacles, "obstacles")
    problems += _unique(cfg.forward, "forward") + _reserved_names(cfg)
    problems += _lesion_problems(cfg, surface) + _obstacle_problems(cfg, surface)
    problems += _cup_problems(cfg, surface) + _forward_problems(cfg) + _grip_problems(cfg, surface)
    lo, hi = body_box(surface)
    problems += insertion_problems(cfg.insertion, float(np.max(hi - lo)))
    problems += body_imaging_problems(cfg, surface, skin_normals)
    problems += surrogate_samples_problems(cfg.controller, len(cfg.cups))
    if cfg.solver.kind != "newton":
        problems.append((("solver", "kind"), f"{cfg.solver.kind!r}: a 3-D body is solved by Newton with its kept "
                         "factor (docs/model.md §19); ADMM is a layer's solver: leave solver.kind newton"))
    if cfg.trials.truth != "layer":
        problems.append((("trials", "truth"), "a 3-D scene's trials run against the body itself: leave trials.truth "
                         "out (the slab is the 2-D layer's 3-D check)"))
    if cfg.trials.budget and cfg.trials.count == 0:
        problems.append((("trials", "budget"), "the error budget reruns the trials: it needs trials.count >= 1"))
    if cfg.tissue.mesh.element == "auto" and cfg.tissue.accuracy_mm is None:
        problems.append((("tissue", "mesh", "element"), "auto picks the element by the accuracy asked for: give "
                         "tissue.accuracy_mm, or name the element (p1 or nodal)"))
    if cfg.tissue.accuracy_mm is not None and not (cfg.forward and cfg.targets):
        problems.append((("tissue", "accuracy_mm"), "the mesh is picked by the lesions' positions under the forward "
                         "cases: the scene needs at least one target and one forward case"))
    if not problems:  # reading a mesh file is worth it only for an otherwise sound scene
        problems += _mesh_file_problems(cfg)
    return problems


def region_names(cfg: BodyConfig) -> tuple[str, ...]:
    """The regions a mesh of this scene has, in order: body, skin (with a shell), the targets, the obstacles."""
    return (("body",) + (("skin",) if cfg.tissue.skin is not None else ()) + tuple(t.name for t in cfg.targets)
            + tuple(o.name for o in cfg.obstacles))


def _mesh_file_problems(cfg: BodyConfig) -> list[Problem]:
    m = cfg.tissue.mesh
    if m.file is None:
        return []
    where = ("tissue", "mesh", "file")
    if cfg.tissue.accuracy_mm is not None:
        return [(where, "a mesh file pins the mesh, tissue.accuracy_mm chooses one: give one of the two")]
    if m.scale != 1.0:
        return [(where, f"a mesh file is used as it is: tissue.mesh.scale must be 1 with it; got {m.scale:g}")]
    if cfg.controller.mesh_scale != 1.0:
        return [(("controller", "mesh_scale"), f"a mesh file pins the body: the model's body cannot be meshed "
                 f"coarser; leave controller.mesh_scale 1 (got {cfg.controller.mesh_scale:g})")]
    try:
        _, _, _, names = read_body_mesh_arrays(m.file)
    except MeshFileError as exc:
        return [(where, f"{m.file}: {exc}")]
    if names != region_names(cfg):
        return [(where, f"{m.file}: its regions {list(names)} are not this scene's {list(region_names(cfg))}")]
    return []


def _shape_problems(cfg: BodyConfig) -> list[Problem]:
    t = cfg.tissue
    out: list[Problem] = []
    if t.shape == "dome":
        for field in ("radius_mm", "height_mm"):
            if getattr(t, field) is None:
                out.append((("tissue", field), "a dome needs radius_mm (its base on the platform) and height_mm"))
        if t.surface_file is not None:
            out.append((("tissue", "surface_file"), "a dome is made from radius_mm and height_mm; surface_file is "
                        "for tissue.shape: surface"))
        if t.fixed != ["base"]:
            out.append((("tissue", "fixed"), "a dome is held at its base on the platform: fixed: [base]"))
        if not out and t.skin is not None and t.skin.thickness_mm >= 0.5 * min(t.radius_mm, t.height_mm):
            out.append((("tissue", "skin", "thickness_mm"), (
                f"must be below half the dome's smaller dimension ({0.5 * min(t.radius_mm, t.height_mm):g} mm); "
                f"got {t.skin.thickness_mm:g}")))
    else:
        if t.surface_file is None:
            out.append((("tissue", "surface_file"), "a surface body needs surface_file: a closed triangulated "
                        "surface in mm (STL, OBJ, PLY, VTK)"))
        for field in ("radius_mm", "height_mm"):
            if getattr(t, field) is not None:
                out.append((("tissue", field), f"{field} describes a dome; a surface body is its surface_file"))
        if any(isinstance(f, str) for f in t.fixed):
            out.append((("tissue", "fixed"), "a surface body is held on planes: fixed: [{plane: {point_mm: [x, y, "
                        "z], normal: [x, y, z]}}] (base is the dome's)"))
    return out


def _held_problems(cfg: BodyConfig, surface) -> list[Problem]:
    if isinstance(surface, MeshSurface) and not surface.held.any():
        return [(("tissue", "fixed"), "no face of the surface lies on the held plane(s): the body would float; "
                 "give a plane through a flat face of the surface (e.g. the chest wall)")]
    return []


def _reserved_names(cfg: BodyConfig) -> list[Problem]:
    out: list[Problem] = []
    for section in ("targets", "obstacles"):
        for i, item in enumerate(getattr(cfg, section)):
            if item.name in RESERVED_NAMES:
                out.append(((section, i, "name"), f"{item.name!r} names a region of every body mesh; choose another"))
    targets = {t.name for t in cfg.targets}
    for i, o in enumerate(cfg.obstacles):
        if o.name in targets:
            out.append((("obstacles", i, "name"), f"{o.name!r} is also a target's name: each region has its own"))
    return out


def _lesion_problems(cfg: BodyConfig, surface) -> list[Problem]:
    out: list[Problem] = []
    if not cfg.targets:
        return out
    skin = cfg.tissue.skin.thickness_mm if cfg.tissue.skin is not None else 0.0
    centres = np.array([t.position_mm for t in cfg.targets], float)
    depth = surface.depth(centres)
    for i, (t, d) in enumerate(zip(cfg.targets, depth)):
        if d < 0:
            out.append((("targets", i, "position_mm"), f"lesion {t.name!r} lies outside the body ({-d:.3g} mm out)"))
        elif d < t.radius_mm + skin:
            out.append((("targets", i, "radius_mm"), (
                f"lesion {t.name!r} reaches {'into the skin shell or ' if skin else ''}out of the body: its centre is "
                f"{d:.3g} mm deep, its radius {t.radius_mm:g} mm{f' and the skin {skin:g} mm' if skin else ''}")))
    desired = [(i, t) for i, t in enumerate(cfg.targets) if t.desired_mm is not None]
    if desired:
        d = surface.depth(np.array([t.desired_mm for _, t in desired], float))
        out += [(("targets", i, "desired_mm"), f"lesion {t.name!r}'s desired position lies outside the body")
                for (i, t), di in zip(desired, d) if di < 0]
    for j in range(len(cfg.targets)):
        for i in range(j):
            gap = np.linalg.norm(centres[i] - centres[j]) - cfg.targets[i].radius_mm - cfg.targets[j].radius_mm
            if gap < 0:
                out.append((("targets", j, "position_mm"),
                            f"lesions {cfg.targets[i].name!r} and {cfg.targets[j].name!r} overlap"))
    return out


def _segments(o) -> tuple[np.ndarray, np.ndarray]:
    """An obstacle as segments (S, 3) → (S, 3): a sphere is one of length 0."""
    if o.sphere is not None:
        c = np.array([o.sphere.center_mm], float)
        return c, c
    p = np.array(o.tube.points_mm, float)
    return p[:-1], p[1:]


def _radius(o) -> float:
    return o.sphere.radius_mm if o.sphere is not None else o.tube.radius_mm


def _obstacle_problems(cfg: BodyConfig, surface) -> list[Problem]:
    out: list[Problem] = []
    for i, o in enumerate(cfg.obstacles):
        a, b = _segments(o)
        field = ("obstacles", i, "sphere" if o.sphere is not None else "tube")
        if o.tube is not None and np.any(np.linalg.norm(b - a, axis=1) < 1e-6):
            out.append((field + ("points_mm",), "consecutive points must differ (a segment of length 0)"))
            continue
        samples = np.concatenate([a + s * (b - a) for s in np.linspace(0.0, 1.0, 9)])
        if not np.any(surface.depth(samples) > 0):
            out.append((field, f"obstacle {o.name!r} lies outside the body"))
        for k, t in enumerate(cfg.targets):
            gap = g3.point_segment_distance(np.array([t.position_mm], float), a, b).min() - _radius(o) - t.radius_mm
            if gap < 0:
                out.append((field, f"obstacle {o.name!r} overlaps lesion {t.name!r} (targets[{k}]): a vessel or cyst "
                            f"beside a lesion must leave it room"))
        for k in range(i):
            p, q = cfg.obstacles[k], o
            pa, pb = _segments(p)
            gap = g3.segment_segment_distance(pa, pb, a, b).min() - _radius(p) - _radius(q)
            if gap < 0:
                out.append((field, f"obstacles {p.name!r} and {q.name!r} overlap"))
    return out


def _grip_problems(cfg: BodyConfig, surface) -> list[Problem]:
    """manipulation_points on a body: cups to place ≤ the cups given; a skin region that reaches the skin."""
    mp = cfg.manipulation_points
    if mp is None:
        return []
    out: list[Problem] = []
    if mp.cups > len(cfg.cups):
        out.append((("manipulation_points", "cups"), (
            f"{mp.cups} cups to place but {len(cfg.cups)} given: the grips replace the first `cups` entries of "
            f"`cups` (their contact_mm and axis); give at least {mp.cups} cups or place fewer")))
    _, dist = surface.nearest_skin(np.asarray([mp.skin.center_mm], float))
    if dist[0] > mp.skin.radius_mm:
        out.append((("manipulation_points", "skin"), (
            f"the ball of radius {mp.skin.radius_mm:g} mm about {mp.skin.center_mm} holds no skin (the skin is "
            f"{dist[0]:.3g} mm from its centre): centre it on the skin or widen radius_mm")))
    return out


def _cup_problems(cfg: BodyConfig, surface) -> list[Problem]:
    out: list[Problem] = []
    if not cfg.cups:
        return out
    contacts = np.array([c.contact_mm for c in cfg.cups], float)
    on_skin, dist = surface.nearest_skin(contacts)
    to_held = surface.to_held(on_skin)
    for i, (c, d) in enumerate(zip(cfg.cups, dist)):
        if d > c.radius_mm:
            out.append((("cups", i, "contact_mm"), (
                f"cup {c.name!r} is {d:.3g} mm from the skin, beyond its radius {c.radius_mm:g} mm: the contact must "
                f"lie on the skin (it is moved to the nearest skin point)")))
        elif to_held[i] < c.radius_mm:
            out.append((("cups", i, "contact_mm"), (
                f"cup {c.name!r}'s patch (radius {c.radius_mm:g} mm) reaches the held "
                f"{'base' if cfg.tissue.shape == 'dome' else 'face'} ({to_held[i]:.3g} mm away): move it up the "
                f"skin or shrink radius_mm")))
    for j in range(len(cfg.cups)):
        for i in range(j):
            if np.linalg.norm(on_skin[i] - on_skin[j]) < cfg.cups[i].radius_mm + cfg.cups[j].radius_mm:
                out.append((("cups", j, "contact_mm"),
                            f"the patches of cups {cfg.cups[i].name!r} and {cfg.cups[j].name!r} overlap"))
    return out
