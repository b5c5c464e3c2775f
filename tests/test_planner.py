"""Tests of scissor_cli.planning: corridor geometry by hand, outlines carried by the mesh, the no-manipulation
case, the paper's pull/push scenes (Fig. 11) re-checked independently, a
configured desired position, and an enclosed target that no stroke frees."""

from dataclasses import replace
from functools import lru_cache

import numpy as np
import pytest

from scissor_cli import geometry
from scissor_cli.config import NeedleConfig, load_config, parse_config
from scissor_cli.experiments.build import scene_of
from scissor_cli.mechanics.tissue import build_tissue
from scissor_cli.mesh.mesh import interpolate, locate, mesh_for_config
from scissor_cli.mesh.outlines import boundary_loop, deformed_outlines, embed_outlines
from scissor_cli.planning import corridor, states
from scissor_cli.planning import needle_plan as needle
from scissor_cli.solvers.newton import solve_newton

RADIUS = 0.6 + 1.0  # 18G needle radius + the default margin, mm
SQUARE = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
LAYER = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 60.0], [0.0, 60.0]])


@lru_cache(maxsize=None)
def _setup(path: str):
    cfg = load_config(path)
    scene = scene_of(cfg)
    tissue = build_tissue(scene, mesh_for_config(scene, cfg.tissue.mesh, scale=2.0))
    return cfg, scene, tissue


def _scene_from_yaml(text: str):
    cfg = parse_config(text, "<test>")
    scene = scene_of(cfg)
    return cfg, scene, build_tissue(scene, mesh_for_config(scene, cfg.tissue.mesh, scale=2.0))


# --------------------------------------------------------------------------
# Geometry


def test_corridor_clearance_past_a_square():
    # A horizontal segment 3 mm above the square's top edge.
    assert corridor.corridor_clearance([-5.0, 13.0], [20.0, 13.0], [SQUARE], RADIUS) == pytest.approx(3.0 - RADIUS)
    # A diagonal segment ending short of the corner (10, 10): distance √8.
    assert corridor.corridor_clearance([15.0, 15.0], [12.0, 12.0], [SQUARE], RADIUS) == pytest.approx(
        np.sqrt(8) - RADIUS)
    # Through the square: distance 0, so the clearance is -radius.
    assert corridor.corridor_clearance([-5.0, 5.0], [20.0, 5.0], [SQUARE], RADIUS) == pytest.approx(-RADIUS)
    # The nearest of two obstacles decides; none at all is +inf.
    far = SQUARE + [0.0, 30.0]
    assert corridor.corridor_clearance([-5.0, 13.0], [20.0, 13.0], [far, SQUARE], RADIUS) == pytest.approx(3.0 - RADIUS)
    assert corridor.corridor_clearance([0.0, 0.0], [1.0, 1.0], [], RADIUS) == np.inf


def test_vectorised_clearance_matches_scalar():
    rng = np.random.default_rng(3)
    target = np.array([5.0, 14.0])
    entries = rng.uniform(-20, 30, (40, 2))
    entries[3] = np.nan  # a candidate without an entry
    obstacles = [SQUARE, geometry.circle_polygon([20.0, 20.0], 3.0, 24)]
    got = corridor.corridor_clearances(entries, target, obstacles, RADIUS)
    assert np.isnan(got[3])
    want = [corridor.corridor_clearance(e, target, obstacles, RADIUS) for k, e in enumerate(entries) if k != 3]
    np.testing.assert_allclose(np.delete(got, 3), want, atol=1e-12)


def test_candidate_directions_and_entries():
    scene = _setup("configs/example.yaml")[1]
    cfg = NeedleConfig(entry_sides=["left", "right"], direction_range_deg=[-20.0, 20.0], direction_step_deg=10.0)
    cands = corridor.candidate_directions(cfg, scene)
    assert [s for s, _ in cands] == ["left"] * 5 + ["right"] * 5
    d = np.array([v for _, v in cands])
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    tilt = np.degrees(np.arctan2(d[:5, 1], d[:5, 0]))  # from the left side's inward normal (1, 0)
    np.testing.assert_allclose(tilt, [-20, -10, 0, 10, 20], atol=1e-12)

    straight = [("left", np.array([1.0, 0.0])), ("right", np.array([-1.0, 0.0]))]
    np.testing.assert_allclose(corridor.entry_points([30.0, 20.0], straight, LAYER), [[0.0, 20.0], [100.0, 20.0]])
    # Tilted 45° up from the left: the ray back from (10, 50) meets x = 0 at y = 40.
    up = [("left", np.array([1.0, 1.0]) / np.sqrt(2))]
    np.testing.assert_allclose(corridor.entry_points([10.0, 50.0], up, LAYER), [[0.0, 40.0]], atol=1e-12)
    # Tilted 60° down from the left near the top: the ray leaves through the top, not the left side.
    down = [("left", np.array([0.5, -np.sqrt(3) / 2]))]
    assert np.all(np.isnan(corridor.entry_points([5.0, 55.0], down, LAYER)))


def test_best_insertion_picks_largest_clearance():
    cfg = NeedleConfig()
    cands = [("left", np.array([1.0, 0.0])), ("right", np.array([-1.0, 0.0]))]
    # A square 2 mm above the left path: both clear, the right one by more.
    obstacle = SQUARE + [20.0, 22.0]
    ranked = corridor.ranked_insertions([50.0, 20.0], [obstacle], LAYER, cands, cfg)
    assert [i.side for i in ranked] == ["right", "left"]
    assert ranked[1].clearance_mm == pytest.approx(2.0 - RADIUS)
    best = corridor.best_insertion([50.0, 20.0], [obstacle], LAYER, cands, cfg)
    assert best.side == "right" and best.clear
    np.testing.assert_allclose(best.entry, [100.0, 20.0])
    assert best.depth_mm == pytest.approx(50.0)
    assert best.clearance_mm == pytest.approx(np.hypot(20.0, 2.0) - RADIUS)  # to the corner (30, 22)
    assert corridor.best_insertion([50.0, 20.0], [obstacle], LAYER, [("top", np.array([1.0, 0.0]))], cfg) is None


# --------------------------------------------------------------------------
# Outlines carried by the mesh


def test_boundary_loop_traces_the_outline_counter_clockwise():
    _, scene, tissue = _setup("configs/example.yaml")
    mesh = tissue.mesh
    loop = boundary_loop(mesh)
    # every boundary edge, once, head to tail, closing the loop
    assert len(loop) == len(mesh.boundary_edges) == len(set(loop.tolist()))
    edges = {(int(a), int(b)) for a, b in mesh.boundary_edges}
    assert {(int(a), int(b)) for a, b in zip(loop, np.roll(loop, -1))} == edges
    # the outline's corners are on it, and it encloses the outline's area counter-clockwise
    for corner in scene.outline:
        assert np.linalg.norm(mesh.nodes[loop] - corner, axis=1).min() < 1e-9
    assert geometry.signed_area(mesh.nodes[loop]) == pytest.approx(geometry.signed_area(scene.outline), rel=1e-12)
    assert geometry.signed_area(scene.outline) > 0


def test_deformed_outlines_follow_an_affine_map_exactly():
    """Barycentric weights reproduce affine maps, so carried outlines are the mapped rest outlines."""
    _, scene, tissue = _setup("configs/example.yaml")
    mesh = tissue.mesh
    outlines = [o.outline for o in scene.obstacles] + [np.array([[40.0, 25.0]])]
    emb = embed_outlines(mesh, outlines)
    assert emb.splits[-1] == sum(len(o) for o in outlines)
    A, b = np.array([[1.1, 0.2], [-0.1, 0.9]]), np.array([3.0, -2.0])
    got = deformed_outlines(emb, mesh.nodes @ A.T + b)
    assert [g.shape for g in got] == [o.shape for o in outlines]
    for g, o in zip(got, outlines):
        np.testing.assert_allclose(g, o @ A.T + b, atol=1e-9)
    assert deformed_outlines(embed_outlines(mesh, []), mesh.nodes) == []


# --------------------------------------------------------------------------
# Plans


def _independent_check(scene, tissue, plan):
    """Solve again from rest, carry the obstacles and target, recompute the clearance."""
    mesh = tissue.mesh
    x = tissue.rest if not plan.manipulated else solve_newton(tissue, plan.strokes).x
    obstacles = []
    for o in scene.obstacles:
        tri, bary = locate(mesh, o.outline)
        obstacles.append(interpolate(x, mesh.triangles, tri, bary))
    target = next(t for t in scene.targets if t.name == plan.target)
    tri, bary = locate(mesh, target.rest[None])
    y = interpolate(x, mesh.triangles, tri, bary)[0]
    # The entry lies on the deformed skin, one depth back along the direction.
    a, b = x[mesh.boundary_edges[:, 0]], x[mesh.boundary_edges[:, 1]]
    assert geometry.point_segment_distance(plan.entry[None], a, b).min() < 1e-6
    np.testing.assert_allclose(plan.entry + plan.depth_mm * plan.direction, plan.desired, atol=1e-6)
    d = min(geometry.segment_polygon_distance(plan.entry, plan.desired, p) for p in obstacles)
    return y, d - RADIUS


@pytest.mark.parametrize("path, sign", [("configs/paper_pull.yaml", -1), ("configs/paper_push.yaml", +1)])
def test_paper_scenes_blocked_at_rest_clear_after_manipulation(path, sign):
    cfg, scene, tissue = _setup(path)
    cache = states.StateCache(tissue)
    cands = corridor.candidate_directions(cfg.needle, scene)
    for target in scene.targets:
        rest = corridor.best_insertion(target.rest, [o.outline for o in scene.obstacles], scene.outline, cands,
                                       cfg.needle)
        assert not rest.clear, f"{target.name} should be blocked at rest"
        plan = needle.plan_target(tissue, scene, target, cfg.needle, cache=cache)
        assert plan.feasible and plan.reason == ""
        assert plan.manipulated and np.sign(plan.strokes[0]) == sign
        assert plan.clearance_mm >= 0.5
        y, clearance = _independent_check(scene, tissue, plan)
        np.testing.assert_allclose(y, plan.desired, atol=1e-6)
        assert clearance == pytest.approx(plan.clearance_mm, abs=1e-6)
        assert np.all(np.isnan(plan.joints)) and plan.robot_note == "robot kinematics not applied"


def test_a_plan_on_another_models_target_positions():
    """`target_at` (a 3-D-aware controller model's target, docs/model.md §15) replaces the tissue's target in the
    search, the obstacles staying the tissue's: given the tissue's own positions it is the plain plan; given a
    target that moves half as far, the plan's desired point is that model's target at the plan's strokes and
    its corridor clears the tissue's obstacles deformed there."""
    cfg, scene, tissue = _setup("configs/paper_push.yaml")
    target = scene.targets[0]
    mesh = tissue.mesh
    tri, bary = locate(mesh, target.rest[None])
    cache = states.StateCache(tissue)

    def layer_target(strokes):
        return interpolate(cache.state(strokes), mesh.triangles, tri, bary)[0]

    def half_as_far(strokes):
        return target.rest + 0.5 * (layer_target(strokes) - target.rest)

    plain = needle.plan_target(tissue, scene, target, cfg.needle, cache=cache)
    same = needle.plan_target(tissue, scene, target, cfg.needle, cache=cache, target_at=layer_target)
    np.testing.assert_allclose(same.strokes, plain.strokes)
    np.testing.assert_allclose(same.desired, plain.desired, atol=1e-9)
    half = needle.plan_target(tissue, scene, target, cfg.needle, cache=cache, target_at=half_as_far)
    assert half.feasible and half.manipulated
    np.testing.assert_allclose(half.desired, half_as_far(half.strokes), atol=1e-9)
    assert not np.allclose(half.desired, layer_target(half.strokes), atol=0.1)
    _, clearance = _independent_check(scene, tissue, half)
    assert clearance == pytest.approx(half.clearance_mm, abs=1e-6) and clearance > 0


def test_free_path_at_rest_needs_no_manipulation():
    cfg, scene, tissue = _setup("configs/example.yaml")
    target = replace(scene.targets[1], desired=None)  # T2 without its configured desired position
    plan = needle.plan_target(tissue, scene, target, cfg.needle)
    assert plan.feasible and not plan.manipulated and plan.solves == 0
    np.testing.assert_array_equal(plan.strokes, [0.0])
    np.testing.assert_allclose(plan.desired, target.rest)
    expected = corridor.corridor_clearance(plan.entry, target.rest, [o.outline for o in scene.obstacles], RADIUS)
    assert plan.clearance_mm == pytest.approx(expected) and plan.clearance_mm > 0


def test_configured_desired_overrides_the_search():
    cfg, scene, tissue = _setup("configs/example.yaml")
    target = scene.targets[1]  # T2, desired_mm [58.0, 20.5]
    plan = needle.plan_target(tissue, scene, target, cfg.needle)
    np.testing.assert_array_equal(plan.desired, [58.0, 20.5])
    assert plan.feasible and plan.manipulated
    # The stroke is where the target comes closest to the desired position.
    y, clearance = _independent_check(scene, tissue, plan)
    assert np.linalg.norm(y - plan.desired) == pytest.approx(plan.desired_error_mm, abs=1e-6)
    mesh = tissue.mesh
    tri, bary = locate(mesh, target.rest[None])
    for ds in (-0.5, 0.5):
        x = solve_newton(tissue, plan.strokes + ds).x
        assert np.linalg.norm(interpolate(x, mesh.triangles, tri, bary)[0] - plan.desired) > plan.desired_error_mm
    assert clearance == pytest.approx(plan.clearance_mm, abs=1e-6)


def test_robot_check_rejection_falls_back_to_next_clear_insertion():
    cfg, scene, tissue = _setup("configs/example.yaml")
    target = replace(scene.targets[1], desired=None)  # clear from both sides at rest

    def no_left(entry, direction, tgt):
        ok = direction[0] < 0
        return np.arange(5.0), ok, "ok" if ok else "theta4 out of range"

    plan = needle.plan_target(tissue, scene, target, cfg.needle, robot_check=no_left)
    assert plan.feasible and plan.side == "right" and plan.robot_ok
    np.testing.assert_array_equal(plan.joints, np.arange(5.0))

    never = lambda e, d, t: (np.full(5, np.nan), False, "tip outside the workspace")  # noqa: E731
    plan = needle.plan_target(tissue, scene, target, cfg.needle, robot_check=never)
    # the corridor stays planned; the robot's refusal is reported beside it
    assert plan.feasible and not plan.robot_ok and "tip outside the workspace" in plan.robot_note


ENCLOSED = """
name: enclosed
tissue: {shape: rectangle, size_mm: [100.0, 60.0], fixed: [bottom]}
cups:
  - {name: cup, contact_mm: [50.0, 60.0], axis: [0.0, -1.0], stroke_mm: [-10.0, 10.0]}
targets:
  - {name: boxed, position_mm: [50.0, 30.0]}
obstacles:   # four bars around the target; the 1 mm corner gaps are narrower than the corridor
  - {name: west,  polygon_mm: [[40.0, 20.0], [43.0, 20.0], [43.0, 40.0], [40.0, 40.0]]}
  - {name: east,  polygon_mm: [[57.0, 20.0], [60.0, 20.0], [60.0, 40.0], [57.0, 40.0]]}
  - {name: north, polygon_mm: [[44.0, 37.0], [56.0, 37.0], [56.0, 40.0], [44.0, 40.0]]}
  - {name: south, polygon_mm: [[44.0, 20.0], [56.0, 20.0], [56.0, 23.0], [44.0, 23.0]]}
needle: {entry_sides: [left, right, top], direction_range_deg: [-30.0, 30.0], direction_step_deg: 15.0}
"""


def test_enclosed_target_is_infeasible_with_a_reason():
    cfg, scene, tissue = _scene_from_yaml(ENCLOSED)
    plan = needle.plan_target(tissue, scene, scene.targets[0], cfg.needle, stroke_samples=11, refine_levels=1)
    assert not plan.feasible
    assert "no entry side/direction clears the obstacles at any stroke in [-10, 10] mm" in plan.reason
    assert "best clearance" in plan.reason
    assert plan.clearance_mm <= 0 and plan.solves > 0


def test_target_inside_an_obstacle_is_infeasible():
    text = ENCLOSED.replace("position_mm: [50.0, 30.0]", "position_mm: [41.5, 30.0]")
    cfg, scene, tissue = _scene_from_yaml(text)
    plan = needle.plan_target(tissue, scene, scene.targets[0], cfg.needle)
    assert not plan.feasible and "inside obstacle 'west'" in plan.reason and plan.solves == 0


def test_default_scene_has_a_plan_the_robot_realises_for_every_target():
    """Plans are ranked by clearance among the insertions the inverse kinematics accepts (docs/model.md §7)."""
    from scissor_cli.experiments.simulate import robot_joint_check

    cfg, scene, tissue = _setup("configs/example.yaml")
    for plan in needle.plan_targets(tissue, scene, cfg.needle, robot_check=robot_joint_check(cfg)):
        assert plan.feasible and plan.robot_ok, (plan.target, plan.robot_note)
        assert plan.clearance_mm > 0 and np.all(np.isfinite(plan.joints))
    t1 = needle.plan_target(tissue, scene, scene.targets[0], cfg.needle, robot_check=robot_joint_check(cfg))
    assert t1.side == "right" and t1.manipulated  # blocked by the nerve at rest, cleared by a push


def test_hard_case_without_a_realisable_plan_says_why():
    from scissor_cli.experiments.simulate import robot_joint_check

    cfg, scene, tissue = _setup("configs/hard/robot_unreachable.yaml")
    plan = needle.plan_target(tissue, scene, scene.targets[0], cfg.needle, robot_check=robot_joint_check(cfg))
    assert plan.feasible and not plan.robot_ok and plan.side == "left"
    assert "cannot realise" in plan.robot_note and "theta4" in plan.robot_note
