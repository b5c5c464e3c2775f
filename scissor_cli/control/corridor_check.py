"""The planned needle corridor, checked on the true tissue after manipulation (docs/model.md §7)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.outlines import Embedding, boundary_loop, deformed_outlines, embed_outlines
from scissor_cli.planning.corridor import corridor_clearance, entry_points


@dataclass(frozen=True)
class Corridor:
    """A planned straight insertion to check after manipulation: side, unit direction (2,), half-width mm."""

    side: str
    direction: np.ndarray
    radius_mm: float

    @classmethod
    def from_plan(cls, plan, radius_mm: float) -> Optional["Corridor"]:
        """From a `NeedlePlan` (None when the plan has no direction)."""
        if plan is None or not plan.side or not np.all(np.isfinite(plan.direction)):
            return None
        return cls(plan.side, np.asarray(plan.direction, float), float(radius_mm))


def corridor_at(tissue: Tissue, x: np.ndarray, point: np.ndarray, corridor: Corridor,
                obstacles: Optional[Embedding] = None) -> tuple[np.ndarray, float]:
    """Entry (2,) mm and clearance (mm, > 0 clear) of the corridor to `point` (2,) at node positions x (N, 2).

    The skin and the obstacles are carried by x (deformed); the entry is
    where the ray from the point against the direction leaves the skin
    through the corridor's side (NaN and clearance NaN if it does not).
    """
    obstacles = obstacles or embed_outlines(tissue.mesh, [o.outline for o in tissue.scene.obstacles])
    outline = x[boundary_loop(tissue.mesh)]
    entry = entry_points(point, [(corridor.side, corridor.direction)], outline)[0]
    if not np.all(np.isfinite(entry)):
        return entry, float("nan")
    return entry, corridor_clearance(entry, point, deformed_outlines(obstacles, x), corridor.radius_mm)
