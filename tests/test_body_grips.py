"""Where the cups grip a body (docs/model.md §20, "Where to grip"): candidates on the skin, their response by adjoint
solves against full solves, the choice of one, two or three cups, and a run whose chosen grips put every lesion on
its needle."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import yaml

from scissor_cli.config.loading import parse_config
from scissor_cli.experiments.build import body_model
from scissor_cli.mesh.probe import target_positions
from scissor_cli.planning import body_grips as bg
from scissor_cli.planning.manipulation_points import adjoint_responses
from scissor_cli.solvers.common import Conditions
from scissor_cli.solvers.equilibrium import solve_equilibrium

from helpers import simulate_here, write_scene
from test_body_loop import SCENE, _true_miss
from test_cli import run_cli

#: the skin above the +y side of the test dome (radius 40, height 25 mm)
REGION = {"center_mm": [0.0, 30.0, 15.0], "radius_mm": 22.0}


def _scene(**mp) -> dict:
    """The loop's dome with grips to choose; its cups stroke ±10 mm (the loop's ±6 mm does not take T1 to its needle
    from every grip in the region on the element that does not lock: `p1`'s locking overstated a cup's reach)."""
    cups = [dict(c, stroke_mm=[-10.0, 10.0]) for c in SCENE["cups"]]
    return dict(SCENE, cups=cups, manipulation_points={"skin": REGION, "spacing_mm": 4.0, "cups": 2, **mp})


@pytest.fixture(scope="module")
def body():
    cfg = parse_config(yaml.safe_dump(dict(_scene(), trials={"count": 0})), "<test>")
    return cfg, body_model(cfg)[2]


def test_candidates_are_skin_nodes_inside_the_region_pushing_inward(body):
    _, tissue = body
    c = bg.skin_candidates(tissue, REGION["center_mm"], REGION["radius_mm"], 4.0, 5.0)
    assert len(c) >= 10
    assert np.all(np.abs(tissue.scene.surface.depth(c.points)) < 0.05)  # on the skin
    assert np.all(np.linalg.norm(c.points - REGION["center_mm"], axis=1) <= REGION["radius_mm"])
    assert np.all(c.points[:, 2] > 5.0)  # a cup's radius above the held base
    outward = c.points / np.array([40.0, 40.0, 25.0]) ** 2  # the dome's outward normal, up to length
    assert np.all(np.einsum("ij,ij->i", c.normals, outward) < 0)
    np.testing.assert_allclose(np.linalg.norm(c.normals, axis=1), 1.0)
    F = bg.skin_forces(tissue, c, 5.0)
    np.testing.assert_allclose(F.reshape(-1, 3, len(c)).sum(axis=0), c.normals.T, atol=1e-12)  # 1 mN each


def test_adjoint_responses_on_the_body_equal_finite_differences_of_full_solves(body):
    _, tissue = body
    free = bg.released_body(tissue)
    assert free.n_cups == 0
    c = bg.skin_candidates(free, REGION["center_mm"], REGION["radius_mm"], 8.0, 5.0)
    F = bg.skin_forces(free, c, 5.0)
    probe = free.probe(np.array([t.rest for t in free.scene.targets]))
    R, u, _ = adjoint_responses(free, free.rest, probe, F)
    assert R.shape == (2, len(c), 3) and np.all(u > 0)
    eps = 0.5  # mN: small enough to stay linear
    for k in (0, len(c) - 1):
        x = [solve_equilibrium(free, np.zeros(0), conditions=Conditions(loads=s * eps * F[:, k]), tol=1e-10).x
             for s in (1.0, -1.0)]
        fd = (target_positions(probe, x[0]) - target_positions(probe, x[1])) / (2 * eps)
        np.testing.assert_allclose(R[:, k], fd, rtol=1e-3, atol=1e-6 * np.abs(R).max())


def test_two_cups_span_the_miss_and_three_the_position():
    # four candidates far apart; per lesion the responses (T, m, P): 0 and 1 parallel, 2 across, 3 out of the plane
    G = np.array([[[1.0, 0.0, 0.0], [0.9, 0.0, 0.0], [0.0, 0.8, 0.0], [0.1, 0.1, 0.7]]])  # (T=1, P, 3)
    points = np.arange(4.0)[:, None] * np.array([[20.0, 0.0, 0.0]])
    chosen, score = bg.choose(np.transpose(G, (0, 2, 1)), points, 3, 10.0, 3)
    assert sorted(chosen) == [0, 2, 3] and score > 0.5
    across = np.transpose(G[:, :, :2], (0, 2, 1))  # the miss across a needle along z: x and y
    chosen, _ = bg.choose(across, points, 2, 10.0, 2)
    assert sorted(chosen) == [0, 2]  # not the parallel pair
    chosen, _ = bg.choose(across, points, 1, 10.0, 1)
    assert list(chosen) == [0]
    with pytest.raises(ValueError, match="two cup radii"):
        bg.choose(across, points, 2, 100.0, 2)  # no two candidates far enough apart


def test_grips_chosen_on_the_skin_put_every_lesion_on_its_needle(tmp_path):
    with h5py.File(simulate_here(tmp_path, _scene()) / "results.h5", "r") as f:
        mp = f["manipulation_points"].attrs
        chosen = mp["chosen"]
        assert chosen.shape == (2, 3)
        on = parse_config(f.attrs["config_yaml"], "<run>")
        assert on.manipulation_points is None  # the run went on with the chosen grips, recorded as its cups
        np.testing.assert_allclose([c.contact_mm for c in on.cups], chosen)
        assert np.all(np.linalg.norm(chosen - REGION["center_mm"], axis=1) <= REGION["radius_mm"])
        assert np.linalg.norm(chosen[0] - chosen[1]) >= 10.0
        for t in ("T1", "T2"):
            table = f[f"manipulation_points/{t}"]
            predicted, verified = table.attrs["predicted"], table.attrs["verified"]
            cosine = np.einsum("ij,ij->i", predicted, verified) / (
                np.linalg.norm(predicted, axis=1) * np.linalg.norm(verified, axis=1))
            assert np.all(cosine > 0.9)  # the adjoint predicts where each cup moves the lesion
            direction = f[f"plan/{t}"].attrs["direction"]
            # the loop ends when the part of the miss the cups can correct is within its tolerance (0.1 mm); grips
            # chosen for the miss across the needle span it, so what they cannot correct stays small
            trial = f[f"trials/{t}"]
            assert list(trial["stop_reason"][()]) == [b"tolerance"]
            assert trial["correctable_mm"][()].max() <= 0.1 and trial["uncorrectable_mm"][()].max() <= 0.02
            assert _true_miss(trial["final_error"][()], direction).max() <= np.hypot(0.1, 0.02)
        assert (tmp_path / "run" / "manipulation_points.png").is_file()


@pytest.mark.parametrize("change, field", [
    ({"cups": 3}, "manipulation_points.cups"),
    ({"skin": {"center_mm": [0.0, 0.0, 90.0], "radius_mm": 5.0}}, "manipulation_points.skin"),
    ({"spacing_mm": 0.0}, "manipulation_points.spacing_mm"),
    ({"sides": ["top"]}, "manipulation_points"),
])
def test_bad_manipulation_points_on_a_body_exit_2(tmp_path, change, field):
    r = run_cli("validate", write_scene(tmp_path, _scene(**change)))
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert field in r.stderr
