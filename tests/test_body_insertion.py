"""The needle in the body (docs/model.md §20, §12 with state): any axis, the strategies, the forces that balance.

The scene is tests/test_body_loop.py's dome (two lesions, a vessel beside T1's path, two cups, two cameras),
coarser, so an insertion takes seconds.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import yaml

from scissor_cli.config.loading import parse_config
from scissor_cli.experiments.body_trials import body_sensor_model
from scissor_cli.experiments.build import body_model
from scissor_cli.experiments.profiles import error_model
from scissor_cli.insertion import InsertionOptions, NeedleParams, NeedlePath, run_strategies
from scissor_cli.insertion.model_table import tabulate
from scissor_cli.planning.body_lines import skin_entries
from scissor_cli.sensing.sensor import EXACT, TrueState
from scissor_cli.solvers.equilibrium import solve_equilibrium

from figure_checks import assert_png_drawn
from helpers import cli_here, simulate_here, write_scene
from test_body_loop import SCENE
from test_cli import run_cli

COARSE = dict(SCENE, tissue=dict(SCENE["tissue"], mesh={"max_edge_mm": 9.0, "min_edge_mm": 3.5, "grading": 0.8}),
              trials={"count": 0})


@pytest.fixture(scope="module")
def body():
    cfg = parse_config(yaml.safe_dump(COARSE), "<test>")
    scene, _, tissue = body_model(cfg)
    return cfg, scene, tissue


def _insert(body, strategy="none", direction=(-1.0, 0.0, 0.0), record=None, sensor=EXACT, tolerance_mm=None,
            table=False, **params):
    """Insert towards T1 from rest along `direction`, from where that line enters the skin, to T1's depth
    (`loop` with the controller's tolerance, or tolerance_mm: the loop's deadband is half of it; table: `loop`
    steered by the nominal insertion's table, as a run's, else by the body itself under the needle)."""
    cfg, scene, tissue = body
    controller = cfg.controller if tolerance_mm is None else cfg.controller.model_copy(
        update={"tolerance_mm": tolerance_mm})
    n = np.asarray(direction, float) / np.linalg.norm(direction)
    rest = scene.targets[0].rest
    mesh = tissue.mesh
    entries, depths, _ = skin_entries(mesh.nodes, mesh.boundary_triangles, np.zeros(len(mesh.boundary_triangles),
                                                                                   bool), rest, n[None])
    strokes = np.zeros(len(scene.cups))
    x0 = solve_equilibrium(tissue, strokes).x
    p = NeedleParams(**{"step_mm": 1.0, "capture_radius_mm": 2.5, **params})
    path = NeedlePath(entries[0], n, float(depths[0]), rest, "T1")
    needle = tabulate(tissue, x0, strokes, path, p, controller) if table else None
    return run_strategies(tissue, x0, strokes, {strategy: path}, p,
                          {strategy: InsertionOptions(strategy, controller, record=record, sensor=sensor,
                                                      needle_model=needle)})[0], rest


def test_with_no_friction_and_no_tip_force_the_lesion_does_not_move(body):
    """Solved to 1e-8 (at the body's default step tolerance, 1e-4, the solves alone are ~1e-3 mm off). A node
    whose static limit is zero never sticks (it once did: caught up, stuck, released, until locked stuck at the tip
    holding 2.6 mN, which carried the lesion 2.7e-3 mm)."""
    r, rest = _insert(body, friction_static_mN_per_mm=0.0, friction_kinetic_mN_per_mm=0.0, tip_force_mN=0.0,
                      step_tol=1e-8, step_mm=2.0)
    assert r.completed and r.steps >= 10 and not np.any(r.stuck)
    assert np.max(np.linalg.norm(r.target - rest, axis=1)) <= 1e-3
    assert np.all(np.abs(r.needle_force_mN) <= 1e-6)


def test_when_every_captured_node_slips_the_force_is_the_tip_plus_kinetic_friction_along_the_shaft(body):
    """f_s = f_k: at the steps where every captured node slips the same way (dragged along the needle), F = F_tip +
    f_k · depth (Σ l_i = depth, from the skin); the tip's half-ball wholly inside (depth > tip_zone_mm)."""
    f_k, f_tip = 10.0, 100.0
    signs = []
    r, _ = _insert(body, friction_static_mN_per_mm=f_k, friction_kinetic_mN_per_mm=f_k, tip_force_mN=f_tip,
                   record=lambda state, x, strokes: signs.append(state.sign.copy()))
    one_way = np.array([s.size > 0 and np.all(s == s[0]) and s[0] != 0 for s in signs])
    all_slip = (r.stuck == 0) & one_way & (r.depth_mm > 2.0)
    assert all_slip.sum() >= 10
    np.testing.assert_allclose(r.needle_force_mN[all_slip], f_tip + f_k * r.depth_mm[all_slip], rtol=0.01)


@pytest.mark.parametrize("direction", [(-1.0, 0.0, 0.0), (-0.8, 0.3, -0.52)])
def test_any_axis_reaches_the_lesion_and_the_tip_is_on_the_needle(body, direction):
    r, rest = _insert(body, "depth", direction=direction)
    assert r.completed and r.tip.shape == (r.steps, 3) and r.target.shape == (r.steps, 3)
    along = (r.tip - r.entry) @ r.direction
    np.testing.assert_allclose(along, r.depth_mm, atol=1e-9)  # the tip rides the axis
    assert abs(r.depth_error_mm) <= 1.0 + 1e-9  # stopped within a step of the lesion as measured
    assert np.isfinite(r.miss_mm) and r.miss_mm < 2.0



def test_a_node_that_sticks_again_beside_a_released_one_does_not_stop_the_needle():
    """A slipping node that catches up with the needle sticks where the needle carried it; placed there alone in the
    pass's equilibrium it can flatten an element that a neighbour's release stretched, whatever the step's size. On
    test_body_loop's dome (the truth's mesh, coarse) T2's line, as a controller model twice as coarse plans it, so
    stopped at 43 mm ("inverts an element even when split into 64 parts"); the pass now starts from the step's own
    start with the set as it stands (`needle._newton_start`) and the needle reaches its depth."""
    cfg = parse_config(yaml.safe_dump(SCENE), "<test>")
    scene, _, tissue = body_model(cfg)
    lesion = scene.targets[1]
    strokes = np.zeros(len(scene.cups))
    x0 = solve_equilibrium(tissue, strokes).x
    path = NeedlePath(np.array([36.69, -5.92, 8.05]), np.array([-1.0, 0.0, 0.0]), 44.69, lesion.rest, lesion.name)
    params = NeedleParams(step_mm=1.0, capture_radius_mm=2.5)
    r = run_strategies(tissue, x0, strokes, {"none": path}, params,
                       {"none": InsertionOptions("none", cfg.controller, keep_displacement=False)})[0]
    assert r.completed, r.stop_reason
    assert np.all(np.isfinite(r.target)) and np.all(np.isfinite(r.needle_force_mN))



def test_nearly_incompressible_the_needle_s_passes_are_damped_not_handed_to_newton(monkeypatch):
    """ν 0.499: a fresh factorisation's chord step (Newton's own) often raises the residual on its way to the
    equilibrium, as Newton's full steps do there. It is damped as Newton damps it, on Φ (`chord.ChordSolver`),
    where before the pass went to Newton from its start (on this body 21 of 31 steps, with a factorisation per
    Newton iteration); the needle still reaches its depth."""
    from scissor_cli.insertion import needle

    cfg = parse_config(yaml.safe_dump(dict(COARSE, material=dict(COARSE["material"], nu=0.499))), "<test>")
    scene, _, tissue = body_model(cfg)
    newton, solve = [], needle.solve_equilibrium
    monkeypatch.setattr(needle, "solve_equilibrium", lambda *a, **k: newton.append(1) or solve(*a, **k))
    r, _ = _insert((cfg, scene, tissue))
    assert r.completed, r.stop_reason
    assert len(newton) <= 2, len(newton)


#: a run of one lesion with the needle and a trial
WITH_NEEDLE = dict(COARSE, targets=COARSE["targets"][:1], trials={"count": 1, "profile": "ideal"},
                   insertion={"step_mm": 1.0, "capture_radius_mm": 2.5, "strategies": ["none", "depth", "loop"]})


@pytest.fixture(scope="module")
def needle_run(tmp_path_factory):
    """`simulate` of WITH_NEEDLE in one process: the run's directory."""
    return simulate_here(tmp_path_factory.mktemp("needle"), WITH_NEEDLE)


def test_the_run_inserts_every_planned_lesion_along_its_plan_and_so_do_its_trials(needle_run, tmp_path):
    """`simulate` with `insertion` on a body: each plan's needle, the results in 3-D, the shaft clear of the vessel,
    `depth` stopping at the lesion as the cameras see it; each trial inserts every strategy from where its loop
    left the body, the miss and depth error per strategy stored (T, S). (`loop` in a run:
    benchmarks/bench_body_insertion.py.)"""
    with h5py.File(needle_run / "results.h5", "r") as f:
        # `loop`'s needle model beside its insertion: the nominal `depth` insertion tabulated
        table = f["insertion/T1/loop/needle_model"]
        assert table["jacobian"].shape == (len(table["depth_mm"]), 3, 2) and table["target"].shape[1] == 3
        np.testing.assert_allclose(table["target"][-1], f["insertion/T1/depth/target"][-1], atol=1e-6)
        plan = f["plan/T1"].attrs
        depth = f["insertion/T1/depth"]
        assert depth["tip"].shape[1] == 3 and depth["target"].shape[1] == 3
        np.testing.assert_allclose(depth.attrs["entry"], plan["entry"])
        np.testing.assert_allclose(depth.attrs["direction"], plan["direction"])
        assert depth.attrs["has_obstacles"] and np.all(depth["min_clearance_mm"][()] > 0.0)  # the vessel beside it
        # `depth` stops where the cameras saw the lesion before its shortened last step; the lesion moves on
        # during that step (its drag is not chased): a few hundredths of a mm, `none`'s push ahead a millimetre
        assert abs(depth.attrs["depth_error_mm"]) <= 0.1 < abs(f["insertion/T1/none"].attrs["depth_error_mm"])
        miss, depth_error = f["trials/T1/miss_mm"][()], f["trials/T1/depth_error_mm"][()]
        assert list(f["trials/T1/miss_mm"].attrs["strategies"]) == ["none", "depth", "loop"]
        f_steps = len(depth["tip"])
    assert miss.shape == (1, 3) and np.all(np.isfinite(miss)) and np.all(miss < 2.0)
    assert abs(depth_error[0, 1]) <= 0.05 < abs(depth_error[0, 0])
    assert_png_drawn(needle_run / "insertion_path_T1.png")
    # ParaView: the insertion's steps on the body's own mesh
    r = cli_here("export", needle_run, "--out", tmp_path / "paraview", "--format", "vtu")
    assert r.exit_code == 0, r.output
    assert len(list((tmp_path / "paraview" / "insertion_T1_depth").glob("*.vtu"))) == f_steps


def test_on_two_workers_the_nominal_insertions_run_beside_the_trials_to_the_same_numbers(needle_run, tmp_path,
                                                                                         monkeypatch):
    """With two local workers a lesion's nominal insertions go to the trials' pool (`run_trial_stage`'s `nominal`,
    `BodyTrialContext.insert_nominal`) instead of the run's own process: every number stored is the one-process
    run's, to the last bit, and the insertions are marked finished for `--resume`."""
    from scissor_cli.experiments import body_closed_loop

    from test_resume_stages import assert_same_run

    def not_here(*args, **kwargs):
        raise AssertionError("the run's own process ran the nominal insertions")

    monkeypatch.setattr(body_closed_loop, "body_insertion_stage", not_here)
    two = simulate_here(tmp_path, WITH_NEEDLE, jobs=2)
    with h5py.File(two / "results.h5", "r") as h5:
        finished = set(h5.attrs["finished"].astype(str))
    assert {"insertion/T1", "manipulation/T1", "trials"} <= finished
    assert_same_run(needle_run / "results.h5", two / "results.h5")
    assert_png_drawn(two / "insertion_path_T1.png")


@pytest.mark.parametrize("table", [False, True], ids=["body", "table"])
def test_loop_drives_both_components_of_the_miss_with_both_cups(body, table):
    """From rest, T1 on its line: the shaft's drag pushes it off; `loop` (J 2 × 2, the body's held response, or
    the nominal insertion's tabulated as a run steers with it) brings it back within 0.1 mm and to a fraction of
    `none`'s miss, the cups within the drives' speed each step.
    Without the tip's force: its push on the lesion in the last steps is faster than the drives follow (the
    cups' reach per step), and on the element that does not lock it moves this coarse dome's lesion by a few
    tenths of a millimetre, which the drag test is not about. The drag here is a few hundredths of a millimetre:
    the controller's tolerance 0.02 mm (its deadband 0.01 mm) lets the loop act on it."""
    cfg, scene, _ = body
    none, _ = _insert(body, "none", tip_force_mN=0.0)
    loop, _ = _insert(body, "loop", tip_force_mN=0.0, tolerance_mm=0.02, table=table)
    assert loop.completed and loop.miss_mm <= 0.1 and loop.miss_mm < 0.2 * none.miss_mm
    assert np.any(np.abs(loop.strokes[-1]) > 0.5)  # the cups moved
    reach = np.array([c.speed_mm_per_s for c in scene.cups]) / cfg.controller.rate_hz
    assert np.all(np.abs(np.diff(loop.strokes, axis=0)) <= reach + 1e-9)


@pytest.mark.parametrize("table", [False, True], ids=["body", "table"])
def test_loop_under_one_camera_drives_the_miss_it_sees(body, table):
    """One camera above does not see the depth along its view: its reading's z is NaN. The loop drives the part of
    the miss across the needle that the camera sees (y, the needle along x), as the manipulation's law does. It
    once computed the miss as T · (reading − entry), which 0 · NaN made NaN in both rows, and the cups never moved:
    `loop` ended where `depth` did."""
    cfg, scene, tissue = body
    one = parse_config(yaml.safe_dump(dict({k: v for k, v in COARSE.items() if k != "cameras"},
                                           camera={"position_mm": [0.0, 0.0, 400.0]})), "<test>")
    sensor = body_sensor_model(one, error_model(one.trials), tissue.mesh).nominal(scene.targets[0].rest)
    assert np.isnan(sensor.measure(TrueState(scene.targets[0].rest, tissue.rest, tissue.mesh))[2])
    runs = {k: _insert(body, k, tip_force_mN=0.0, sensor=sensor, tolerance_mm=0.02, table=table)[0]
            for k in ("depth", "loop")}
    loop = runs["loop"]
    assert loop.completed and np.any(np.abs(loop.strokes[-1] - loop.strokes[0]) > 0.1)  # the cups moved
    seen_miss = {k: abs(r.target[-1][1] - r.entry[1]) for k, r in runs.items()}  # y: across the needle, seen
    assert seen_miss["loop"] <= 0.1 and seen_miss["loop"] < 0.5 * seen_miss["depth"]


def test_with_one_cup_loop_does_not_chase_the_miss_it_cannot_correct(body):
    """One cup moves the lesion along one line across the needle; the rest of the miss is out of its reach. The
    loop moves the cup only while the part of the miss it can correct (J J⁺ e) is beyond the deadband: it once
    moved at most steps, trading one component for the other by hundredths of a millimetre, each move an
    equilibrium of the body."""
    one = parse_config(yaml.safe_dump(dict(COARSE, cups=COARSE["cups"][:1])), "<test>")
    scene, _, tissue = body_model(one)
    none, _ = _insert((one, scene, tissue), "none", tip_force_mN=0.0)
    loop, _ = _insert((one, scene, tissue), "loop", tip_force_mN=0.0, tolerance_mm=0.02, table=True)
    moves = int(np.sum(np.any(np.diff(loop.strokes, axis=0) != 0.0, axis=1)))
    assert loop.completed and 0 < moves <= loop.steps // 3
    assert loop.miss_mm < 0.75 * none.miss_mm  # and it still corrects what it can


def test_a_bad_insertion_section_of_a_body_exits_2(tmp_path):
    data = dict(COARSE, insertion={"friction_static_mN_per_mm": 5.0, "friction_kinetic_mN_per_mm": 10.0})
    r = run_cli("validate", write_scene(tmp_path, data))
    assert r.returncode == 2 and "insertion.friction_kinetic_mN_per_mm" in r.stderr and "Traceback" not in r.stderr



def test_a_run_makes_each_lesion_s_needle_model_once_and_reads_it_from_the_cache(body, tmp_path, monkeypatch):
    """`loop`'s model under the needle in a run: the nominal body's `depth` insertion at the plan, tabulated once
    (depths increasing, the lesion dragged, its held J 3 × C), kept in the run's cache and read back unchanged."""
    from types import SimpleNamespace

    import scissor_cli.experiments.body_insertion as body_insertion

    cfg, scene, tissue = body
    rest = scene.targets[0].rest
    mesh = tissue.mesh
    n = np.array([-1.0, 0.0, 0.0])
    entries, depths, _ = skin_entries(mesh.nodes, mesh.boundary_triangles, np.zeros(len(mesh.boundary_triangles),
                                                                                   bool), rest, n[None])
    plans = [SimpleNamespace(feasible=True, strokes=np.zeros(len(scene.cups)), entry=entries[0], direction=n,
                             depth_mm=float(depths[0])),
             SimpleNamespace(feasible=False)]
    cfg = parse_config(yaml.safe_dump(dict(COARSE, insertion={"step_mm": 2.0, "capture_radius_mm": 2.5,
                                                               "strategies": ["none", "loop"]})), "<test>")
    made = body_insertion.body_needle_models(cfg, tissue, plans, tmp_path)
    assert list(made) == ["T1"]
    table = made["T1"]
    assert np.all(np.diff(table.depth_mm) > 0) and table.jacobian.shape == (len(table.depth_mm), 3, len(scene.cups))
    assert np.all(np.isfinite(table.jacobian)) and np.linalg.norm(table.target_mm[-1] - rest) > 1e-3
    monkeypatch.setattr(body_insertion, "tabulate", lambda *a, **k: pytest.fail("made again, not read"))
    again = body_insertion.body_needle_models(cfg, tissue, plans, tmp_path)["T1"]
    np.testing.assert_array_equal(again.jacobian, table.jacobian)
    np.testing.assert_array_equal(again.target_mm, table.target_mm)


def test_a_lesion_whose_nominal_insertion_fails_gets_no_needle_model_and_the_run_says_so(body, monkeypatch, capsys):
    """`loop` on that lesion then follows the needle in the undrawn body (`ModelState`): the run goes on."""
    from types import SimpleNamespace

    import scissor_cli.experiments.body_insertion as body_insertion
    from scissor_cli import progress
    from scissor_cli.solvers.common import SolverError

    cfg, scene, tissue = body
    cfg = parse_config(yaml.safe_dump(dict(COARSE, insertion={"strategies": ["loop"]})), "<test>")

    def fails(*args, **kwargs):
        raise SolverError("the nominal insertion stopped short")

    monkeypatch.setattr(body_insertion, "tabulate", fails)
    monkeypatch.setattr(progress, "info", lambda message: print(message))
    plans = [SimpleNamespace(feasible=True, strokes=np.zeros(len(scene.cups)), entry=np.zeros(3),
                             direction=np.array([1.0, 0.0, 0.0]), depth_mm=10.0)]
    assert body_insertion.body_needle_models(cfg, tissue, plans, None, {"T1": tissue.rest}) == {}
    assert "needle model T1: none (the nominal insertion stopped short)" in capsys.readouterr().out
