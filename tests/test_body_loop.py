"""A 3-D scene's closed loop (docs/model.md §19, "Plan", "Sensing", "Control", "Trials"): the needle planned past a
vessel, each lesion moved across it onto the needle's line by two cups under triangulating cameras, and trials.

The scene: a dome (radius 40, height 25 mm), two lesions, each to be moved across its horizontal needle in
y and z to where the cups can put it (the miss has two components: two cups, seen by two cameras), a vessel beside
T1's path, two cups on the skin; coarse (its edges grow twice as fast away from the lesions, vessel and cups
as a body's default `tissue.mesh.grading`), so a run takes seconds. The planner's search for a move that clears
a blocked line is tested in tests/test_body_plan.py.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from helpers import simulate_here

SCENE = {
    "name": "loop-dome",
    "seed": 5,
    "tissue": {"shape": "dome", "radius_mm": 40.0, "height_mm": 25.0, "fixed": ["base"],
               "mesh": {"max_edge_mm": 8.0, "min_edge_mm": 3.0, "grading": 0.8}},
    "material": {"model": "neo_hookean_fiber", "E_kPa": 10.0, "nu": 0.45, "eta_kPa": 5.0, "fiber_angle_deg": 30.0},
    "cups": [
        {"name": "side", "contact_mm": [0.0, 38.5, 8.0], "radius_mm": 5.0, "stroke_mm": [-6.0, 6.0]},
        {"name": "front", "contact_mm": [-38.5, 0.0, 8.0], "radius_mm": 5.0, "stroke_mm": [-6.0, 6.0]},
    ],
    "targets": [
        {"name": "T1", "position_mm": [5.0, 10.0, 10.0], "radius_mm": 3.0, "desired_mm": [5.0, 9.55, 10.09]},
        {"name": "T2", "position_mm": [-8.0, -6.0, 8.0], "radius_mm": 3.0, "desired_mm": [-8.0, -5.92, 8.05]},
    ],
    "obstacles": [{"name": "vessel", "tube": {"points_mm": [[12.0, 14.0, 10.0], [30.0, 14.0, 10.0]], "radius_mm": 1.5},
                   "stiffness_factor": 3.0}],
    "needle": {"direction": [-1.0, 0.0, 0.0], "margin_mm": 1.0},
    "solver": {"kind": "newton"},
    "robot": {"layer_origin_mm": [100.0, 215.0, 200.0]},
    "cameras": [{"position_mm": [0.0, 0.0, 400.0]}, {"position_mm": [0.0, -400.0, 12.0], "look_at_mm": [0, 0, 12]}],
    "trials": {"count": 1, "profile": "ideal"},
}


def _run(tmp_path, data, jobs=1):
    """The scene's run (`simulate_here`: through the API in this process), its results.h5 open."""
    return h5py.File(simulate_here(tmp_path, data, jobs=jobs) / "results.h5", "r")


#: the scene with one forward case: the uninterrupted run the resume below is held to, and the run the two cameras'
#: checks read (one run for both)
WITH_FORWARD = {**SCENE, "forward": [{"name": "push3", "strokes": {"side": 3.0}}]}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """WITH_FORWARD's uninterrupted run, in this process: (its config, results.h5)."""
    from scissor_cli.config import load_config

    tmp = tmp_path_factory.mktemp("loop")
    out = simulate_here(tmp, WITH_FORWARD, name="ref")
    return load_config(tmp / "ref.yaml"), out / "results.h5"


def _true_miss(error: np.ndarray, direction: np.ndarray) -> np.ndarray:
    n = np.asarray(direction, float)
    return np.linalg.norm(np.atleast_2d(error) @ (np.eye(3) - np.outer(n, n)), axis=1)


def test_two_cameras_and_two_cups_put_every_lesion_on_its_needle(reference):
    with h5py.File(reference[1], "r") as f:
        for t in ("T1", "T2"):
            plan = f[f"plan/{t}"].attrs
            assert plan["feasible"] and plan["clearance_mm"] >= 0.0  # clear by the margin and the radii
            assert _true_miss(f[f"trials/{t}/final_error"][()], plan["direction"]).max() <= 0.1
            assert f[f"trials/{t}/manipulation_miss_mm"][0] <= 0.1
            history = f[f"trials/{t}/history/0"]
            columns = list(history.attrs["columns"])
            assert np.all(np.isfinite(history[()][:, columns.index("measured_z")]))  # triangulated: z seen
        # the loop moved T1 with both cups
        assert np.all(np.abs(f["trials/T1/history/0"][()][-1, 3:5]) > 1.0)
        assert f["/"].attrs["status"] == "complete"


def test_one_camera_above_does_not_see_depth_and_the_true_3d_error_is_kept(tmp_path):
    data = dict(SCENE, cameras=None, camera={"position_mm": [0.0, 0.0, 400.0]})
    data.pop("cameras")
    with _run(tmp_path, data) as f:
        history = f["trials/T2/history/0"]
        columns = list(history.attrs["columns"])
        table = history[()]
        assert np.all(np.isnan(table[:, columns.index("measured_z")]))
        assert np.all(np.isfinite(table[:, columns.index("measured_y")]))
        assert np.all(np.isfinite(table[:, [columns.index(c) for c in ("true_x", "true_y", "true_z")]]))
        error = f["trials/T2/final_error"][()]
        assert error.shape == (1, 3) and np.all(np.isfinite(error))


def test_on_two_workers_the_nominal_manipulations_run_beside_the_trials_to_the_same_numbers(reference, tmp_path,
                                                                                            monkeypatch):
    """With two local workers the nominal manipulations go to the trials' pool (`run_trial_stage`'s `nominal`) instead
    of the run's own process: every number stored is the one-process run's, to the last bit."""
    from scissor_cli.experiments import body_closed_loop

    from test_resume_stages import assert_same_run

    def not_here(*args, **kwargs):
        raise AssertionError("the run's own process solved the nominal manipulations")

    monkeypatch.setattr(body_closed_loop, "_manipulation_stage", not_here)
    _, ref = reference
    run = simulate_here(tmp_path, WITH_FORWARD, jobs=2)
    with h5py.File(run / "results.h5", "r") as h5:
        finished = set(h5.attrs["finished"].astype(str))
    assert {"manipulation/T1", "manipulation/T2", "trials"} <= finished
    assert_same_run(ref, run / "results.h5")


@pytest.mark.slow  # (the default run has the ideal trials above; these are the profile's, with two workers)
def test_prosthesis_trials_run_on_two_workers_none_failed(tmp_path):
    data = dict(SCENE, trials={"count": 4, "profile": "prosthesis"})
    with _run(tmp_path, data, jobs=2) as f:
        for t in ("T1", "T2"):
            assert f[f"trials/{t}/done"][()].all() and not f[f"trials/{t}/failed"][()].any()


def test_a_run_stopped_in_its_manipulations_resumes_to_the_uninterrupted_run(reference, tmp_path, monkeypatch):
    """Ctrl-C while T2's nominal manipulation is stored: `--resume` keeps the forward cases, the plans and T1's
    manipulation as stored and completes the run to the numbers of one that was never stopped."""
    from scissor_cli.experiments.simulate import Execution, resume_simulation, run_simulation
    from scissor_cli.output import results_sink as sink_module
    from scissor_cli.output.results_sink import RunDirectory, open_for_resume

    from test_resume_stages import assert_same_run, wall_times

    cfg, ref = reference
    real = sink_module.ResultsSink.manipulation

    def stopped(self, product, *args):
        if product.target == "T2":
            raise KeyboardInterrupt("SIGINT")
        return real(self, product, *args)

    monkeypatch.setattr(sink_module.ResultsSink, "manipulation", stopped)
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_simulation(cfg, RunDirectory(run), execution=Execution(jobs=1))
    monkeypatch.undo()
    with h5py.File(run / "results.h5", "r") as h5:
        finished = set(h5.attrs["finished"].astype(str))
    assert {"forward/push3", "jacobian", "plan", "manipulation/T1"} <= finished
    assert "manipulation/T2" not in finished and "trials" not in finished
    kept = wall_times(run / "results.h5", ["forward/push3"])
    with h5py.File(run / "results.h5", "r") as h5:
        plans_before = {k: dict(h5[f"plan/{k}"].attrs) for k in ("T1", "T2")}

    assert resume_simulation(open_for_resume(run), execution=Execution(jobs=1)) == 2  # 1 trial x 2 lesions
    assert wall_times(run / "results.h5", ["forward/push3"]) == kept
    with h5py.File(run / "results.h5", "r") as h5:
        assert h5.attrs["status"] == "complete"
        for k, attrs in plans_before.items():
            assert all(np.array_equal(np.asarray(h5[f"plan/{k}"].attrs[a]), np.asarray(v)) for a, v in attrs.items())
    assert_same_run(ref, run / "results.h5")
