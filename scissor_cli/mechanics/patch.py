"""A cup's patch: the surface nodes it grips, whose shares of the surface add up to the cup's area (docs/model.md §21).

Gripping every node within the cup's radius makes the gripped area follow
the mesh: a node's share of the surface reaches about half an edge beyond
it, so the held area swings by the width of the last ring of nodes with
where that ring happens to fall. Taking the nodes nearest the contact
until their shares add up closest to the cup's area keeps the area the
cup's, within one node's share, on any mesh. The body (`body_tissue`) and
the slab (`layer3d.slab`) grip this way, each with its own surface's shares.
"""

from __future__ import annotations

import math

import numpy as np

#: a cup whose nearest surface node alone stands for more than this many times its area is refused: the mesh
#: is too coarse there to grip it (`nearest_patch`)
PATCH_AREA_LIMIT = 2.0


def nearest_patch(nodes: np.ndarray, points: np.ndarray, shares: np.ndarray, contact: np.ndarray,
                  area_mm2: float) -> np.ndarray:
    """The nodes (P,) sorted, of the candidates `nodes` (S,) at `points` (S, 3) mm with surface shares `shares`
    (S,) mm², nearest the contact (3,) mm whose shares add up closest to area_mm2, the nearest one at least.
    Empty when even the nearest node's share exceeds PATCH_AREA_LIMIT × area_mm2 (or there is no candidate)."""
    nodes = np.asarray(nodes, np.int64)
    distance = np.linalg.norm(np.asarray(points, float) - np.asarray(contact, float), axis=1)
    order = np.lexsort((nodes, distance))  # nearest first; ties by node number (deterministic)
    covered = np.cumsum(np.asarray(shares, float)[order])
    if covered.size == 0 or covered[0] > PATCH_AREA_LIMIT * area_mm2:
        return np.zeros(0, np.int64)
    count = int(np.argmin(np.abs(covered - area_mm2))) + 1
    return np.sort(nodes[order[:count]])


def disc_area_in_strip(radius_mm: float, below_mm: float, above_mm: float) -> float:
    """The area (mm²) of a disc of radius_mm between the lines below_mm under and above_mm over its centre
    (both ≥ 0; inf: no line): a cup on a face that ends within its radius grips only the face."""

    def cap(distance: float) -> float:  # the circular segment beyond a line `distance` from the centre
        if distance >= radius_mm:
            return 0.0
        return radius_mm**2 * math.acos(distance / radius_mm) - distance * math.sqrt(radius_mm**2 - distance**2)

    return math.pi * radius_mm**2 - cap(below_mm) - cap(above_mm)
