"""Needle plan: a straight, obstacle-free insertion to each target (docs/model.md §7).

The paper's idea (§4.1, Fig. 11): when the straight needle path to a lesion
is blocked by vessels or nerves, a suction cup pushes or pulls the tissue
until a straight path is clear. The obstacles are tissue too, so every check
is made on the *deformed* scene: the target, the obstacle outlines and the
skin outline are all carried by the deformed mesh (`mesh.outlines`), and the
corridors are judged by `planning.corridor`.

The search over cup strokes solves full nonlinear equilibria
(`planning.states.StateCache`: Newton, warm-started from the nearest solved
stroke), so it is exact for the model, not a linearisation; it does not need
the Jacobian of docs/model.md §5.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from scissor_cli import geometry
from scissor_cli.config import NeedleConfig
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.outlines import boundary_loop, deformed_outlines, embed_outlines
from scissor_cli.planning.corridor import Insertion, best_insertion, candidate_directions, ranked_insertions
from scissor_cli.planning.states import StateCache, clip_strokes, grid_steps, stroke_grid
from scissor_cli.scene.scene import Scene, Target

#: A caller-supplied check that the robot can realise an insertion:
#: (entry (2,), direction (2,), target (2,)) in the layer frame, mm →
#: (joints (5,) as (d1, d2, d3, θ4, d5) in mm/rad, ok, note).
RobotCheck = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, bool, str]]

#: The target's position (2,) mm at cup strokes (C,) mm by another model than the planner's tissue
#: (a 3-D-aware controller model, docs/model.md §15); the obstacles and the skin come with `LayerAt`.
TargetAt = Callable[[np.ndarray], np.ndarray]
#: strokes (C,) mm → the layer's node positions (N, 2) mm as a controller model predicts them (docs/model.md §15)
LayerAt = Callable[[np.ndarray], np.ndarray]

N_JOINTS = 5


@dataclass
class NeedlePlan:
    """The insertion planned for one target (docs/model.md §7), all in the layer frame.

    desired (2,) mm: y_d, the target position at which to insert (the
        deformed target at `strokes`, or the config's desired position).
    strokes (C,) mm: cup strokes at which the plan holds (zeros: no manipulation).
    entry (2,) mm, direction (2,) unit, depth_mm, clearance_mm (> 0 when clear), side.
    joints (5,): (d1, d2, d3, θ4, d5) in mm/rad from the robot check, NaN without one.
    desired_error_mm: distance between `desired` and the target's deformed
        position at `strokes` (0 unless the config gave the desired position).
    reason: empty when feasible, else why no plan exists (with the best found).
    model_strokes, slab_strokes (C,) mm, model_error_mm: see the fields (docs/model.md §15).
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
    #: with a 3-D-aware controller model or slab truth (docs/model.md §15): the strokes (C,) mm the controller's
    #: model needs for `desired` (then also `strokes`), and those the nominal slab needs; None when not asked
    model_strokes: Optional[np.ndarray] = None
    slab_strokes: Optional[np.ndarray] = None
    #: with a slab at hand: the distance (mm) between the target where the controller's model puts it at
    #: `model_strokes` and where the nominal slab does at the same strokes (0 for the slab model itself)
    model_error_mm: Optional[float] = None
    #: the model whose target positions chose `desired` and `strokes`: "layer" (the planner's tissue), or the
    #: controller model's kind when the plan was made again with it (`target_at`, docs/model.md §15)
    planned_with: str = "layer"

    @property
    def manipulated(self) -> bool:
        return bool(np.any(self.strokes != 0))


@dataclass(frozen=True)
class _Sample:
    strokes: np.ndarray  # (C,)
    target: np.ndarray  # (2,) deformed target
    insertion: Optional[Insertion]  # best the robot accepts at this state (best of all without a robot check)
    clearance: float  # of that insertion; -inf without one
    any_insertion: Optional[Insertion] = None  # best at this state, robot or not
    any_clearance: float = -np.inf

    @property
    def size(self) -> float:
        return float(np.linalg.norm(self.strokes))


class _Evaluator:
    """Evaluates the target's best insertion on the deformed scene at given strokes."""

    def __init__(self, tissue: Tissue, scene: Scene, target: Target, needle_cfg: NeedleConfig, cache: StateCache,
                 robot_check: Optional[RobotCheck] = None, target_at: Optional[TargetAt] = None,
                 layer_at: Optional[LayerAt] = None):
        self.scene, self.needle_cfg, self.cache, self.robot_check = scene, needle_cfg, cache, robot_check
        self.target_at, self.layer_at = target_at, layer_at
        mesh = tissue.mesh
        self.obstacles = embed_outlines(mesh, [o.outline for o in scene.obstacles])
        self.target = embed_outlines(mesh, [target.rest])
        self.loop = boundary_loop(mesh)
        self.candidates = candidate_directions(needle_cfg, scene)
        self.samples: dict[tuple[float, ...], _Sample] = {}

    def scene_at(self, x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
        """Deformed target (2,), obstacle outlines and skin outline at node positions x (N, 2)."""
        return deformed_outlines(self.target, x)[0][0], deformed_outlines(self.obstacles, x), x[self.loop]

    def state(self, strokes) -> Optional[np.ndarray]:
        """The layer's node positions (N, 2) at the strokes: `layer_at`'s when given, else the tissue's solve
        (None if it failed)."""
        if self.layer_at is not None:
            return np.asarray(self.layer_at(np.array(StateCache.key(strokes))), float)
        return self.cache.state(strokes)

    def insertions_at(self, point: np.ndarray, x: np.ndarray) -> list[Insertion]:
        _, obstacles, outline = self.scene_at(x)
        return ranked_insertions(point, obstacles, outline, self.candidates, self.needle_cfg)

    def sample(self, strokes) -> Optional[_Sample]:
        key = StateCache.key(strokes)
        if key in self.samples:
            return self.samples[key]
        x = self.state(strokes)
        if x is None:
            return None
        y, obstacles, outline = self.scene_at(x)
        if self.target_at is not None:
            y = np.asarray(self.target_at(np.array(key)), float)
        if self.robot_check is None:
            best = best_insertion(y, obstacles, outline, self.candidates, self.needle_cfg)
            c = -np.inf if best is None else best.clearance_mm
            s = _Sample(np.array(key), y, best, c, best, c)
        else:
            ranked = ranked_insertions(y, obstacles, outline, self.candidates, self.needle_cfg)
            # Ranked by clearance among the insertions the inverse kinematics accepts (docs/model.md §7).
            ok = next((i for i in ranked if self.robot_check(i.entry, i.direction, y)[1]), None)
            top = ranked[0] if ranked else None
            s = _Sample(np.array(key), y, ok, -np.inf if ok is None else ok.clearance_mm,
                        top, -np.inf if top is None else top.clearance_mm)
        self.samples[key] = s
        return s

    def robot_pool(self, samples: Sequence[_Sample]) -> Sequence[_Sample]:
        """The samples as the choice sees them: by robot-accepted clearance when some state has a clear,
        realisable insertion; else by any insertion (the plan then reports that the robot cannot realise it)."""
        if any(s.clearance > 0 for s in samples):
            return samples
        return [_Sample(s.strokes, s.target, s.any_insertion, s.any_clearance, s.any_insertion, s.any_clearance)
                for s in samples]


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
            ev.sample(clip_strokes(ev.scene, chosen.strokes + off * h))
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
    target_at: Optional[TargetAt] = None,
    layer_at: Optional[LayerAt] = None,
) -> NeedlePlan:
    """Plan a straight, obstacle-free insertion to one target (docs/model.md §7).

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
    `target_at` (see `TargetAt`) gives the target's position at the strokes
    in place of the tissue's, and `layer_at` (see `LayerAt`) the layer's
    nodes, which carry the obstacles and the skin (without it they stay
    the tissue's): the plan of a 3-D-aware controller model (docs/model.md §15).
    """
    t0 = time.perf_counter()
    cache = cache or StateCache(tissue)
    solves0 = cache.solves
    ev = _Evaluator(tissue, scene, target, needle_cfg, cache, robot_check, target_at, layer_at)
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
        reason = (f"target {target.name!r} lies inside obstacle {inside[0]!r}: "
                  "no corridor can reach it without crossing it")
        return done(_plan(target, False, reason, target.rest, zero, rest.any_insertion), [])

    if target.desired is None and rest.clearance > 0:
        ranked = ev.insertions_at(rest.target, tissue.rest)
        return done(_plan(target, True, "", rest.target, zero, rest.insertion), ranked)

    for s in stroke_grid(scene, stroke_samples):
        ev.sample(s)
    step = grid_steps(scene, stroke_samples)
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
    ranked = ev.insertions_at(yd, ev.state(chosen.strokes))
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
        return _choose_clearance(ev.robot_pool(samples), tie_mm)

    chosen = _refine(ev, choose(list(ev.samples.values())), step, levels, choose)
    ranked = ev.insertions_at(chosen.target, ev.state(chosen.strokes))
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
    return [plan_target(tissue, scene, t, needle_cfg, robot_check=robot_check, cache=cache, **kwargs)
            for t in scene.targets]


def stored_plan(name: str, a: dict, has_obstacles: bool) -> NeedlePlan:
    """A plan from its stored /plan/<target> attributes (docs/contract.md), as the planner gave it.

    Values the file holds as fills are restored: no geometry without a plan,
    no joints the robot cannot reach, an infinite clearance without obstacles.
    """
    feasible, reachable = bool(a["feasible"]), bool(a["robot_reachable"])
    geometry = (lambda v: np.asarray(v, float)) if str(a["side"]) else (lambda v: np.full(np.shape(v), np.nan))
    joints = np.asarray(a["joints"], float)
    optional = {k: np.asarray(a[k], float) for k in ("model_strokes", "slab_strokes") if k in a}
    return NeedlePlan(
        name, feasible, str(a["reason"]), np.asarray(a["desired"], float), np.asarray(a["strokes"], float),
        geometry(a["entry"]), geometry(a["direction"]), float(geometry(a["depth_mm"])),
        float(a["clearance_mm"]) if has_obstacles else float("inf"), str(a["side"]),
        joints if reachable else np.full(joints.shape, np.nan), reachable, str(a["joints_note"]),
        float(a["desired_error_mm"]), **optional,
        model_error_mm=float(a["model_error_mm"]) if "model_error_mm" in a else None)
