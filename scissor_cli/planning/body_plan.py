"""The needle planned in 3-D: a straight line to each lesion of a body, clear of its vessels and cysts
(docs/model.md §19, "Plan"; the 2-D layer's planner is `planning.needle_plan`, §7).

For one lesion:

1. The allowed directions: the configured axis and, with `needle.cone_deg`,
   rings within that half-angle (`planning.body_lines.cone_directions`).
2. At rest, the line along each direction through the lesion's centre, its
   entry on the skin and its clearance (`planning.body_lines`). The lines
   are ranked by clearance (largest first, ties closest to the axis); the
   first that is clear (clearance ≥ 0) and that the robot accepts is the
   plan, without moving the tissue.
3. Otherwise, with cups and a `solve`, the cups' strokes are searched for
   the least move that clears a line: the stroke grid (`stroke_grid`) in
   order of ‖s‖, each sample a full equilibrium at which the lesion, the
   skin and the obstacles are carried and every line judged again. The
   first ‖s‖ at which a line the robot accepts clears by CLEAR_RESERVE_MM
   is kept (the best clearance among samples of that norm), then bisected
   BISECT_STEPS times along s between the last blocked sample on that ray
   (rest when none) and it, so the move is near the least that clears by
   the reserve. At most MAX_SOLVES solves per lesion. A sample whose solve
   fails is passed over (and named in a failed plan's reason). When no
   sample clears by the reserve, the smallest clear one (≥ 0) is the plan.
4. A configured `desired_mm`: the line is planned through it at rest,
   judged against the rest obstacles; moving the lesion there is the
   caller's (the plan's strokes are zeros).

A plan the robot cannot realise is no plan (`feasible` false, the robot's
note in the reason). The robot check is the caller's (`body_robot_check`
makes the one of a `RobotModel` registered at the body's frame).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from scissor_cli.config.body_sections import BodyNeedleConfig
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import target_positions
from scissor_cli.planning import body_lines as bl
from scissor_cli.robot.chain import RobotModel
from scissor_cli.robot.registration import body_plan_to_joints
from scissor_cli.scene.body_scene import BodyScene
from scissor_cli.solvers.common import SolverError

#: (entry (3,) mm, direction (3,) unit, depth_mm) in the body's frame → (ok, joints (5,) or None, note)
BodyRobotCheck = Callable[[np.ndarray, np.ndarray, float], tuple[bool, Optional[np.ndarray], str]]
#: cup strokes (C,) mm → the body's node positions (N, 3) mm at equilibrium (None or SolverError: not solved)
BodySolve = Callable[[np.ndarray], Optional[np.ndarray]]

#: solves one lesion's stroke search may make
MAX_SOLVES = 60
#: the clearance (mm) a moved plan keeps above 0, so the least move is not one that only grazes clear
CLEAR_RESERVE_MM = 0.1
#: halvings along the chosen stroke ray: the move is within 1/16 of a grid step of the least that clears
BISECT_STEPS = 4
#: grid values on each side of 0 of each cup's stroke range: one cup, two (a tensor grid), more (one at a time)
SIDE_VALUES = {1: 5, 2: 3}
#: clear lines per state offered to the robot check, in rank order
MAX_CANDIDATES = 64


@dataclass(frozen=True)
class BodyNeedlePlan:
    """The straight insertion planned for one lesion (docs/model.md §19, "Plan"), in the body's frame.

    desired (3,) mm: where the lesion's centre must be (its rest position when no move is needed); strokes (C,) mm
    the cups' strokes that put it there. entry (3,) mm on the deformed skin, direction (3,) unit (entry → lesion),
    depth_mm, clearance_mm (≥ 0 when clear, +inf without obstacles): the plan's line, or for an infeasible plan
    the best line found (NaN when none enters through the skin). joints (5,) (d1, d2, d3 mm, θ4 rad, d5 mm) from
    the robot check or None. solves: equilibria the search solved for this lesion.
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
    joints: Optional[np.ndarray]
    robot_ok: bool
    robot_note: str
    solves: int = 0
    time_s: float = 0.0

    @property
    def manipulated(self) -> bool:
        return bool(np.any(self.strokes != 0))


@dataclass(frozen=True)
class _State:
    strokes: np.ndarray  # (C,)
    lines: bl.Lines
    chosen: int  # the best clear line the robot accepts, −1 none
    joints: Optional[np.ndarray]
    note: str  # the robot's note on the chosen line, else on the first clear line it refused
    refused: int  # clear lines the robot refused

    @property
    def clearance(self) -> float:
        return float(self.lines.clearance[self.chosen]) if self.chosen >= 0 else -np.inf

    @property
    def best(self) -> int:
        ranked = self.lines.ranked()
        return int(ranked[0]) if len(ranked) else -1


class _Planner:
    """One lesion's lines judged at states of the body."""

    def __init__(self, tissue: Tissue, scene: BodyScene, index: int, needle: BodyNeedleConfig,
                 robot_check: Optional[BodyRobotCheck], solve: Optional[BodySolve], memo: dict,
                 obstacles, max_candidates: int):
        self.tissue, self.scene, self.needle, self.lesion = tissue, scene, needle, scene.targets[index]
        self.robot_check, self.solve_fn, self.memo, self.max_candidates = robot_check, solve, memo, max_candidates
        self.directions, self.angle = bl.cone_directions(needle.direction, needle.cone_deg)
        self.obstacles = obstacles
        self.lesion_probe = tissue.probe(self.lesion.rest[None])
        self.allowance = 0.5 * needle.diameter_mm + needle.margin_mm
        self.solves, self.capped, self.failures = 0, False, {}

    def at(self, strokes: np.ndarray, x: np.ndarray, centre: Optional[np.ndarray] = None) -> _State:
        """Every line at node positions x (the lesion carried there unless `centre` is given)."""
        if centre is None:
            centre = target_positions(self.lesion_probe, x)[0]
        lines = bl.needle_lines(x, self.tissue.mesh, centre, self.directions, self.angle, self.obstacles,
                                self.allowance)
        ranked = lines.ranked()
        clear = ranked[lines.clearance[ranked] >= 0]
        if self.robot_check is None:
            chosen = int(clear[0]) if len(clear) else -1
            return _State(strokes, lines, chosen, None, "robot kinematics not checked", 0)
        first_note = ""
        for k, i in enumerate(clear[:self.max_candidates]):
            ok, joints, note = self.robot_check(lines.entry[i], lines.directions[i], float(lines.depth[i]))
            if ok:
                return _State(strokes, lines, int(i), None if joints is None else np.asarray(joints, float),
                              note, k)
            first_note = first_note or note
        return _State(strokes, lines, -1, None, first_note, min(len(clear), self.max_candidates))

    def state(self, strokes: np.ndarray) -> Optional[_State]:
        """The state at the strokes: solved (shared memo), None when the solve failed or the cap is reached."""
        key = tuple(np.round(strokes, 9))
        if key not in self.memo:
            if self.solves >= MAX_SOLVES:
                self.capped = True
                return None
            self.solves += 1
            try:
                x = self.solve_fn(np.array(key))
            except SolverError as exc:
                x = str(exc)
            self.memo[key] = "the solve returned nothing" if x is None else x
        x = self.memo[key]
        if isinstance(x, str):
            self.failures[key] = x
            return None
        return self.at(np.array(key), np.asarray(x, float))


def stroke_grid(scene: BodyScene) -> np.ndarray:
    """Stroke samples (S, C) mm of the search, rest excluded, in order of ‖s‖ (ties in grid order): each cup's
    range split into SIDE_VALUES equal steps on either side of 0; one cup alone, two cups a tensor grid, more
    cups one at a time (the others at 0)."""
    c = len(scene.cups)
    if c == 0:
        return np.zeros((0, 0))
    n = SIDE_VALUES.get(c, SIDE_VALUES[2])
    per_cup = [np.unique(np.concatenate([cup.stroke_min_mm * np.arange(n, 0, -1) / n, [0.0],
                                         cup.stroke_max_mm * np.arange(1, n + 1) / n])) for cup in scene.cups]
    if c <= 2:
        grid = np.stack(np.meshgrid(*per_cup, indexing="ij"), axis=-1).reshape(-1, c)
    else:
        grid = np.concatenate([np.eye(c)[k] * v[:, None] for k, v in enumerate(per_cup)])
    norm = np.linalg.norm(grid, axis=1)
    grid, norm = grid[norm > 0], norm[norm > 0]
    return grid[np.argsort(norm, kind="stable")]


def _search(p: _Planner, rest: _State) -> tuple[Optional[_State], list[_State], int]:
    """The least-‖s‖ state with a clear line the robot accepts (see the module's step 3); every state sampled."""
    grid = stroke_grid(p.scene)
    norm = np.linalg.norm(grid, axis=1)
    samples, chosen, i = [rest], None, 0
    while i < len(grid) and chosen is None and not p.capped:
        group = np.flatnonzero(np.isclose(norm, norm[i], rtol=1e-9, atol=0.0))
        states = [s for s in (p.state(grid[j]) for j in group) if s is not None]
        samples += states
        good = [s for s in states if s.clearance >= CLEAR_RESERVE_MM]
        chosen = max(good, key=lambda s: s.clearance) if good else None
        i = group[-1] + 1
    sampled = len(samples) - 1
    if chosen is None:
        clear = [s for s in samples if s.clearance >= 0]
        return (min(clear, key=lambda s: np.linalg.norm(s.strokes)) if clear else None), samples, sampled
    top = chosen.strokes
    lam = np.array([s.strokes @ top / (top @ top) for s in samples])
    on_ray = [lam[k] for k, s in enumerate(samples) if 0 <= lam[k] < 1 and s.clearance < CLEAR_RESERVE_MM
              and np.linalg.norm(s.strokes - lam[k] * top) <= 1e-9 * np.linalg.norm(top)]
    lo, hi = max(on_ray, default=0.0), 1.0
    for _ in range(BISECT_STEPS):
        mid = 0.5 * (lo + hi)
        s = p.state(mid * top)
        if s is None:
            break
        samples.append(s)
        if s.clearance >= CLEAR_RESERVE_MM:
            hi, chosen = mid, s
        else:
            lo = mid
    return chosen, samples, sampled


def _fmt(v) -> str:
    return "[" + ", ".join(f"{float(c):.3g}" for c in np.atleast_1d(v)) + "]"


def _lines_reason(p: _Planner, st: _State, where: str) -> str:
    """Why no line at the state is the plan: none enters through the skin, none is clear, or the robot."""
    lines, name = st.lines, p.lesion.name
    cone = (f"direction {_fmt(p.needle.direction)}" if p.needle.cone_deg == 0 else
            f"the {len(lines.code)} directions within {p.needle.cone_deg:g}° of {_fmt(p.needle.direction)}")
    best = st.best
    if best < 0:
        counts = [(int(np.sum(lines.code == c)), what) for c, what in (
            (bl.THROUGH_BASE, "enter through the held base"),
            (bl.RECROSSES, "cross the body again outside their entry"), (bl.NO_EXIT, "leave the body nowhere"))]
        parts = ", ".join(f"{n} {what}" for n, what in counts if n)
        return (f"no line of {cone} reaches lesion {name!r} through the skin {where} ({parts}): allow other "
                f"directions (needle.direction, needle.cone_deg)")
    if not lines.clearance[best] >= 0:
        blocker = p.scene.obstacles[int(lines.nearest[best])].name
        return (f"no line of {cone} to lesion {name!r} clears the obstacles {where}: the best clearance is "
                f"{lines.clearance[best]:.2f} mm, blocked by {blocker!r}")
    n_clear = int(np.sum(lines.clearance[lines.ranked()] >= 0))
    return (f"the robot cannot realise any of the {n_clear} clear line(s) to lesion {name!r} {where}"
            f"{'' if st.refused == n_clear else f' ({st.refused} tried)'}: {st.note}")


def _plan(p: _Planner, st: _State, feasible: bool, reason: str, desired, strokes, t0: float) -> BodyNeedlePlan:
    lines = st.lines
    i = st.chosen if feasible else st.best
    have = i >= 0
    return BodyNeedlePlan(
        target=p.lesion.name, feasible=feasible, reason=reason, desired=np.asarray(desired, float).copy(),
        strokes=np.asarray(strokes, float).copy(), entry=lines.entry[i].copy() if have else np.full(3, np.nan),
        direction=lines.directions[i].copy() if have else np.full(3, np.nan),
        depth_mm=float(lines.depth[i]) if have else float("nan"),
        clearance_mm=float(lines.clearance[i]) if have else float("nan"),
        joints=st.joints if feasible else None, robot_ok=feasible and p.robot_check is not None,
        robot_note=st.note if p.robot_check is not None else "robot kinematics not checked",
        solves=p.solves, time_s=time.perf_counter() - t0)


def _carried(tissue: Tissue, scene: BodyScene):
    mesh = tissue.mesh
    return bl.carry_obstacles(scene.obstacles, mesh.nodes, mesh.tetrahedra, mesh.boundary_triangles)


def plan_body_target(tissue: Tissue, scene: BodyScene, index: int, needle: BodyNeedleConfig,
                     robot_check: Optional[BodyRobotCheck] = None, solve: Optional[BodySolve] = None,
                     max_candidates: int = MAX_CANDIDATES) -> BodyNeedlePlan:
    """The needle plan of lesion `index` of the scene on the body `tissue` (see the module's steps).

    robot_check (`BodyRobotCheck`): whether the robot realises a line, with its joints; None: not checked.
    solve (`BodySolve`): the body's equilibrium at cup strokes (the caller's warm-started Newton); None: no
    stroke search. max_candidates: clear lines per state offered to the robot check. Never raises for a scene
    without a plan: the plan says feasible=False and why, in words a user acts on.
    """
    return _plan_lesion(_Planner(tissue, scene, index, needle, robot_check, solve, {}, _carried(tissue, scene),
                                 max_candidates))


def _plan_lesion(p: _Planner) -> BodyNeedlePlan:
    t0 = time.perf_counter()
    tissue, scene, solve = p.tissue, p.scene, p.solve_fn
    zero = np.zeros(len(scene.cups))
    if p.lesion.desired is not None:
        st = p.at(zero, tissue.rest, centre=p.lesion.desired)
        ok = st.chosen >= 0
        where = f"at its desired position {_fmt(p.lesion.desired)} mm (judged at rest)"
        return _plan(p, st, ok, "" if ok else _lines_reason(p, st, where), p.lesion.desired, zero, t0)
    rest = p.at(zero, tissue.rest)
    if rest.chosen >= 0:
        return _plan(p, rest, True, "", rest.lines.centre, zero, t0)
    why = _lines_reason(p, rest, "at rest")
    if rest.best < 0:  # no line enters through the skin: a move does not make one (see docs/model.md §19)
        return _plan(p, rest, False, why, rest.lines.centre, zero, t0)
    if not scene.cups:
        return _plan(p, rest, False, why + "; the scene has no cups to move the lesion", rest.lines.centre, zero, t0)
    if solve is None:
        return _plan(p, rest, False, why + "; no solver was given to search the cups' strokes", rest.lines.centre,
                     zero, t0)
    chosen, samples, sampled = _search(p, rest)
    if chosen is not None:
        return _plan(p, chosen, True, "", chosen.lines.centre, chosen.strokes, t0)
    best = max(samples, key=lambda s: (s.lines.clearance[s.best] if s.best >= 0 else -np.inf))
    limits = ", ".join(f"{c.name} [{c.stroke_min_mm:g}, {c.stroke_max_mm:g}]" for c in scene.cups)
    reason = (f"{why}; and none does at the {sampled} stroke sample(s) searched within the cups' limits ({limits} "
              f"mm): {_lines_reason(p, best, f'at strokes {_fmt(best.strokes)} mm')}")
    if p.capped:
        reason += f" (the search stopped at its cap of {MAX_SOLVES} solves)"
    if p.failures:
        reason += f" ({len(p.failures)} stroke sample(s) could not be solved, e.g. {next(iter(p.failures.values()))})"
    return _plan(p, best, False, reason, best.lines.centre, best.strokes, t0)


def plan_body_targets(tissue: Tissue, scene: BodyScene, needle: BodyNeedleConfig,
                      robot_check: Optional[BodyRobotCheck] = None, solve: Optional[BodySolve] = None,
                      max_candidates: int = MAX_CANDIDATES) -> list[BodyNeedlePlan]:
    """`plan_body_target` for every lesion, the solved states shared (each stroke solved once for all)."""
    memo: dict = {}
    obstacles = _carried(tissue, scene)
    return [_plan_lesion(_Planner(tissue, scene, k, needle, robot_check, solve, memo, obstacles, max_candidates))
            for k in range(len(scene.targets))]


def body_robot_check(robot: RobotModel, origin, yaw_rad: float) -> BodyRobotCheck:
    """The robot check of a puncture module whose base frame holds the body's frame at `origin` (3,) mm turned
    by yaw_rad about z (the robot config's layer_origin_mm, layer_yaw_deg): inverse kinematics to the line's tip
    (`robot.registration.body_plan_to_joints`)."""

    def check(entry: np.ndarray, direction: np.ndarray, depth_mm: float):
        r = body_plan_to_joints(robot, np.asarray(entry) + depth_mm * np.asarray(direction), direction, origin,
                                yaw_rad)
        return r.reachable, (r.q if np.all(np.isfinite(r.q)) else None), r.reason

    return check


__all__ = ["BISECT_STEPS", "CLEAR_RESERVE_MM", "MAX_SOLVES", "BodyNeedlePlan", "BodyRobotCheck", "BodySolve",
           "body_robot_check", "plan_body_target", "plan_body_targets", "stroke_grid"]


def stored_body_plan(name: str, a: dict, has_obstacles: bool) -> BodyNeedlePlan:
    """A lesion's plan from its stored /plan/<target> attributes (`output.body.results.write_body_plan`), as the
    planner gave it: no joints where the robot cannot reach, an infinite clearance without obstacles."""
    reachable = bool(a["robot_reachable"])
    return BodyNeedlePlan(
        name, bool(a["feasible"]), str(a["reason"]), np.asarray(a["desired"], float),
        np.asarray(a["strokes"], float), np.asarray(a["entry"], float), np.asarray(a["direction"], float),
        float(a["depth_mm"]), float(a["clearance_mm"]) if has_obstacles else float("inf"),
        np.asarray(a["joints"], float) if reachable else None, reachable, str(a["joints_note"]))
