"""The needle planned in 3-D (docs/model.md §19, "Plan"): lines to a lesion of a dome, clear of its obstacles.

Two coarse domes (radius 40, height 25 mm; each meshed in about 2 s):

* CYST: a lesion with a cyst on the needle's axis (−x travel, entry on the
  +x side) and a vessel beside it; no cups. The planner's lines are checked
  against a brute-force line search on the exact spheroid (entries by
  bisection of the inside test along the ray, clearances from dense points
  along the shaft).
* VESSEL: a lesion whose horizontal line runs through a vessel at rest,
  one cup on top; pushing moves the lesion down more than the vessel, so a
  move clears the line. The move is checked with independent solves.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml
from scenes.body_surfaces import box

from scissor_cli import geometry3d as g3
from scissor_cli.config import parse_config
from scissor_cli.experiments.build import body_model
from scissor_cli.mesh.probe import probe_points, target_positions
from scissor_cli.planning import body_lines
from scissor_cli.planning import body_plan as bp
from scissor_cli.planning.states import StateCache
from scissor_cli.robot.chain import RobotModel
from scissor_cli.robot.registration import body_plan_to_joints
from scissor_cli.scene.body_scene import Inclusion
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.equilibrium import solve_equilibrium

R, H = 40.0, 25.0
NEEDLE = {"diameter_mm": 1.2, "margin_mm": 1.0, "direction": [-1.0, 0.0, 0.0]}
ALLOWANCE = 0.6 + 1.0
BASE = {"tissue": {"shape": "dome", "radius_mm": R, "height_mm": H,
                   "mesh": {"max_edge_mm": 10.0, "min_edge_mm": 4.0, "grading": 1.0}},
        "material": {"model": "neo_hookean", "E_kPa": 10.0, "nu": 0.45}, "trials": {"count": 0}}
CYST = {**BASE, "name": "cyst",
        "targets": [{"name": "T", "position_mm": [-5.0, 0.0, 10.0], "radius_mm": 3.0}],
        "obstacles": [{"name": "cyst", "sphere": {"center_mm": [12.0, 0.5, 10.5], "radius_mm": 3.0}},
                      {"name": "vessel", "tube": {"points_mm": [[5.0, -12.0, 16.0], [8.0, 12.0, 14.0]],
                                                  "radius_mm": 1.5}}],
        "needle": {**NEEDLE, "cone_deg": 25.0}}
VESSEL = {**BASE, "name": "vessel",
          "cups": [{"name": "top", "contact_mm": [-5.0, 0.0, 25.0], "radius_mm": 8.0, "stroke_mm": [-10.0, 10.0]}],
          "targets": [{"name": "T", "position_mm": [-5.0, 0.0, 12.0], "radius_mm": 3.0}],
          "obstacles": [{"name": "vessel", "tube": {"points_mm": [[15.0, -15.0, 12.0], [15.0, 15.0, 12.0]],
                                                    "radius_mm": 1.5}}],
          "needle": {**NEEDLE, "cone_deg": 0.0}}


def _build(data: dict):
    cfg = parse_config(yaml.safe_dump(data, sort_keys=False), "scene.yaml")
    scene, mesh, tissue = body_model(cfg)
    return cfg, scene, mesh, tissue


@pytest.fixture(scope="module")
def cyst():
    return _build(CYST)


@pytest.fixture(scope="module")
def vessel():
    return _build(VESSEL)


def _needle(cfg, **changes):
    return cfg.needle.model_copy(update=changes)


# --- an independent line search on the exact dome ------------------------------------------------------------------

def _brute_exit(c: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where rays c − t n (t > 0) leave the exact dome, for directions n (D, 3): t (D,) by marching 0.25 mm then
    60 bisections of the inside test, and whether they leave through the base (z ≈ 0)."""
    t_grid = np.arange(0.0, 2 * R + H, 0.25)
    pts = c - t_grid[None, :, None] * n[:, None, :]
    inside = g3.inside_spheroid_cap(pts.reshape(-1, 3), R, H).reshape(pts.shape[:2])
    k = np.argmin(inside, axis=1)  # the first sample outside (the dome is convex)
    lo, hi = t_grid[k - 1], t_grid[k]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        ins = g3.inside_spheroid_cap(c - mid[:, None] * n, R, H)
        lo, hi = np.where(ins, mid, lo), np.where(ins, hi, mid)
    exit_ = c - lo[:, None] * n
    return lo, np.abs(exit_[:, 2]) < 1e-6


def _brute_clearance(entry: np.ndarray, tip: np.ndarray, spheres, tubes, step: float = 0.02) -> np.ndarray:
    """min over dense points along each shaft entry (D, 3) → tip (3,) of the distance to the obstacles' surfaces,
    less the allowance: spheres [(centre (3,), r)], tubes [(points (P, 3), r)] (each segment's distance written
    out here: the foot of the perpendicular, clamped)."""
    if len(entry) > 100:
        return np.concatenate([_brute_clearance(entry[i:i + 100], tip, spheres, tubes, step)
                               for i in range(0, len(entry), 100)])
    length = np.linalg.norm(tip - entry, axis=1).max()
    s = np.linspace(0.0, 1.0, int(np.ceil(length / step)) + 1)
    pts = entry[:, None, :] + s[None, :, None] * (tip - entry)[:, None, :]  # (D, K, 3)
    best = np.full(len(entry), np.inf)
    for centre, r in spheres:
        best = np.minimum(best, np.linalg.norm(pts - centre, axis=-1).min(axis=1) - r)
    for points, r in tubes:
        for a, b in zip(points[:-1], points[1:]):
            u = np.clip(np.einsum("dkj,j->dk", pts - a, b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
            foot = a + u[..., None] * (b - a)
            best = np.minimum(best, np.linalg.norm(pts - foot, axis=-1).min(axis=1) - r)
    return best - ALLOWANCE


def _obstacles_at_rest(scene):
    spheres = [(o.points[0], o.radius_mm) for o in scene.obstacles if o.kind == "sphere"]
    tubes = [(o.points, o.radius_mm) for o in scene.obstacles if o.kind == "tube"]
    return spheres, tubes


def _dense_cone(axis: np.ndarray, cone_deg: float, step_deg: float = 1.0) -> np.ndarray:
    e1 = np.array([0.0, 1.0, 0.0])
    e2 = np.cross(axis, e1)
    dirs = []
    for tilt in np.deg2rad(np.arange(0.0, cone_deg + 1e-9, step_deg)):
        m = max(1, int(np.ceil(2 * np.pi * np.sin(tilt) / np.deg2rad(step_deg))))
        phi = 2 * np.pi * np.arange(m) / m
        dirs.append(np.cos(tilt) * axis + np.sin(tilt) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2))
    return np.concatenate([np.atleast_2d(d) for d in dirs])


def _chord_error(mesh) -> float:
    """How far the mesh's skin lies inside the exact spheroid: the largest distance of a skin face's centroid."""
    skin = mesh.boundary_triangles[~mesh.boundary_base]
    return float(g3.spheroid_cap_nearest(mesh.nodes[skin].mean(axis=1), R, H)[1].max())


def test_the_planners_lines_and_choice_match_a_brute_force_line_search(cyst):
    cfg, scene, mesh, tissue = cyst
    plan = bp.plan_body_target(tissue, scene, 0, cfg.needle)
    c = scene.targets[0].rest
    axis = np.asarray(cfg.needle.direction)
    spheres, tubes = _obstacles_at_rest(scene)
    chord = _chord_error(mesh)
    assert 0.05 < chord < 1.5

    # the planner's own lines, each against the brute force along the same direction
    dirs, angle = body_lines.cone_directions(axis, cfg.needle.cone_deg)
    obstacles = body_lines.carry_obstacles(scene.obstacles, mesh.nodes, mesh.tetrahedra, mesh.boundary_triangles)
    lines = body_lines.needle_lines(mesh.nodes, mesh, c, dirs, angle, obstacles, ALLOWANCE)
    t, base = _brute_exit(c, dirs)
    np.testing.assert_array_equal(lines.code == body_lines.THROUGH_BASE, base)
    ok = lines.code == body_lines.LINE_OK
    assert ok.sum() == len(dirs) - base.sum() and ok.sum() >= 25
    assert np.all(np.abs(lines.depth[ok] - t[ok]) <= 3 * chord)  # the mesh's skin lies inside the spheroid
    brute = _brute_clearance(c - t[:, None] * dirs, c, spheres, tubes)
    np.testing.assert_allclose(lines.clearance[ok], brute[ok], atol=0.02)
    assert np.ptp(brute[ok]) > 3.0  # the directions differ: the choice matters

    # the plan is the best of them, and as good as the best of a dense sample of the cone up to its spacing
    assert plan.feasible and not plan.manipulated and plan.reason == ""
    assert plan.clearance_mm == pytest.approx(np.max(brute[ok]), abs=0.02)
    dense = np.concatenate([_dense_cone(axis, cfg.needle.cone_deg), dirs])  # a superset of the planner's
    td, based = _brute_exit(c, dense)
    best_dense = np.max(_brute_clearance(c - td[~based, None] * dense[~based], c, spheres, tubes))
    spacing = np.deg2rad(cfg.needle.cone_deg / 3)  # the planner's rings: no direction farther from one of them
    assert best_dense - plan.depth_mm * spacing <= plan.clearance_mm <= best_dense + 0.02
    # its line: from the entry on the skin through the lesion's centre, within the cone
    assert g3.spheroid_cap_nearest(plan.entry, R, H)[1][0] <= chord + 1e-9
    np.testing.assert_allclose(plan.entry + plan.depth_mm * plan.direction, c, atol=1e-9)
    assert np.degrees(np.arccos(plan.direction @ axis)) <= cfg.needle.cone_deg + 1e-9


def test_an_obstacle_on_the_axis_tilts_the_needle_within_the_cone(cyst):
    cfg, scene, mesh, tissue = cyst
    axis = np.asarray(cfg.needle.direction)
    straight = bp.plan_body_target(tissue, scene, 0, _needle(cfg, cone_deg=0.0))
    assert not straight.feasible and straight.clearance_mm < 0
    assert "'cyst'" in straight.reason and "no cups" in straight.reason
    np.testing.assert_allclose(straight.direction, axis)  # the best line found is reported
    tilted = bp.plan_body_target(tissue, scene, 0, cfg.needle)
    tilt = np.degrees(np.arccos(np.clip(tilted.direction @ axis, -1, 1)))
    assert tilted.feasible and tilted.clearance_mm >= 0
    assert 1.0 < tilt <= cfg.needle.cone_deg + 1e-9


def test_a_robot_that_keeps_the_needle_horizontal_gets_the_best_horizontal_line(cyst):
    cfg, scene, mesh, tissue = cyst
    asked = []

    def horizontal(entry, direction, depth):
        asked.append(direction)
        ok = abs(direction[2]) <= 1e-9
        return ok, (np.arange(5.0) if ok else None), "ok" if ok else "not horizontal"

    free = bp.plan_body_target(tissue, scene, 0, cfg.needle)
    level = bp.plan_body_target(tissue, scene, 0, cfg.needle, robot_check=horizontal)
    assert abs(free.direction[2]) > 1e-3  # the best line overall tilts up or down …
    assert level.feasible and level.robot_ok and abs(level.direction[2]) <= 1e-9  # … the robot's does not
    assert level.clearance_mm < free.clearance_mm and level.robot_note == "ok"
    np.testing.assert_array_equal(level.joints, np.arange(5.0))
    # it is the best horizontal one: every clear line ranked above it was offered to the robot and refused
    dirs, angle = body_lines.cone_directions(cfg.needle.direction, cfg.needle.cone_deg)
    horiz = np.abs(dirs[:, 2]) <= 1e-9
    spheres, tubes = _obstacles_at_rest(scene)
    t, base = _brute_exit(scene.targets[0].rest, dirs)
    brute = _brute_clearance(scene.targets[0].rest - t[:, None] * dirs, scene.targets[0].rest, spheres, tubes)
    assert level.clearance_mm == pytest.approx(brute[horiz & ~base].max(), abs=0.02)
    assert all(abs(d[2]) > 1e-9 for d in asked[:-1]) and len(asked) > 1

    never = bp.plan_body_target(tissue, scene, 0, cfg.needle, robot_check=lambda e, d, t: (False, None, "d2 too far"))
    assert not never.feasible and not never.robot_ok and never.joints is None
    assert "robot cannot realise" in never.reason and "d2 too far" in never.reason


def test_a_line_through_the_base_is_refused(cyst):
    cfg, scene, mesh, tissue = cyst
    up = bp.plan_body_target(tissue, scene, 0, _needle(cfg, direction=[0.0, 0.0, 1.0], cone_deg=0.0))
    assert not up.feasible and "held base" in up.reason and np.isnan(up.entry).all()
    # the same direction travelling down enters through the skin on top
    down = bp.plan_body_target(tissue, scene, 0, _needle(cfg, direction=[0.0, 0.0, -1.0], cone_deg=0.0))
    assert down.feasible and down.entry[2] > 0.8 * H


def test_a_desired_position_is_planned_at_rest(cyst):
    cfg, scene, mesh, tissue = cyst
    yd = np.array([-5.0, 4.0, 12.0])
    moved = dataclasses.replace(scene, targets=(dataclasses.replace(scene.targets[0], desired=yd),))
    plan = bp.plan_body_target(tissue, moved, 0, cfg.needle)
    assert plan.feasible and not plan.manipulated and plan.solves == 0
    np.testing.assert_array_equal(plan.desired, yd)
    np.testing.assert_allclose(plan.entry + plan.depth_mm * plan.direction, yd, atol=1e-9)
    spheres, tubes = _obstacles_at_rest(scene)
    assert _brute_clearance(plan.entry[None], yd, spheres, tubes)[0] == pytest.approx(plan.clearance_mm, abs=0.02)


def test_without_obstacles_the_axis_is_the_plan_with_infinite_clearance(cyst):
    cfg, scene, mesh, tissue = cyst
    plan = bp.plan_body_target(tissue, dataclasses.replace(scene, obstacles=()), 0, cfg.needle)
    assert plan.feasible and plan.clearance_mm == np.inf
    np.testing.assert_allclose(plan.direction, cfg.needle.direction)


def test_a_vessel_that_leaves_the_body_is_judged_only_inside_it(cyst):
    _, _, mesh, _ = cyst
    tube = Inclusion("v", "tube", np.array([[0.0, 0.0, 10.0], [60.0, 0.0, 10.0], [60.0, 0.0, 30.0]]), 1.0, 1.0)
    carried = body_lines.carry_obstacles((tube,), mesh.nodes, mesh.tetrahedra, mesh.boundary_triangles)
    q0, q1 = carried.segments(mesh.nodes)
    assert len(q0) == 1  # the second segment lies outside; the first is cut at the skin
    np.testing.assert_allclose(q0[0], [0.0, 0.0, 10.0], atol=1e-9)
    assert g3.spheroid_cap_nearest(q1, R, H)[1][0] <= _chord_error(mesh)
    assert 0.9 * R * np.sqrt(1 - (10 / H) ** 2) < q1[0, 0] <= R * np.sqrt(1 - (10 / H) ** 2) + 1e-9


def test_a_line_that_would_pierce_a_fold_of_the_body_before_its_entry_is_refused():
    # two boxes as one boundary (a body folded over itself); the centre in the first, its bottom face held
    va, fa = box((0.0, 0.0, 0.0), (10.0, 10.0, 10.0))
    vb, fb = box((20.0, 0.0, 0.0), (30.0, 10.0, 10.0))
    nodes, tris = np.vstack([va, vb]), np.vstack([fa, fb + 8])
    base = np.all(nodes[tris][:, :, 2] == 0.0, axis=1)
    dirs = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0], [0, 0, -1.0]])
    entry, depth, code = body_lines.skin_entries(nodes, tris, base, np.array([5.0, 5.0, 4.0]), dirs)
    # travelling −x enters at x = 10 with the second box beyond it; +x at x = 0; up through the base; down on top
    np.testing.assert_array_equal(code, [body_lines.RECROSSES, body_lines.LINE_OK, body_lines.THROUGH_BASE,
                                         body_lines.LINE_OK])
    np.testing.assert_allclose(depth, [5.0, 5.0, 4.0, 6.0])
    np.testing.assert_allclose(entry[1], [0.0, 5.0, 4.0])


def test_a_cyst_whose_centre_lies_outside_follows_the_nearest_tetrahedron(cyst):
    _, _, mesh, _ = cyst
    outside = Inclusion("c", "sphere", np.array([[0.0, 0.0, H + 1.0]]), 2.0, 1.0)
    with pytest.raises(ValueError, match="outside the mesh"):
        probe_points(mesh.nodes, mesh.tetrahedra, outside.points)
    carried = body_lines.carry_obstacles((outside,), mesh.nodes, mesh.tetrahedra, mesh.boundary_triangles)
    A, b = np.array([[1.1, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.2]]), np.array([1.0, -2.0, 0.5])
    q0, q1 = carried.segments(mesh.nodes @ A.T + b)  # an affine map is reproduced outside its cell too
    np.testing.assert_allclose(q0[0], A @ outside.points[0] + b, atol=1e-9)
    np.testing.assert_allclose(q1, q0)


# --- moving the lesion off the line --------------------------------------------------------------------------------

def _independent(tissue, scene, strokes):
    """The lesion (3,) and the vessel (P, 3) carried by a solve from rest, not the planner's warm-started chain."""
    x = solve_equilibrium(tissue, np.asarray(strokes, float)).x
    lesion = target_positions(tissue.probe(scene.targets[0].rest[None]), x)[0]
    ob = scene.obstacles[0]
    return x, lesion, target_positions(probe_points(tissue.mesh.nodes, tissue.mesh.tetrahedra, ob.points), x)


def test_a_blocked_line_is_cleared_by_the_least_push_that_clears_it(vessel):
    cfg, scene, mesh, tissue = vessel
    cache = StateCache(tissue)
    plan = bp.plan_body_target(tissue, scene, 0, cfg.needle, solve=cache.state)
    assert plan.feasible and plan.manipulated and plan.reason == ""
    assert plan.clearance_mm >= bp.CLEAR_RESERVE_MM
    assert 0 < plan.solves == cache.solves <= 20
    np.testing.assert_allclose(plan.direction, cfg.needle.direction)
    # the lesion where an independent solve at the plan's strokes puts it is the desired position
    x, lesion, tube = _independent(tissue, scene, plan.strokes)
    np.testing.assert_allclose(plan.desired, lesion, atol=1e-6)
    np.testing.assert_allclose(plan.entry + plan.depth_mm * plan.direction, lesion, atol=1e-9)
    # and the line is clear there (the vessel, a straight tube, carried by the same solve)
    assert _brute_clearance(plan.entry[None], lesion, [], [(tube, 1.5)])[0] == pytest.approx(plan.clearance_mm,
                                                                                               abs=0.02)
    # at rest it was blocked; an eighth of a grid step less stroke does not clear by the reserve (the move is
    # near the least)
    rest = bp.plan_body_target(tissue, scene, 0, cfg.needle)
    assert not rest.feasible and rest.clearance_mm < 0 and "no solver" in rest.reason
    step = np.diff(np.unique(bp.stroke_grid(scene)[:, 0]))[0]
    less = plan.strokes - np.sign(plan.strokes) * step / 8
    _, lesion_less, tube_less = _independent(tissue, scene, less)
    entry_less = lesion_less - 60.0 * np.asarray(cfg.needle.direction)  # the shaft beyond the vessel is what counts
    assert _brute_clearance(entry_less[None], lesion_less, [], [(tube_less, 1.5)])[0] < bp.CLEAR_RESERVE_MM


def test_a_push_the_cups_cannot_make_is_reported_with_the_best_found(vessel):
    cfg, scene, mesh, tissue = vessel
    cache = StateCache(tissue)
    short = dataclasses.replace(scene, cups=(dataclasses.replace(scene.cups[0], stroke_min_mm=-2.0,
                                                                 stroke_max_mm=2.0),))
    plan = bp.plan_body_target(tissue, short, 0, cfg.needle, solve=cache.state)
    assert not plan.feasible and plan.clearance_mm < 0
    assert "top [-2, 2]" in plan.reason and "stroke sample(s)" in plan.reason and "'vessel'" in plan.reason
    assert plan.solves == len(bp.stroke_grid(short))
    nocups = bp.plan_body_target(tissue, dataclasses.replace(scene, cups=()), 0, cfg.needle, solve=cache.state)
    assert not nocups.feasible and "no cups" in nocups.reason

    def pushes_fail(s):  # the caller's solver fails on every push; pulls are solved
        if s[0] > 0:
            raise SolverError("Newton did not converge")
        return cache.state(s)

    failing = bp.plan_body_target(tissue, scene, 0, cfg.needle, solve=pushes_fail)
    assert not failing.feasible and np.all(failing.strokes <= 0) and failing.solves == len(bp.stroke_grid(scene))
    assert "5 stroke sample(s) could not be solved, e.g. Newton did not converge" in failing.reason


def test_the_stroke_grid_covers_each_cups_range_in_order_of_size(vessel):
    _, scene, _, _ = vessel
    cup = scene.cups[0]
    one = bp.stroke_grid(scene)
    np.testing.assert_allclose(np.sort(one[:, 0]), [-10, -8, -6, -4, -2, 2, 4, 6, 8, 10])
    pull_only = dataclasses.replace(cup, name="b", stroke_min_mm=-6.0, stroke_max_mm=0.0)
    two = bp.stroke_grid(dataclasses.replace(scene, cups=(cup, pull_only)))
    assert two.shape == (7 * 4 - 1, 2) and np.all(np.diff(np.linalg.norm(two, axis=1)) >= 0)
    assert set(np.round(two[:, 1], 9)) == {-6.0, -4.0, -2.0, 0.0} and two[:, 0].min() == -10 and two[:, 0].max() == 10
    three = bp.stroke_grid(dataclasses.replace(scene, cups=(cup, pull_only, dataclasses.replace(cup, name="c"))))
    assert three.shape == (6 + 3 + 6, 3) and np.all(np.count_nonzero(three, axis=1) == 1)  # one cup at a time
    assert bp.stroke_grid(dataclasses.replace(scene, cups=())).size == 0


def test_the_targets_of_a_scene_share_their_solves(vessel):
    cfg, scene, mesh, tissue = vessel
    twice = dataclasses.replace(scene, targets=scene.targets * 2)
    calls = []
    cache = StateCache(tissue)

    def solve(s):
        calls.append(s)
        return cache.state(s)

    first, second = bp.plan_body_targets(tissue, twice, cfg.needle, solve=solve)
    assert first.feasible and second.feasible
    np.testing.assert_array_equal(first.strokes, second.strokes)
    assert first.solves == len(calls) > 0 and second.solves == 0


# --- the robot --------------------------------------------------------------------------------------------------------

def test_body_plan_to_joints_round_trips_through_the_forward_kinematics():
    robot = RobotModel.paper()
    q = np.array([150.0, 80.0, 60.0, np.deg2rad(-30.0), 30.0])
    tip, axis = (v[0] for v in robot.tip_and_axis(q))
    origin, yaw = np.array([120.0, -40.0, 90.0]), np.deg2rad(25.0)
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    tip_body, dir_body = Rz.T @ (tip - origin), Rz.T @ axis
    r = body_plan_to_joints(robot, tip_body, 3.0 * dir_body, origin, yaw)
    assert r.reachable and r.reason == "reachable"
    tip2, axis2 = (v[0] for v in robot.tip_and_axis(r.q))
    np.testing.assert_allclose(tip2, tip, atol=1e-9)
    np.testing.assert_allclose(axis2, axis, atol=1e-12)
    tilted = dir_body + np.array([0.0, 0.0, 0.05])
    r = body_plan_to_joints(robot, tip_body, tilted, origin, yaw)
    assert not r.reachable and "vertical" in r.reason and np.isnan(r.q).all()
    # the robot check of a plan: the joints put the tip on the lesion
    check = bp.body_robot_check(robot, origin, yaw)
    ok, joints, note = check(tip_body - 40.0 * dir_body, dir_body, 40.0)
    assert ok and note == "reachable"
    np.testing.assert_allclose(robot.tip_and_axis(joints)[0][0], tip, atol=1e-9)
    ok, joints, note = check(tip_body - 40.0 * tilted, tilted / np.linalg.norm(tilted), 40.0)
    assert not ok and joints is None and "vertical" in note
