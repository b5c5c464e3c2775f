"""Straight needle corridors: candidate directions, entry points, clearance (docs/model.md §7).

Geometry of one insertion, all in the layer frame, mm:

* an entry side s (left/right/top/bottom, `geometry.SIDE_NORMALS`) and a tilt
  φ give the travel direction d = Rot(φ)·(−n_s): φ = 0 is the side's inward
  normal, φ > 0 turns d counter-clockwise;
* the entry point is where the ray from the target along −d leaves the
  tissue outline; it must leave through an edge of side s (the accessible
  skin), else the candidate has no entry;
* the corridor is the segment entry → target dilated by the needle radius
  plus the safety margin; its clearance is the distance from the segment to
  the nearest obstacle minus that radius, and the insertion is clear when
  the clearance is > 0.

Everything here is pure geometry on given outlines; the planner passes the
deformed ones (`mesh.outlines`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from scissor_cli import geometry
from scissor_cli.config import NeedleConfig
from scissor_cli.scene.scene import Scene

Candidate = tuple[str, np.ndarray]  # (entry side, unit travel direction (2,))


@dataclass(frozen=True)
class Insertion:
    """One straight insertion: entry (2,) mm, unit direction (2,), depth and clearance in mm."""

    entry: np.ndarray
    direction: np.ndarray
    depth_mm: float
    clearance_mm: float
    side: str

    @property
    def clear(self) -> bool:
        return self.clearance_mm > 0


def corridor_radius(needle_cfg: NeedleConfig) -> float:
    """Half-width (mm) of the corridor that must miss every obstacle: needle radius + margin."""
    return needle_cfg.diameter_mm / 2 + needle_cfg.margin_mm


def _tilts_rad(needle_cfg: NeedleConfig) -> np.ndarray:
    lo, hi = needle_cfg.direction_range_deg
    step = needle_cfg.direction_step_deg
    tilts = np.arange(lo, hi + 1e-9, step)
    if hi - tilts[-1] > 1e-9:  # a range that is not a whole number of steps keeps its end
        tilts = np.append(tilts, hi)
    return np.deg2rad(tilts)


def candidate_directions(needle_cfg: NeedleConfig, scene: Scene) -> list[Candidate]:
    """Every allowed (side, unit travel direction (2,)) over entry sides × tilts.

    Sides the outline has no edge for (e.g. 'top' of a triangle) are skipped.
    """
    out: list[Candidate] = []
    tilts = _tilts_rad(needle_cfg)
    for side in needle_cfg.entry_sides:
        if not geometry.side_edge_mask(scene.outline, side).any():
            continue
        inward = -geometry.SIDE_NORMALS[side]
        for phi in tilts:
            c, s = np.cos(phi), np.sin(phi)
            d = np.array([c * inward[0] - s * inward[1], s * inward[0] + c * inward[1]]) + 0.0  # no -0.0
            out.append((side, d))
    return out


def entry_points(target: np.ndarray, candidates: Sequence[Candidate], outline: np.ndarray) -> np.ndarray:
    """Entry points (K, 2) mm of the candidates for a target (2,), NaN where there is none.

    The entry is the first crossing of the ray target − t·d (t > 0) with the
    outline (K_o, 2, CCW). A candidate has no entry when that crossing is not
    on an edge of its side (the needle would come through inaccessible skin).
    """
    target = np.asarray(target, float)
    K = len(candidates)
    out = np.full((K, 2), np.nan)
    if K == 0:
        return out
    a, b = geometry.edges(np.asarray(outline, float))
    e = b - a  # (E, 2)
    u = -np.array([d for _, d in candidates])  # (K, 2): from the target back to the skin
    w = a - target  # (E, 2)
    denom = geometry.cross2(u[:, None, :], e[None])  # (K, E)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = geometry.cross2(w[None], e[None]) / denom
        s = geometry.cross2(w[None], u[:, None, :]) / denom
    tol = 1e-9
    hit = (np.abs(denom) > 1e-12) & (t > tol) & (s >= -tol) & (s <= 1 + tol)
    t = np.where(hit, t, np.inf)
    t_min = t.min(axis=1)
    # A ray through a corner hits two edges at once; either may carry the side.
    first = t <= t_min[:, None] + tol * (1 + t_min[:, None])
    masks = {side: geometry.side_edge_mask(outline, side) for side in {c[0] for c in candidates}}
    for k, (side, _) in enumerate(candidates):
        if np.isfinite(t_min[k]) and np.any(first[k] & masks[side]):
            out[k] = target + t_min[k] * u[k]
    return out


def corridor_clearance(entry, target, obstacle_outlines: Sequence[np.ndarray], radius: float) -> float:
    """Clearance (mm) of the corridor entry (2,) mm → target (2,) mm: min distance to any obstacle − radius.

    obstacle_outlines: polygons (K_i, 2) mm; `radius` (mm) is the corridor
    half-width (needle radius + margin, `corridor_radius`). Clear when
    > 0; +inf with no obstacles. An overlapping obstacle counts as distance 0,
    so the clearance is never below −radius.
    """
    if len(obstacle_outlines) == 0:
        return float("inf")
    d = min(geometry.segment_polygon_distance(entry, target, poly) for poly in obstacle_outlines)
    return d - radius


def corridor_clearances(entries: np.ndarray, target, obstacle_outlines: Sequence[np.ndarray],
                        radius: float) -> np.ndarray:
    """`corridor_clearance` for many entries (K, 2) to one target (2,): (K,) mm, NaN for NaN entries.

    Same definition as the scalar version, vectorised over the candidates
    (one small loop over obstacles).
    """
    entries = np.atleast_2d(np.asarray(entries, float))
    target = np.asarray(target, float)
    out = np.full(len(entries), np.nan)
    ok = np.all(np.isfinite(entries), axis=1)
    if not ok.any():
        return out
    p = entries[ok]
    q = np.broadcast_to(target, p.shape)
    dist = np.full(len(p), np.inf)
    for poly in obstacle_outlines:
        poly = np.asarray(poly, float)
        pa, pb = geometry.edges(poly)
        touch = geometry.segments_intersect(p, q, pa, pb).any(axis=1)
        touch |= geometry.points_in_polygon(p, poly) | geometry.points_in_polygon(target[None], poly)[0]
        d = np.minimum(
            geometry.point_segment_distance(pa, p, q).min(axis=0),  # polygon vertices to the segments
            geometry.point_segment_distance(p, pa, pb).min(axis=1),  # entries to the polygon edges
        )
        d = np.minimum(d, geometry.point_segment_distance(target[None], pa, pb).min())
        dist = np.minimum(dist, np.where(touch, 0.0, d))
    out[ok] = dist - radius
    return out


def ranked_insertions(
    target_position, obstacle_outlines: Sequence[np.ndarray], outline: np.ndarray,
    candidates: Sequence[Candidate], needle_cfg: NeedleConfig,
) -> list[Insertion]:
    """Every candidate that has an entry, as an `Insertion`, largest clearance first.

    Arguments as for `best_insertion`. Ties keep the candidates' order
    (entry sides and tilts as configured).
    """
    target = np.asarray(target_position, float)
    entries = entry_points(target, candidates, outline)
    clearance = corridor_clearances(entries, target, obstacle_outlines, corridor_radius(needle_cfg))
    valid = np.flatnonzero(np.isfinite(entries[:, 0]))
    order = valid[np.argsort(-clearance[valid], kind="stable")]
    return [
        Insertion(
            entry=entries[k],
            direction=candidates[k][1].copy(),
            depth_mm=float(np.linalg.norm(target - entries[k])),
            clearance_mm=float(clearance[k]),
            side=candidates[k][0],
        )
        for k in order
    ]


def best_insertion(
    target_position, obstacle_outlines: Sequence[np.ndarray], outline: np.ndarray,
    candidates: Sequence[Candidate], needle_cfg: NeedleConfig,
) -> Optional[Insertion]:
    """The candidate with the largest clearance, or None if no candidate has an entry.

    target_position (2,) mm; obstacle_outlines: deformed outlines (K_i, 2);
    outline: the (deformed) tissue outline (K, 2), counter-clockwise.
    """
    ranked = ranked_insertions(target_position, obstacle_outlines, outline, candidates, needle_cfg)
    return ranked[0] if ranked else None
