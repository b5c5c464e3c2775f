"""Needle planner: a straight, obstacle-free insertion to each target (MODEL.md §7).

The paper's idea (§4.1, Fig. 11): when the straight needle path to a lesion
is blocked by vessels or nerves, a suction cup pushes or pulls the tissue
until a straight path is clear. The obstacles are tissue too, so every check
is made on the *deformed* scene: the target, the obstacle outlines and the
skin outline are all carried by barycentric coordinates on the deformed mesh.

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

The search over cup strokes solves full nonlinear equilibria (Newton,
warm-started from the nearest solved stroke), so it is exact for the model,
not a linearisation; it does not need the Jacobian of MODEL.md §5.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from scissor_cli import geometry
from scissor_cli.config import NeedleConfig
from scissor_cli.mesh.mesh import Mesh, interpolate, locate
from scissor_cli.solvers.equilibrium import solve_equilibrium
from scissor_cli.scene.scene import Scene, Target
from scissor_cli.solvers.common import SolverError
from scissor_cli.mechanics.tissue import Tissue

#: A caller-supplied check that the robot can realise an insertion:
#: (entry (2,), direction (2,), target (2,)) in the layer frame, mm →
#: (joints (5,) as (d1, d2, d3, θ4, d5) in mm/rad, ok, note).
RobotCheck = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, bool, str]]

Candidate = tuple[str, np.ndarray]  # (entry side, unit travel direction (2,))

N_JOINTS = 5


# --------------------------------------------------------------------------
# Straight-corridor geometry


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


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


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
    denom = _cross(u[:, None, :], e[None])  # (K, E)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = _cross(w[None], e[None]) / denom
        s = _cross(w[None], u[:, None, :]) / denom
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
    """Clearance (mm) of the corridor entry → target: min distance to any obstacle − radius.

    `radius` is the corridor half-width (needle radius + margin). Clear when
    > 0; +inf with no obstacles. An overlapping obstacle counts as distance 0,
    so the clearance is never below −radius.
    """
    if len(obstacle_outlines) == 0:
        return float("inf")
    d = min(geometry.segment_polygon_distance(entry, target, poly) for poly in obstacle_outlines)
    return d - radius


def corridor_clearances(entries: np.ndarray, target, obstacle_outlines: Sequence[np.ndarray], radius: float) -> np.ndarray:
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

    Ties keep the candidates' order (entry sides and tilts as configured).
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


# --------------------------------------------------------------------------
# Points carried by the deformation


@dataclass(frozen=True)
class Embedding:
    """Points embedded in the rest mesh: triangle (P,) and barycentric coordinates (P, 3).

    `splits` cuts the P points back into the outlines they came from.
    """

    triangles: np.ndarray  # (M, 3) the mesh's
    tri_idx: np.ndarray  # (P,)
    bary: np.ndarray  # (P, 3)
    splits: tuple[int, ...]  # cumulative ends of each outline in the P points


def embed_outlines(mesh: Mesh, outlines: Sequence[np.ndarray]) -> Embedding:
    """Locate outline points (K_i, 2) once, at rest, in the mesh."""
    pts = np.vstack([np.asarray(o, float).reshape(-1, 2) for o in outlines]) if outlines else np.zeros((0, 2))
    tri_idx, bary = locate(mesh, pts) if len(pts) else (np.zeros(0, np.int64), np.zeros((0, 3)))
    return Embedding(mesh.triangles, tri_idx, bary, tuple(np.cumsum([len(o) for o in outlines]).tolist()))


def deformed_outlines(embedding: Embedding, x: np.ndarray) -> list[np.ndarray]:
    """The embedded outlines carried to node positions x (N, 2): a list of (K_i, 2) mm."""
    if not embedding.splits:
        return []
    pts = interpolate(x, embedding.triangles, embedding.tri_idx, embedding.bary)
    return np.split(pts, embedding.splits[:-1])


def boundary_loop(mesh: Mesh) -> np.ndarray:
    """Node indices (B,) of the mesh's outer boundary in counter-clockwise order.

    At rest it traces the scene outline; under load, the deformed skin, which
    is where the needle actually enters.
    """
    nxt = {int(a): int(b) for a, b in mesh.boundary_edges}
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, n = [start], nxt[start]
        seen.add(start)
        while n != start and n not in seen:
            loop.append(n)
            seen.add(n)
            n = nxt[n]
        loops.append(np.array(loop))
    # Boundary edges keep the domain on their left, so the outer loop has the largest positive area.
    return max(loops, key=lambda l: geometry.signed_area(mesh.nodes[l]))


# --------------------------------------------------------------------------
# Deformed states over the cups' strokes


class StateCache:
    """Equilibria (N, 2) of a tissue for cup strokes (C,) mm, each solved once.

    A new stroke is solved by Newton warm-started from the nearest solved one
    (stroke distance), so a sweep ordered outwards from zero is a chain of
    small load steps. Zero strokes are the rest state without a solve. Share
    one cache between the targets of a scene to solve each stroke once.
    """

    def __init__(self, tissue: Tissue, tol: float = 1e-9):
        self.tissue = tissue
        self.tol = tol
        self._states: dict[tuple[float, ...], np.ndarray] = {}
        self.failures: dict[tuple[float, ...], str] = {}
        self.solves = 0
        self.solve_time_s = 0.0
        zero = (0.0,) * tissue.n_cups
        self._states[zero] = tissue.rest

    @staticmethod
    def key(strokes) -> tuple[float, ...]:
        # Round so that a grid value reached twice by float arithmetic is one state.
        return tuple(float(v) for v in np.round(np.asarray(strokes, float), 9))

    def state(self, strokes) -> Optional[np.ndarray]:
        """Node positions (N, 2) at the strokes, or None if the solve failed (see `failures`)."""
        k = self.key(strokes)
        if k in self._states:
            return self._states[k]
        if k in self.failures:
            return None
        s = np.array(k)
        known = np.array(list(self._states))
        near = known[np.argmin(np.linalg.norm(known - s, axis=1))]
        t0 = time.perf_counter()
        self.solves += 1
        try:
            x = solve_equilibrium(self.tissue, s, start=self._states[tuple(near)], start_strokes=near, tol=self.tol).x
        except SolverError as exc:
            self.failures[k] = str(exc)
            return None
        finally:
            self.solve_time_s += time.perf_counter() - t0
        self._states[k] = x
        return x


def _values_per_cup(n_cups: int, samples: int) -> int:
    # A tensor grid grows as n^C, so several cups get a coarse grid and rely on the refinement.
    return samples if n_cups == 1 else max(5, int(np.ceil(np.sqrt(samples))) + 2)


def stroke_grid(scene: Scene, samples: int) -> np.ndarray:
    """Stroke samples (S, C) mm over every cup's range, zero included, nearest zero first.

    One cup gets `samples` values; several cups a coarse tensor grid of
    max(5, ⌈√samples⌉ + 2) values each (a refinement follows the search).
    """
    n = _values_per_cup(len(scene.cups), samples)
    axes = []
    for cup in scene.cups:
        v = np.linspace(cup.stroke_min_mm, cup.stroke_max_mm, n)
        if cup.stroke_min_mm <= 0 <= cup.stroke_max_mm:
            v = np.union1d(v, [0.0])
        axes.append(v)
    grid = np.array(list(itertools.product(*axes))).reshape(-1, len(scene.cups))
    # Outwards from rest, so every solve warm-starts from a close neighbour.
    return grid[np.argsort(np.linalg.norm(grid, axis=1), kind="stable")]


def _grid_steps(scene: Scene, samples: int) -> np.ndarray:
    """Spacing (C,) mm of `stroke_grid` along each cup."""
    n = _values_per_cup(len(scene.cups), samples)
    return np.array([(c.stroke_max_mm - c.stroke_min_mm) / (n - 1) for c in scene.cups])


def _clip_strokes(scene: Scene, s: np.ndarray) -> np.ndarray:
    lo = np.array([c.stroke_min_mm for c in scene.cups])
    hi = np.array([c.stroke_max_mm for c in scene.cups])
    return np.clip(s, lo, hi)


# --------------------------------------------------------------------------
# The plan


@dataclass
class NeedlePlan:
    """The insertion planned for one target (MODEL.md §7), all in the layer frame.

    desired (2,) mm: y_d, the target position at which to insert (the
        deformed target at `strokes`, or the config's desired position).
    strokes (C,) mm: cup strokes at which the plan holds (zeros: no manipulation).
    entry (2,) mm, direction (2,) unit, depth_mm, clearance_mm (> 0 when clear), side.
    joints (5,): (d1, d2, d3, θ4, d5) in mm/rad from the robot check, NaN without one.
    desired_error_mm: distance between `desired` and the target's deformed
        position at `strokes` (0 unless the config gave the desired position).
    reason: empty when feasible, else why no plan exists (with the best found).
    """

    target: str
    feasible: bool
    reason: str
    desired: np.ndarray
    strokes: np.ndarray
    entry: np.ndarray
    direction: np.ndarray
    depth_mm: float
    clearance_mm: float
    side: str
    joints: np.ndarray = field(default_factory=lambda: np.full(N_JOINTS, np.nan))
    robot_ok: bool = False
    robot_note: str = "robot kinematics not applied"
    desired_error_mm: float = 0.0
    solves: int = 0
    time_s: float = 0.0

    @property
    def manipulated(self) -> bool:
        return bool(np.any(self.strokes != 0))


@dataclass(frozen=True)
class _Sample:
    strokes: np.ndarray  # (C,)
    target: np.ndarray  # (2,) deformed target
    insertion: Optional[Insertion]  # best at this state
    clearance: float  # -inf without an entry

    @property
    def size(self) -> float:
        return float(np.linalg.norm(self.strokes))


class _Evaluator:
    """Evaluates the target's best insertion on the deformed scene at given strokes."""

    def __init__(self, tissue: Tissue, scene: Scene, target: Target, needle_cfg: NeedleConfig, cache: StateCache):
        self.scene, self.needle_cfg, self.cache = scene, needle_cfg, cache
        mesh = tissue.mesh
        self.obstacles = embed_outlines(mesh, [o.outline for o in scene.obstacles])
        self.target = embed_outlines(mesh, [target.rest])
        self.loop = boundary_loop(mesh)
        self.candidates = candidate_directions(needle_cfg, scene)
        self.samples: dict[tuple[float, ...], _Sample] = {}

    def scene_at(self, x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
        """Deformed target (2,), obstacle outlines and skin outline at node positions x (N, 2)."""
        return deformed_outlines(self.target, x)[0][0], deformed_outlines(self.obstacles, x), x[self.loop]

    def insertions_at(self, point: np.ndarray, x: np.ndarray) -> list[Insertion]:
        _, obstacles, outline = self.scene_at(x)
        return ranked_insertions(point, obstacles, outline, self.candidates, self.needle_cfg)

    def sample(self, strokes) -> Optional[_Sample]:
        key = StateCache.key(strokes)
        if key in self.samples:
            return self.samples[key]
        x = self.cache.state(strokes)
        if x is None:
            return None
        y, obstacles, outline = self.scene_at(x)
        best = best_insertion(y, obstacles, outline, self.candidates, self.needle_cfg)
        s = _Sample(np.array(key), y, best, -np.inf if best is None else best.clearance_mm)
        self.samples[key] = s
        return s


def _choose_clearance(samples: Sequence[_Sample], tie_mm: float) -> _Sample:
    """Largest clearance; among clear samples within tie_mm of it, the smallest stroke."""
    best = max(samples, key=lambda s: (s.clearance, -s.size))
    if best.clearance > 0:
        pool = [s for s in samples if s.clearance > 0 and s.clearance >= best.clearance - tie_mm]
        return min(pool, key=lambda s: (s.size, -s.clearance))
    return best


def _refine(ev: _Evaluator, chosen: _Sample, step: np.ndarray, levels: int, choose) -> _Sample:
    """Local grids of half, quarter, ... the coarse step around the chosen sample."""
    C = len(step)
    offsets = np.array(list(itertools.product((-1.0, 0.0, 1.0), repeat=C)))
    offsets = offsets[np.any(offsets != 0, axis=1)]
    for level in range(1, levels + 1):
        h = step / 2**level
        for off in offsets:
            ev.sample(_clip_strokes(ev.scene, chosen.strokes + off * h))
        chosen = choose(list(ev.samples.values()))
    return chosen


def _fmt_strokes(scene: Scene, strokes: np.ndarray) -> str:
    if len(scene.cups) == 1:
        return f"stroke {strokes[0]:.3g} mm"
    return "strokes (" + ", ".join(f"{c.name} {v:.3g}" for c, v in zip(scene.cups, strokes)) + ") mm"


def _fmt_ranges(scene: Scene) -> str:
    if len(scene.cups) == 1:
        c = scene.cups[0]
        return f"any stroke in [{c.stroke_min_mm:g}, {c.stroke_max_mm:g}] mm"
    return "any strokes within " + ", ".join(
        f"{c.name} [{c.stroke_min_mm:g}, {c.stroke_max_mm:g}]" for c in scene.cups
    ) + " mm"


def _failures_note(cache: StateCache) -> str:
    if not cache.failures:
        return ""
    first = next(iter(cache.failures.values()))
    return f" ({len(cache.failures)} stroke sample(s) could not be solved, e.g. {first})"


def _no_entry_reason(needle_cfg: NeedleConfig) -> str:
    lo, hi = needle_cfg.direction_range_deg
    return (
        f"no allowed direction reaches the target through an entry side "
        f"(sides {list(needle_cfg.entry_sides)}, tilts [{lo:g}, {hi:g}] deg)"
    )


def _apply_robot(plan: NeedlePlan, ranked: list[Insertion], robot_check: Optional[RobotCheck]) -> NeedlePlan:
    """Fill the joints; if the robot cannot realise the best insertion, try the next clear one."""
    if robot_check is None:
        return plan
    clear = [i for i in ranked if i.clear]
    if not plan.feasible or not clear:
        plan.robot_note = "robot kinematics not checked: no clear insertion"
        return plan
    notes = []
    for ins in clear:
        joints, ok, note = robot_check(ins.entry, ins.direction, plan.desired)
        notes.append(note)
        if ok:
            _set_insertion(plan, ins)
            plan.joints, plan.robot_ok, plan.robot_note = np.asarray(joints, float), True, note
            return plan
    # The corridor is clear, so the tissue side of the plan stands (`feasible`);
    # that the puncture module as registered cannot realise it is reported
    # beside it, with the best insertion kept, rather than hiding the plan.
    plan.joints = np.asarray(robot_check(clear[0].entry, clear[0].direction, plan.desired)[0], float)
    plan.robot_ok = False
    plan.robot_note = f"the robot cannot realise any of the {len(clear)} clear insertion(s): {notes[0]}"
    return plan


def _set_insertion(plan: NeedlePlan, ins: Optional[Insertion]) -> None:
    if ins is None:
        return
    plan.entry, plan.direction = ins.entry, ins.direction
    plan.depth_mm, plan.clearance_mm, plan.side = ins.depth_mm, ins.clearance_mm, ins.side


def _plan(target: Target, feasible: bool, reason: str, desired, strokes, ins) -> NeedlePlan:
    plan = NeedlePlan(
        target=target.name, feasible=feasible, reason=reason,
        desired=np.asarray(desired, float), strokes=np.asarray(strokes, float),
        entry=np.full(2, np.nan), direction=np.full(2, np.nan),
        depth_mm=float("nan"), clearance_mm=float("nan"), side="",
    )
    _set_insertion(plan, ins)
    return plan


def plan_target(
    tissue: Tissue,
    scene: Scene,
    target: Target,
    needle_cfg: NeedleConfig,
    stroke_samples: int = 25,
    robot_check: Optional[RobotCheck] = None,
    tie_mm: float = 0.25,
    refine_levels: int = 3,
    cache: Optional[StateCache] = None,
) -> NeedlePlan:
    """Plan a straight, obstacle-free insertion to one target (MODEL.md §7).

    1. A configured `target.desired` overrides the search: the stroke that
       brings the target closest to it is found by the sweep below, and the
       best direction is chosen at the desired position against the
       obstacles deformed at that stroke.
    2. Else, if a candidate is clear at rest, insert without manipulation.
    3. Else sweep the cups' strokes (`stroke_samples` per cup for one cup, a
       coarse grid for several; then `refine_levels` halvings around the
       choice) for the deformed state whose best corridor has the largest
       clearance; among clearances within `tie_mm` of it, the smallest
       stroke (least manipulation). y_d is the deformed target there.

    Never raises for an infeasible scene: the plan says feasible=False and
    why. `robot_check` (see `RobotCheck`) gives the joints; when it rejects
    the best insertion, the next clear one at the same state is tried.
    `cache` shares solved states between the targets of a scene.
    """
    t0 = time.perf_counter()
    cache = cache or StateCache(tissue)
    solves0 = cache.solves
    ev = _Evaluator(tissue, scene, target, needle_cfg, cache)
    zero = np.zeros(len(scene.cups))
    rest = ev.sample(zero)

    def done(plan: NeedlePlan, ranked: list[Insertion]) -> NeedlePlan:
        plan = _apply_robot(plan, ranked, robot_check)
        plan.solves, plan.time_s = cache.solves - solves0, time.perf_counter() - t0
        return plan

    if not ev.candidates:
        return done(_plan(target, False, _no_entry_reason(needle_cfg), target.rest, zero, None), [])

    inside = [o.name for o in scene.obstacles if geometry.points_in_polygon(target.rest[None], o.outline)[0]]
    if inside:
        reason = f"target {target.name!r} lies inside obstacle {inside[0]!r}: no corridor can reach it without crossing it"
        return done(_plan(target, False, reason, target.rest, zero, rest.insertion), [])

    if target.desired is None and rest.clearance > 0:
        ranked = ev.insertions_at(rest.target, tissue.rest)
        return done(_plan(target, True, "", rest.target, zero, rest.insertion), ranked)

    for s in stroke_grid(scene, stroke_samples):
        ev.sample(s)
    step = _grid_steps(scene, stroke_samples)
    if target.desired is not None:
        plan, ranked = _plan_for_desired(ev, target, np.asarray(target.desired, float), step, refine_levels)
    else:
        plan, ranked = _plan_by_search(ev, target, step, refine_levels, tie_mm)
    return done(plan, ranked)


def _plan_for_desired(ev: _Evaluator, target: Target, yd: np.ndarray, step: np.ndarray, levels: int):
    """The configured y_d (2,): the stroke that brings the target closest, the best direction at y_d."""

    def closest(samples):
        return min(samples, key=lambda s: (np.linalg.norm(s.target - yd), s.size))

    chosen = _refine(ev, closest(list(ev.samples.values())), step, levels, closest)
    ranked = ev.insertions_at(yd, ev.cache.state(chosen.strokes))
    ins = ranked[0] if ranked else None
    err = float(np.linalg.norm(chosen.target - yd))
    where = (
        f"at the desired position {np.round(yd, 3).tolist()} mm "
        f"(reached within {err:.2g} mm at {_fmt_strokes(ev.scene, chosen.strokes)})"
    )
    reason = ""
    if ins is None:
        reason = f"{_no_entry_reason(ev.needle_cfg)} {where}" + _failures_note(ev.cache)
    elif not ins.clear:
        reason = (
            f"no entry side/direction clears the obstacles {where}; "
            f"best clearance {ins.clearance_mm:.2g} mm" + _failures_note(ev.cache)
        )
    plan = _plan(target, not reason, reason, yd, chosen.strokes, ins)
    plan.desired_error_mm = err
    return plan, ranked


def _plan_by_search(ev: _Evaluator, target: Target, step: np.ndarray, levels: int, tie_mm: float):
    """y_d chosen by the sweep: the deformed state with the largest clearance (least stroke among ties)."""

    def choose(samples):
        return _choose_clearance(samples, tie_mm)

    chosen = _refine(ev, choose(list(ev.samples.values())), step, levels, choose)
    ranked = ev.insertions_at(chosen.target, ev.cache.state(chosen.strokes))
    reason = ""
    if chosen.insertion is None:
        reason = f"{_no_entry_reason(ev.needle_cfg)} at {_fmt_ranges(ev.scene)}"
    elif not chosen.clearance > 0:
        reason = (
            f"no entry side/direction clears the obstacles at {_fmt_ranges(ev.scene)}; "
            f"best clearance {chosen.clearance:.2g} mm at {_fmt_strokes(ev.scene, chosen.strokes)}"
        )
    if reason:
        reason += _failures_note(ev.cache)
    return _plan(target, not reason, reason, chosen.target, chosen.strokes, chosen.insertion), ranked


def plan_targets(
    tissue: Tissue, scene: Scene, needle_cfg: NeedleConfig, robot_check: Optional[RobotCheck] = None, **kwargs
) -> list[NeedlePlan]:
    """`plan_target` for every target of the scene, sharing one `StateCache`."""
    cache = kwargs.pop("cache", None) or StateCache(tissue)
    return [plan_target(tissue, scene, t, needle_cfg, robot_check=robot_check, cache=cache, **kwargs) for t in scene.targets]
