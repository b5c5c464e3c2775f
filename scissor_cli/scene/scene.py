"""The scene: what the config describes, as arrays in mm (docs/model.md §1).

A `Scene` is geometry and physics without a mesh: the layer outline, the
obstacles, the cups, the targets and the material constants. The mesher and
the mechanics read it; nothing here knows about triangles.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from scissor_cli.config import (
    CupConfig,
    MaterialConfig,
    ObstacleConfig,
    TargetConfig,
    TissueConfig,
    obstacle_outline,
    tissue_outline,
)


@dataclass(frozen=True)
class Obstacle:
    name: str
    outline: np.ndarray  # (K, 2) mm, counter-clockwise
    stiffness_factor: float


@dataclass(frozen=True)
class Cup:
    name: str
    contact: np.ndarray  # (2,) mm, on the boundary
    axis: np.ndarray  # (2,) unit direction of a positive stroke
    radius_mm: float
    stroke_min_mm: float
    stroke_max_mm: float
    speed_mm_per_s: float


@dataclass(frozen=True)
class Target:
    name: str
    rest: np.ndarray  # (2,) mm
    desired: np.ndarray | None  # (2,) mm, or None: the planner chooses


@dataclass(frozen=True)
class Material:
    model: str
    E_kPa: float
    nu: float
    eta_kPa: float
    fiber_angle_rad: float
    tension_only: bool
    density_kg_per_mm3: float


@dataclass(frozen=True)
class Scene:
    name: str
    outline: np.ndarray  # (K, 2) mm, counter-clockwise
    thickness_mm: float
    fixed_sides: tuple[str, ...]
    obstacles: tuple[Obstacle, ...]
    cups: tuple[Cup, ...]
    targets: tuple[Target, ...]
    material: Material

    @property
    def cup_names(self) -> list[str]:
        return [c.name for c in self.cups]

    def strokes_vector(self, strokes: dict[str, float]) -> np.ndarray:
        """Cup strokes (C,) in mm, in cup order; cups not named stay at 0."""
        return np.array([float(strokes.get(c.name, 0.0)) for c in self.cups])


def build_scene(name: str, tissue: TissueConfig, material: MaterialConfig, cups: Sequence[CupConfig],
                targets: Sequence[TargetConfig], obstacles: Sequence[ObstacleConfig]) -> Scene:
    """The scene of the config's scene sections, as plain arrays in mm (degrees become radians)."""
    return Scene(
        name=name,
        outline=tissue_outline(tissue, n_curve=_curve_points(tissue)),
        thickness_mm=tissue.thickness_mm,
        fixed_sides=tuple(tissue.fixed),
        obstacles=tuple(
            Obstacle(o.name, obstacle_outline(o, _obstacle_points(o, tissue)), o.stiffness_factor)
            for o in obstacles
        ),
        cups=tuple(
            Cup(
                c.name,
                np.asarray(c.contact_mm, float),
                np.asarray(c.axis, float),
                c.radius_mm,
                c.stroke_mm[0],
                c.stroke_mm[1],
                c.speed_mm_per_s,
            )
            for c in cups
        ),
        targets=tuple(
            Target(t.name, np.asarray(t.position_mm, float),
                   None if t.desired_mm is None else np.asarray(t.desired_mm, float))
            for t in targets
        ),
        material=material_of(material),
    )


def material_of(m: MaterialConfig) -> Material:
    """The `material` section as plain numbers (the fiber angle in radians; η only for the fiber model)."""
    return Material(m.model, m.E_kPa, m.nu, m.eta_kPa if m.model == "neo_hookean_fiber" else 0.0,
                    np.deg2rad(m.fiber_angle_deg), m.fiber_tension_only, m.density_kg_per_mm3)


def _curve_points(tissue: TissueConfig) -> int:
    # An ellipse is sampled finely enough that the finest edge still follows the curve.
    if tissue.shape != "ellipse":
        return 0
    w, h = tissue.size_mm
    perimeter = np.pi * (3 * (w + h) / 2 - np.sqrt((3 * w + h) * (w + 3 * h)) / 2)
    return int(np.clip(perimeter / (tissue.mesh.min_edge_mm * tissue.mesh.scale), 32, 4096))


def _obstacle_points(o: ObstacleConfig, tissue: TissueConfig) -> int:
    if o.circle is None:
        return 0
    circumference = 2 * np.pi * o.circle.radius_mm
    return int(np.clip(circumference / (tissue.mesh.min_edge_mm * tissue.mesh.scale), 12, 1024))
