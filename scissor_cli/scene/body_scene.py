"""A 3-D scene as plain data: the breast body, its lesions, vessels and cups on its skin (docs/model.md §19).

What a `BodyConfig` describes, in mm, without a mesh. The body is a dome
(a half-spheroid standing on the platform z = 0, held at its base) or a
closed surface read from a file (held on planes). Cups are given where
the user put them and carried to the nearest skin point here, so the
mesher can refine their patches and the mechanics grip them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scissor_cli.config.body_checks import DomeSurface, MeshSurface, body_apex, body_surface, skin_normals
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.scene.scene import Material, material_of


@dataclass(frozen=True)
class Lesion:
    """A target: a sphere about `rest` (3,) mm, `desired` (3,) mm or None (the planner chooses)."""

    name: str
    rest: np.ndarray
    desired: np.ndarray | None
    radius_mm: float
    stiffness_factor: float


@dataclass(frozen=True)
class Inclusion:
    """An obstacle: a sphere (one point) or a vessel (a polyline) of `points` (P, 3) mm and a radius."""

    name: str
    kind: str  # "sphere" | "tube"
    points: np.ndarray
    radius_mm: float
    stiffness_factor: float


@dataclass(frozen=True)
class SkinCup:
    """A suction cup: its patch is the skin of area π radius_mm² around `contact` (3,) mm, the nearest skin point
    to where it was given (`mechanics.body_tissue.cup_patch`); a stroke moves the patch along `axis` (3,), the
    inward normal there unless given."""

    name: str
    contact: np.ndarray
    axis: np.ndarray
    radius_mm: float
    stroke_min_mm: float
    stroke_max_mm: float
    speed_mm_per_s: float


@dataclass(frozen=True)
class BodyScene:
    name: str
    shape: str  # "dome" | "surface"
    surface: DomeSurface | MeshSurface  # the body's exact surface (the dome's) or its triangulation
    held_planes: tuple  # ((point (3,), unit normal (3,)), ...): a surface body's held faces; () for the dome
    skin_thickness_mm: float | None
    skin_E_kPa: float | None
    fibers: str  # "uniform" | "radial"
    targets: tuple[Lesion, ...]
    obstacles: tuple[Inclusion, ...]
    cups: tuple[SkinCup, ...]
    material: Material

    dim = 3

    @property
    def cup_names(self) -> list[str]:
        return [c.name for c in self.cups]

    def strokes_vector(self, strokes: dict[str, float]) -> np.ndarray:
        """Cup strokes (C,) in mm, in cup order; cups not named stay at 0."""
        return np.array([float(strokes.get(c.name, 0.0)) for c in self.cups])

    @property
    def apex(self) -> np.ndarray:
        """(3,) mm: the body's top (`body_checks.body_apex`), where radial fibers point."""
        return body_apex(self.surface)


def build_body_scene(cfg: BodyConfig) -> BodyScene:
    """The scene of a validated 3-D config (degrees become radians; cups moved onto the skin)."""
    t = cfg.tissue
    surface = body_surface(cfg)
    contacts = np.array([c.contact_mm for c in cfg.cups], float).reshape(-1, 3)
    on_skin, _ = surface.nearest_skin(contacts) if len(contacts) else (np.zeros((0, 3)), None)
    normals = skin_normals(surface, on_skin)
    cups = tuple(
        SkinCup(c.name, on_skin[i], -normals[i] if c.axis is None else np.asarray(c.axis, float), c.radius_mm,
                c.stroke_mm[0], c.stroke_mm[1], c.speed_mm_per_s)
        for i, c in enumerate(cfg.cups))
    planes = tuple((np.asarray(f.plane.point_mm, float), np.asarray(f.plane.normal, float))
                   for f in t.fixed if not isinstance(f, str))
    return BodyScene(
        name=cfg.name, shape=t.shape, surface=surface, held_planes=planes,
        skin_thickness_mm=None if t.skin is None else t.skin.thickness_mm,
        skin_E_kPa=None if t.skin is None else t.skin.E_kPa, fibers=t.fibers,
        targets=tuple(Lesion(x.name, np.asarray(x.position_mm, float),
                             None if x.desired_mm is None else np.asarray(x.desired_mm, float), x.radius_mm,
                             x.stiffness_factor) for x in cfg.targets),
        obstacles=tuple(Inclusion(o.name, "sphere", np.array([o.sphere.center_mm], float), o.sphere.radius_mm,
                                  o.stiffness_factor) if o.sphere is not None else
                        Inclusion(o.name, "tube", np.array(o.tube.points_mm, float), o.tube.radius_mm,
                                  o.stiffness_factor) for o in cfg.obstacles),
        cups=cups, material=material_of(cfg.material))
