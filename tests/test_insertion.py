"""Needle insertion (docs/model.md §12): capture, stick–slip friction, tip force, strategies, hard cases."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from scissor_cli import progress
from scissor_cli.config import load_config
from scissor_cli.experiments.build import build_model
from scissor_cli.insertion import InsertionOptions, NeedleParams, NeedlePath, run_insertion, shaft_lengths
from scissor_cli.insertion.capture import free_nodes
from scissor_cli.insertion.needle import NeedleState, advance
from scissor_cli.solvers.newton import solve_newton

from figure_checks import assert_png_drawn
from helpers import example_dict, write_scene

INSERTION = {"step_mm": 1.0, "friction_static_mN_per_mm": 15.0, "friction_kinetic_mN_per_mm": 10.0,
             "tip_force_mN": 100.0, "tip_zone_mm": 2.0, "strategies": ["none", "depth", "loop"]}
#: a left entry at T1's height, straight along +x, 25 mm deep (a coarse mesh keeps the tests quick)
ENTRY, AXIS, DEPTH = np.array([0.0, 32.0]), np.array([1.0, 0.0]), 25.0


def _tissue(tmp_path, **changes):
    data = example_dict()
    data["tissue"]["mesh"]["scale"] = 2.0
    data["insertion"] = dict(INSERTION)
    for k, v in changes.items():
        data[k] = v
    cfg = load_config(write_scene(tmp_path, data))
    return cfg, build_model(cfg)[2]


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return _tissue(tmp_path_factory.mktemp("ins"))


def _params(cfg, **kw):
    return dataclasses.replace(NeedleParams.from_config(cfg.insertion, cfg.needle, cfg.tissue.mesh), **kw)


def _insert(tissue, params, strategy="none", entry=ENTRY, axis=AXIS, depth=DEPTH, target=(45.0, 32.0), cfg=None):
    x0 = tissue.rest.copy()
    s0 = np.zeros(tissue.n_cups)
    return run_insertion(tissue, x0, s0, NeedlePath(entry, axis, depth, np.asarray(target, float)), params,
                         InsertionOptions(strategy, None if cfg is None else cfg.controller))


def _finite(r):
    for name in ("depth_mm", "tip", "target", "needle_force_mN", "min_clearance_mm", "displacement", "x"):
        assert np.all(np.isfinite(getattr(r, name))), name
    assert np.isfinite(r.miss_mm) and np.isfinite(r.depth_error_mm)


def test_shaft_lengths_sum_to_the_inserted_length():
    s = np.array([3.0, 0.2, 7.5, 7.5, 9.9])
    lengths = shaft_lengths(s, 10.0)
    assert lengths.sum() == pytest.approx(10.0, abs=1e-12)
    assert np.all(lengths >= 0)
    assert lengths[1] == pytest.approx(0.2 + (3.0 - 0.2) / 2)  # the first takes the gap to the entry
    assert shaft_lengths(np.zeros(0), 5.0).size == 0


def test_captured_lengths_sum_to_the_depth_every_step(model):
    cfg, tissue = model
    state = NeedleState(ENTRY, AXIS)
    x, params = tissue.rest.copy(), _params(cfg)
    for _ in range(8):
        x = advance(tissue, state, x, np.zeros(tissue.n_cups), 1.0, params, free_nodes(tissue)).x
        assert state.lengths.sum() == pytest.approx(state.depth_mm, abs=1e-9)
    assert state.captured.size >= 2


def test_no_friction_and_no_tip_force_move_nothing(model):
    cfg, tissue = model
    r = _insert(tissue, _params(cfg, friction_static_mN_per_mm=0.0, friction_kinetic_mN_per_mm=0.0, tip_force_mN=0.0))
    assert r.completed and r.steps == 25
    assert np.abs(r.displacement).max() <= 1e-6
    np.testing.assert_allclose(r.needle_force_mN, 0.0, atol=1e-6)


def test_when_every_node_slips_the_force_is_tip_plus_kinetic_friction(model):
    cfg, tissue = model
    params = _params(cfg, friction_static_mN_per_mm=1.0, friction_kinetic_mN_per_mm=1.0, tip_force_mN=5.0)
    r = _insert(tissue, params)
    all_slip = (r.stuck == 0) & (r.slipping > 0)
    assert all_slip.sum() >= 5
    expected = 5.0 + 1.0 * r.depth_mm[all_slip]
    np.testing.assert_allclose(r.needle_force_mN[all_slip], expected, rtol=1e-12)


def test_boundary_and_cup_reactions_balance_the_needle_force(model):
    cfg, tissue = model
    r = _insert(tissue, _params(cfg))
    _, grad = tissue.energy_gradient(r.x)  # Σ ∇U over all dofs is 0: the supports carry what the needle pushes
    d = tissue.dirichlet_dofs
    axial_reaction = float(np.sum(grad[d] * AXIS[d % 2]))
    assert r.needle_force_mN[-1] > 100.0
    assert axial_reaction + r.needle_force_mN[-1] == pytest.approx(0.0, abs=1e-6 * r.needle_force_mN[-1])


def test_drag_grows_with_friction(model):
    cfg, tissue = model
    drag = []
    for fs, fk in ((2.0, 1.0), (15.0, 10.0), (40.0, 30.0)):
        r = _insert(tissue, _params(cfg, friction_static_mN_per_mm=fs, friction_kinetic_mN_per_mm=fk, tip_force_mN=0.0))
        drag.append(float((r.target[-1] - r.target[0]) @ AXIS + (r.target[0] - np.array([45.0, 32.0])) @ AXIS))
    assert drag[0] < drag[1] < drag[2] and drag[0] > 0


def test_halving_the_step_changes_the_final_target_little(model):
    """docs/model.md §12 reports the measured difference (0.5 vs 1 mm steps)."""
    cfg, tissue = model
    coarse = _insert(tissue, _params(cfg, step_mm=1.0))
    fine = _insert(tissue, _params(cfg, step_mm=0.5))
    moved = np.linalg.norm(coarse.target[-1] - np.array([45.0, 32.0]))
    assert moved > 0.1
    assert np.linalg.norm(coarse.target[-1] - fine.target[-1]) <= 0.25 * moved


def test_strategies_depth_and_loop_stop_at_the_target(model):
    cfg, tissue = model
    params = _params(cfg)
    # a target 1 mm off the axis: only the loop corrects the miss
    none = _insert(tissue, params, "none", target=(30.0, 33.0), depth=30.0, cfg=cfg)
    depth = _insert(tissue, params, "depth", target=(30.0, 33.0), depth=30.0, cfg=cfg)
    loop = _insert(tissue, params, "loop", target=(30.0, 33.0), depth=30.0, cfg=cfg)
    for r in (none, depth, loop):
        _finite(r)
        assert r.completed
    assert abs(depth.depth_error_mm) < abs(none.depth_error_mm)
    assert abs(loop.depth_error_mm) < 0.5
    assert loop.miss_mm < 0.5 * depth.miss_mm


def test_an_oblique_needle_keeps_each_captured_node_across_the_axis(model):
    cfg, tissue = model
    a = np.deg2rad(20.0)
    axis = np.array([np.cos(a), np.sin(a)])
    state = NeedleState(np.array([0.0, 20.0]), axis)
    x, params = tissue.rest.copy(), _params(cfg)
    for _ in range(15):
        x = advance(tissue, state, x, np.zeros(tissue.n_cups), 1.0, params, free_nodes(tissue)).x
    offsets = (x[state.captured] - state.entry) @ state.across
    np.testing.assert_allclose(offsets, state.offset, atol=1e-9)
    assert np.any(~state.stuck) and state.captured.size >= 3


def test_hard_ten_times_friction(model):
    cfg, tissue = model
    r = _insert(tissue, _params(cfg, friction_static_mN_per_mm=150.0, friction_kinetic_mN_per_mm=100.0))
    _finite(r)
    assert r.completed or r.stop_reason


def test_hard_stiff_obstacle_beside_the_path(tmp_path):
    obstacles = [{"name": "rib", "circle": {"center_mm": [25.0, 35.0], "radius_mm": 2.0}, "stiffness_factor": 20.0}]
    cfg, tissue = _tissue(tmp_path, obstacles=obstacles)
    r = _insert(tissue, _params(cfg))
    _finite(r)
    assert r.completed and r.has_obstacles
    assert r.min_clearance_mm.min() > 0 and not r.obstacle_touched
    touching = _insert(tissue, _params(cfg), entry=np.array([0.0, 34.0]))
    _finite(touching)
    assert touching.obstacle_touched or not touching.completed


def test_hard_entry_at_a_cups_edge(model):
    cfg, tissue = model
    cup = tissue.scene.cups[0]
    entry = cup.contact + np.array([cup.radius_mm + 0.2, 0.0])  # just beside the grip, going down
    r = _insert(tissue, _params(cfg), entry=entry, axis=np.array([0.0, -1.0]), depth=20.0, target=entry + [0, -20])
    _finite(r)
    assert r.completed or r.stop_reason


@pytest.mark.parametrize("field, value, words", [
    ("friction_static_mN_per_mm", -1.0, "must be"),
    ("tip_force_mN", -5.0, "must be"),
    ("friction_kinetic_mN_per_mm", 20.0, "exceeds the static"),
    ("step_mm", 0.0, "must be"),
    ("step_mm", 150.0, "longer than the tissue"),
])
def test_bad_insertion_input_exits_2_with_one_message(tmp_path, field, value, words):
    from scissor_cli import cli

    data = example_dict()
    data["insertion"] = dict(INSERTION, **{field: value})
    path = write_scene(tmp_path, data)
    result = CliRunner().invoke(cli.app, ["validate", str(path)])
    assert result.exit_code == 2
    err = result.stderr.strip()
    assert err.count("\n") == 0 and f"insertion.{field}" in err and "line" in err and words in err


def test_a_long_step_is_split_not_restarted_from_rest(model):
    """A 5 mm step whose start would invert elements is split; it never loses the needle's hold."""
    cfg, tissue = model
    long = _insert(tissue, _params(cfg, step_mm=5.0))
    short = _insert(tissue, _params(cfg, step_mm=1.0))
    _finite(long)
    assert long.completed
    moved = np.linalg.norm(short.target[-1] - np.array([45.0, 32.0]))
    assert np.linalg.norm(long.target[-1] - short.target[-1]) <= 0.25 * moved


def test_simulate_and_report_with_insertion(tmp_path):
    """The contract paths, finite values, the printed miss per strategy, the figures and the report."""
    import h5py

    from scissor_cli import cli

    data = example_dict()
    data["tissue"]["mesh"].update(max_edge_mm=8.0, min_edge_mm=2.5)
    data["insertion"] = dict(INSERTION, step_mm=2.0, strategies=["none", "depth"])
    data["trials"] = {"count": 1, "profile": "prosthesis"}
    data.pop("forward", None)
    path = write_scene(tmp_path, data)
    out = tmp_path / "run"
    result = CliRunner().invoke(cli.app, ["simulate", str(path), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "insertion T1: miss none" in result.output and "depth" in result.output
    with h5py.File(out / "results.h5") as f:
        for s in ("none", "depth"):
            g = f[f"insertion/T1/{s}"]
            k = int(g.attrs["steps"])
            assert k > 0 and g["depth_mm"].shape == (k,) and g["tip"].shape == (k, 2)
            assert g["displacement"].shape[0] == k and g["displacement"].compression == "gzip"
            assert g["stuck"].dtype == np.int64 and g.attrs["entry"].shape == (2,)
            for key in ("miss_mm", "depth_error_mm", "time_s"):
                assert np.isfinite(g.attrs[key])
        assert f["trials/T1/miss_mm"].shape == (1, 2)
        assert list(f["trials/T1/miss_mm"].attrs["strategies"]) == ["none", "depth"]
        # the whole trial's wall time holds the insertions beside the loop's own
        assert f["trials/T1/trial_time_s"][0] > f["trials/T1/time_s"][0] > 0.0
    for name in ("insertion_force_T1.png", "insertion_path_T1.png"):
        assert_png_drawn(out / name)
    assert (out / "insertion_T1.gif").stat().st_size > 1000
    rep = CliRunner().invoke(cli.app, ["report", str(out), "--out", str(tmp_path / "rep")])
    assert rep.exit_code == 0, rep.output
    # one trial: each box is its orange median line alone
    assert_png_drawn(tmp_path / "rep" / "insertion_boxplots.png", min_colour=0.0005)
    assert "miss (depth)" in (tmp_path / "rep" / "insertion_summary.md").read_text()


# -- the kept factorisation of the needle's solves (insertion/chord.py) -------------------------------------------


def _a_hold(tissue, cfg, depth=12.0):
    """An insertion 12 mm deep, then a hold with some nodes stuck (ridden 0.3 mm further) and the others slipping."""
    from scissor_cli.insertion.chord import Hold

    state = NeedleState(ENTRY, AXIS)
    x, params = tissue.rest.copy(), _params(cfg)
    while state.depth_mm < depth - 1e-9:
        x = advance(tissue, state, x, np.zeros(tissue.n_cups), 1.0, params, free_nodes(tissue)).x
    p = state.captured.size
    stuck = np.arange(p) % 2 == 0
    hold = Hold(state.captured, x[state.captured], stuck, np.full(p, 0.3), state.direction, state.across)
    loads = np.zeros(x.size)
    loads[2 * state.captured[~stuck]] = 5.0  # a kinetic pull along +x on the slipping ones
    return x, hold, loads


def test_the_chord_holds_residual_is_newtons(model):
    from scissor_cli.solvers.common import objective_gradient
    from scissor_cli.solvers.newton import _Held

    cfg, tissue = model
    x, hold, loads = _a_hold(tissue, cfg)
    x = hold.place(x) + 0.01 * np.sin(np.arange(x.size)).reshape(x.shape)  # off equilibrium
    _, g = objective_gradient(tissue, x, None, loads)
    assert hold.residual(tissue, g) == pytest.approx(_Held(tissue, hold.conditions(loads)).residual(tissue, g),
                                                     rel=1e-12)


def test_a_schur_chord_step_meets_the_hold_and_the_tangent_equations(model):
    """d from the kept columns: C d = r exactly and K d + Cᵀμ = −g on the free dofs, K the factored tangent."""
    from scissor_cli.insertion.chord import ChordSolver
    from scissor_cli.solvers.common import objective_gradient

    cfg, tissue = model
    x, hold, loads = _a_hold(tissue, cfg)
    solver = ChordSolver(tissue)
    solver.refactor(x)
    _, g = objective_gradient(tissue, x, None, loads)
    d, mu = solver.step(g, hold, x)
    np.testing.assert_allclose(hold.gap(x + d), 0.0, atol=1e-10)
    force = np.zeros(x.size)  # Cᵀμ on the (x, y) dofs
    D = hold.directions()
    assert D.shape == (2 * hold.captured.size, hold.captured.size + hold.stuck.sum())
    force[2 * hold.captured] += D[0::2] @ mu
    force[2 * hold.captured + 1] += D[1::2] @ mu
    K = tissue.stiffness_free(x)
    f = tissue.free_dofs
    lhs = K @ d.ravel()[f] + force[f]
    np.testing.assert_allclose(lhs, -g[f], atol=1e-10 * np.abs(g[f]).max())


def test_the_compiled_hold_loops_equal_their_numpy_definitions(model):
    """Residual, gap, frame compliance, the captured step, the predicted reactions and the trial against plain numpy."""
    from scissor_cli.insertion import kernels
    from scissor_cli.insertion.chord import ChordSolver
    from scissor_cli.solvers.common import objective_gradient

    cfg, tissue = model
    x, hold, loads = _a_hold(tissue, cfg)
    solver = ChordSolver(tissue)
    solver.refactor(x)
    y = x + 0.01 * np.sin(np.arange(x.size)).reshape(x.shape)  # off equilibrium, the rows not met
    _, g = objective_gradient(tissue, y, None, loads)
    assert hold.held_residual(solver, g) == pytest.approx(hold.residual(tissue, g), rel=1e-12)
    gap = np.empty(hold.rows.size)
    largest = hold.gap_into(y, gap)
    np.testing.assert_allclose(gap, hold.gap(y), rtol=0, atol=1e-14)
    assert largest == np.abs(gap).max() > 0
    # the compliance in the (t, n) frame: Qᵀ (K⁻¹)[idx, idx] Q, Q = I ⊗ [t n]
    idx, A = solver.compliance(hold.captured, hold.frame)
    f = tissue.free_dofs
    K_inv = np.linalg.inv(tissue.stiffness_free(x).toarray())
    Q = np.kron(np.eye(hold.captured.size), hold.frame)
    np.testing.assert_allclose(A, Q.T @ K_inv[np.ix_(idx, idx)] @ Q, atol=1e-12 * np.abs(A).max())
    # μ and the captured step from the Schur complement written with the rows' directions D
    d0, mu, d_captured = solver.predict(g[f], hold, hold.gap(y))
    D = hold.directions()
    W = K_inv[np.ix_(idx, idx)]
    mu_dense = np.linalg.solve(D.T @ W @ D, D.T @ d0[idx] - hold.gap(y))
    np.testing.assert_allclose(mu, mu_dense, rtol=1e-9, atol=1e-12 * np.abs(mu_dense).max())
    np.testing.assert_allclose(d_captured.ravel(), d0[idx] - W @ D @ mu_dense, atol=1e-10)
    np.testing.assert_allclose(solver.complete(d0, mu, d_captured, hold), d0 - K_inv[:, idx] @ D @ mu_dense, atol=1e-10)
    # what an early decision reads: the stuck nodes' reactions (−μ of their along rows) and every node's lag
    axial, lag = np.empty(hold.captured.size), np.empty(hold.captured.size)
    kernels.predicted_reactions(mu, hold.stuck, d_captured, y, hold.captured, hold.base, hold.n, hold.ride, axial, lag)
    expected = np.zeros(hold.captured.size)
    expected[hold.stuck] = -mu[hold.captured.size:]
    np.testing.assert_array_equal(axial, expected)
    np.testing.assert_allclose(lag, (y[hold.captured] + d_captured - hold.base) @ hold.n - hold.ride, atol=1e-13)
    trial, finite = kernels.moved(y, f, d0)
    expect = y.ravel().copy()
    expect[f] += d0
    assert finite and np.array_equal(trial.ravel(), expect)
    assert not kernels.moved(y, f, np.where(np.arange(f.size) == 3, np.nan, d0))[1]


@given(st.integers(0, 2**32 - 1), st.floats(0.0, 2.0), st.floats(0.0, 0.5))
@settings(max_examples=200, deadline=None)
def test_the_compiled_friction_rule_is_the_rule(seed, force_error, position_error):
    from scissor_cli.insertion import kernels

    rng = np.random.default_rng(seed)
    p = int(rng.integers(0, 12))
    axial, lag = rng.normal(0, 5, p), rng.normal(0, 0.3, p)
    limit, sign = rng.uniform(0, 6, p), rng.choice([-1.0, 1.0], p)
    stuck, locked = rng.random(p) < 0.6, rng.random(p) < 0.2
    free, slip = stuck & ~locked, ~stuck
    release, against = np.empty(p, bool), np.empty(p, bool)
    changed = kernels.friction_rule(axial, lag, limit, free, slip, sign, 1e-6, force_error, position_error,
                                    release, against)
    np.testing.assert_array_equal(release, free & (np.abs(axial) > limit))
    np.testing.assert_array_equal(against, slip & (sign * lag > 1e-6))
    unclear = bool(np.any(free & (np.abs(np.abs(axial) - limit) <= force_error))
                   or np.any(slip & (np.abs(sign * lag - 1e-6) <= position_error)))
    assert changed == (-1 if unclear else int(np.sum(release | against)))


def test_the_kept_factorisation_and_a_fresh_newton_reach_the_same_equilibrium(model):
    """A chord solve on a factorisation from elsewhere (an older state) equals Newton's with the same hold to 1e-10."""
    from scissor_cli.insertion.chord import ChordSolver
    from scissor_cli.solvers.common import objective_gradient
    from scissor_cli.solvers.equilibrium import solve_equilibrium

    cfg, tissue = model
    x, hold, loads = _a_hold(tissue, cfg)
    start = hold.place(x)
    solver = ChordSolver(tissue)
    solver.refactor(tissue.rest)  # stale on purpose: the rest state's tangent
    _, g = objective_gradient(tissue, start, None, loads)
    chord_x, chord_g, its, verdict = solver.converge(start, g, hold, 1e-11, loads)
    assert verdict is None and its > 0
    newton = solve_equilibrium(tissue, np.zeros(tissue.n_cups), start=start, start_strokes=np.zeros(tissue.n_cups),
                               conditions=hold.conditions(loads), tol=1e-11)
    assert hold.residual(tissue, chord_g) <= 1e-11
    np.testing.assert_allclose(chord_x, newton.x, atol=1e-10)
    assert solver.factorizations >= 1


def test_a_step_on_the_kept_factorisation_matches_newton_passes(model, monkeypatch):
    """The same insertion with the chord solver and with every pass solved by Newton: same stick/slip, same
    positions."""
    from scissor_cli.insertion import chord, needle
    from scissor_cli.insertion.chord import ChordFailed

    cfg, tissue = model
    params = _params(cfg)
    fast = _insert(tissue, params, depth=15.0)

    def no_chord(self, *args, **kw):
        raise ChordFailed("test: Newton for every pass")

    monkeypatch.setattr(chord.ChordSolver, "converge", no_chord)
    monkeypatch.setattr(needle, "EARLY_DECISIONS", False)
    slow = _insert(tissue, params, depth=15.0)
    np.testing.assert_array_equal(fast.stuck, slow.stuck)
    # each pass converged to PASS_TOL (1e-5 of the force scale) either way: positions agree to about that
    np.testing.assert_allclose(fast.x, slow.x, atol=1e-5)
    np.testing.assert_allclose(fast.needle_force_mN, slow.needle_force_mN, rtol=1e-6)


def test_the_nearly_incompressible_hard_case_decides_as_the_converged_passes(monkeypatch):
    """ν = 0.499, the example's needle and friction, 40 mm: early decisions give every step the stuck set the
    converged passes give. A pass there predicts lurches of 4.4 mm in a 0.5 mm step, outside the range the
    guards were measured in; deciding on that prediction once sent a step down another path (0.71 mm at the
    end), so no decision is taken on a lurch (`needle.LURCH_STEPS`)."""
    from scissor_cli.insertion import needle
    from scissor_cli.planning.needle_plan import plan_target

    from helpers import ROOT

    cfg = load_config(ROOT / "configs" / "hard" / "nearly_incompressible.yaml")
    ins = load_config(ROOT / "configs" / "example_3d.yaml").insertion
    scene, _, tissue = build_model(cfg)
    plan = plan_target(tissue, scene, scene.targets[0], cfg.needle)
    assert plan.feasible
    params = NeedleParams.from_config(ins, cfg.needle, cfg.tissue.mesh)
    x0 = solve_newton(tissue, plan.strokes, tol=1e-10).x
    candidates = free_nodes(tissue)

    def stuck_counts(early_decisions):
        monkeypatch.setattr(needle, "EARLY_DECISIONS", early_decisions)
        state, x = NeedleState(plan.entry, plan.direction), x0.copy()
        counts = []
        while state.depth_mm < 40.0 - 1e-9:
            out = advance(tissue, state, x, plan.strokes, ins.step_mm, params, candidates)
            x = out.x
            counts.append(out.stuck)
        return np.array(counts), x

    fast, x_fast = stuck_counts(True)
    exact, x_exact = stuck_counts(False)
    np.testing.assert_array_equal(fast, exact)
    np.testing.assert_allclose(x_fast, x_exact, atol=1e-3)


# -- the loop strategy's controller model (insertion/model_state.py) --------------------------------------------


def _truth(tissue, E_scale=1.3, fiber_offset_deg=10.0):
    """A "true" tissue that differs from the model: stiffer, fibers turned."""
    m = tissue.scene.material
    return tissue.with_material(E_scale, None, None, m.fiber_angle_rad + np.deg2rad(fiber_offset_deg))


def _old_loop(monkeypatch):
    """The loop as it was before the model state: J from the plant's tangent predictor per cup (with its
    residual), the plant's correction by Newton."""
    from scissor_cli.insertion import model_state, run
    from scissor_cli.insertion.needle import STEP_TOL, needle_conditions
    from scissor_cli.mesh.probe import target_positions
    from scissor_cli.solvers.equilibrium import solve_equilibrium
    from scissor_cli.solvers.newton import tangent_predictor

    def jacobian(self, state, probe, kept=None):
        x, s = self.x, self.strokes
        cond = needle_conditions(state, self.loads)
        y = target_positions(probe, x)[0]
        J = np.zeros((1, s.size))
        for c in range(s.size):
            moved = tangent_predictor(self.tissue, x, s + np.eye(s.size)[c], conditions=cond)
            J[0, c] = (target_positions(probe, moved)[0] - y) @ state.across
        return J, np.zeros((s.size,) + x.shape)

    follow = model_state.ModelState.follow

    def keep_loads(self, state, x, s, loads):
        self.loads = loads
        follow(self, state, x, s, loads)

    def move(tissue, state, x, s, command, loads, responses):
        return solve_equilibrium(tissue, command, start=x, start_strokes=s, conditions=needle_conditions(state, loads),
                                 tol=STEP_TOL).x

    monkeypatch.setattr(model_state.ModelState, "jacobian", jacobian)
    monkeypatch.setattr(model_state.ModelState, "follow", keep_loads)
    monkeypatch.setattr(run, "_move_plant", move)


def test_loop_with_truth_equal_to_model_is_the_old_loop(model, monkeypatch):
    """The nominal run: the same insertion as with the plant's own tangent, to solver tolerance.

    Both are solved to STEP_TOL (a relative residual of 1e-5): on this 30 mm insertion they then differ by
    4e-6 mm in the nodes and 1.3e-5 mm in the stroke (solved to 1e-8: 6e-9 and 1.2e-8), so the
    comparison is to 5e-5 mm.
    """
    target = (30.0, 33.0)
    cfg, tissue = model
    params = _params(cfg)
    new = _insert(tissue, params, "loop", target=target, depth=30.0, cfg=cfg)
    with monkeypatch.context() as m:
        _old_loop(m)
        old = _insert(tissue, params, "loop", target=target, depth=30.0, cfg=cfg)
    assert new.steps == old.steps and new.stop_reason == old.stop_reason
    np.testing.assert_allclose(new.x, old.x, rtol=0, atol=5e-5)
    np.testing.assert_allclose(new.strokes, old.strokes, rtol=0, atol=5e-5)
    assert new.miss_mm == pytest.approx(old.miss_mm, abs=5e-5)
    assert np.any(np.abs(new.strokes) > 0.05)  # the loop did move the cup


def _model_state_mid_insertion(tissue, cfg, truth, depth=12.0):
    """The truth inserted `depth` mm at a 3 mm stroke, the controller's model following it every step."""
    from scissor_cli.insertion.model_state import ModelState
    from scissor_cli.solvers.equilibrium import solve_equilibrium

    s = np.array([3.0])
    x = solve_equilibrium(truth, s).x
    ms = ModelState(tissue, truth, solve_equilibrium(tissue, s).x, x, s)
    state, params = NeedleState(ENTRY, AXIS), _params(cfg)
    while state.depth_mm < depth - 1e-9:
        out = advance(truth, state, x, s, 1.0, params, free_nodes(truth))
        x = out.x
        ms.follow(state, x, s, out.loads)
    return ms, state, out.loads, s


def test_the_model_jacobian_is_the_model_held_response(model):
    """J from the model state equals central differences of full held solves of the model, and is not the truth's."""
    from scissor_cli.insertion.model_state import ModelState
    from scissor_cli.insertion.needle import needle_conditions
    from scissor_cli.mesh.probe import probe_targets, target_positions
    from scissor_cli.solvers.equilibrium import solve_equilibrium

    cfg, tissue = model
    truth = _truth(tissue)
    ms, state, loads, s = _model_state_mid_insertion(tissue, cfg, truth)
    probe = probe_targets(tissue.mesh, np.array([[30.0, 33.0]]))
    J, responses = ms.jacobian(state, probe)
    cond = needle_conditions(state, loads)
    # the model state is the model's equilibrium under the needle's hold (nothing moves when solved again)
    again = solve_equilibrium(tissue, s, start=ms.x, start_strokes=s, conditions=cond, tol=1e-10).x
    assert np.abs(again - ms.x).max() <= 1e-5  # (the model state is solved to STEP_TOL, 1e-5 of the force scale)
    delta = 1e-3
    ends = [target_positions(probe, solve_equilibrium(tissue, s + sign * delta, start=ms.x, start_strokes=s,
                                                      conditions=cond, tol=1e-12).x)[0] @ state.across
            for sign in (1.0, -1.0)]
    fd = (ends[0] - ends[1]) / (2 * delta)
    assert J[0, 0] == pytest.approx(fd, rel=1e-5)
    assert responses.shape == (1,) + ms.x.shape and np.all(np.isfinite(responses))
    # a target the needle holds has J exactly 0 across the axis (round-off would send the loop's step to the limit)
    held = state.captured[0]
    on_shaft = probe_targets(tissue.mesh, tissue.rest[held][None])
    assert ms.jacobian(state, on_shaft)[0][0, 0] == 0.0
    # the truth's own J at its state differs: the controller does not know it
    plant = ModelState(truth, truth, ms._x_plant, ms._x_plant, s)
    J_truth, _ = plant.jacobian(state, probe, state.solver)
    assert abs(J_truth[0, 0] - J[0, 0]) > 1e-3 * abs(J[0, 0])


def test_loop_on_a_mismatched_truth_still_corrects_the_miss(model):
    """The model's J (E ×1.3 and fibers +10° in the truth): the closed loop still ends with a small miss."""
    cfg, tissue = model
    truth = _truth(tissue)
    params = _params(cfg)
    x0, s0 = truth.rest.copy(), np.zeros(truth.n_cups)
    runs = {strategy: run_insertion(truth, x0, s0, NeedlePath(ENTRY, AXIS, 30.0, np.array([30.0, 33.0])), params,
                                    InsertionOptions(strategy, cfg.controller, model=tissue))
            for strategy in ("none", "loop")}
    for r in runs.values():
        _finite(r)
        assert r.completed
    # measured: none 1.021 mm, depth 0.978 mm, loop 0.0014 mm (0.0016 mm with the truth's own J, the old shortcut)
    assert runs["loop"].miss_mm < 0.05 < runs["none"].miss_mm
    assert runs["loop"].miss_mm < 0.1 * runs["none"].miss_mm


@pytest.mark.slow  # (every strategy in a run's trials: tests/test_layer_check.py's slab-truth run; the layer's
# none and depth: test_simulate_and_report_with_insertion; loop against the layer model: the tests above)
def test_trials_insert_every_strategy_with_a_finite_miss(tmp_path):
    """Trials (truth drawn ≠ model) insert under none, depth and loop: finite misses, nothing failed."""
    import h5py

    from scissor_cli import cli

    data = example_dict()
    data["tissue"]["mesh"].update(max_edge_mm=8.0, min_edge_mm=2.5)
    data["insertion"] = dict(INSERTION, step_mm=2.0)
    data["trials"] = {"count": 2, "profile": "ex_vivo"}
    data.pop("forward", None)
    out = tmp_path / "run"
    result = CliRunner().invoke(cli.app, ["simulate", str(write_scene(tmp_path, data)), "--out", str(out)])
    assert result.exit_code == 0, result.output
    with h5py.File(out / "results.h5") as f:
        for t in f["trials"]:
            miss = f[f"trials/{t}/miss_mm"][...]
            assert miss.shape == (2, 3) and np.all(np.isfinite(miss))
            assert list(f[f"trials/{t}/miss_mm"].attrs["strategies"]) == ["none", "depth", "loop"]
            assert not np.any(f[f"trials/{t}/failed"][...])


class _Bars:
    """A reporter that records each progress bar: its total and what it was advanced by."""

    def __init__(self):
        self.bars = []

    def info(self, message):
        pass

    def progress(self, description, total):
        bar = [description, total, 0]
        self.bars.append(bar)

        def advance(n=1):
            bar[2] += n

        return advance


def test_an_insertion_shows_its_progress_and_ends_its_bar(model):
    """The insertion stage's bar advances after every step and ends at its total whether the insertion took
    fewer steps than planned (`depth` stops at the target) or more (a bar must end before the next starts);
    `none` and `depth` share their steps, so their needle counts once."""
    from types import SimpleNamespace

    from scissor_cli.experiments.insertion_stage import _insert as insert_with_bar

    cfg, tissue = model
    params = _params(cfg)
    target = SimpleNamespace(name="T1", rest=np.array([45.0, 32.0]))
    steps = {}
    # the target lies 45 mm in: `depth` planned 25 mm takes more steps than planned, planned 50 mm fewer
    for strategies, depth in ((("none",), DEPTH), (("depth",), DEPTH), (("depth",), 2 * DEPTH),
                              (("none", "depth", "loop"), DEPTH)):
        bars = _Bars()
        path = NeedlePath(ENTRY, AXIS, depth, target.rest, target.name)
        with progress.reporting(bars):
            results = insert_with_bar(tissue, tissue.rest.copy(), np.zeros(tissue.n_cups),
                                      dict.fromkeys(strategies, path), params,
                                      {k: InsertionOptions(k, cfg.controller) for k in strategies})
        [(label, total, advanced)] = bars.bars
        needles = 2 if "loop" in strategies else 1
        assert label == f"insertion T1 ({', '.join(strategies)})"
        assert total == needles * int(np.ceil(depth / params.step_mm)) and advanced == total
        assert [r.strategy for r in results] == list(strategies)
        steps[strategies, depth] = (results[0].steps, total)
    assert steps[("none",), DEPTH][0] == steps[("none",), DEPTH][1]
    assert steps[("depth",), DEPTH][0] > steps[("depth",), DEPTH][1]
    assert steps[("depth",), 2 * DEPTH][0] < steps[("depth",), 2 * DEPTH][1]
