"""The ultrasound as the loop's sensor (docs/ultrasound.md §6, docs/model.md §17).

One PSF (L11-5v, 70 mm) is measured on SIMUS for the module; the scene is
the example on a coarse mesh, the probe on its left side at (0, 30) mm
looking along +x. Checks: first-frame localisation and the closed loop's
miss with the ideal profile; the tracking error over a manipulation; the
time-of-flight law through the sensor; scatterers carried by a slab, and
out-of-plane motion decorrelating the speckle; determinism; a lost lesion
held and counted; reseeded copies; the camera without imaging; the
budget's rows and a trial end to end with imaging.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import yaml

from scissor_cli import control
from scissor_cli.config import TrialsConfig, parse_config, resolved_yaml
from scissor_cli.experiments.build import build_model
from scissor_cli.experiments.profiles import PROFILES, error_model
from scissor_cli.experiments.sensor_models import imaging_data, imaging_tables_for, sensor_model
from scissor_cli.sensing.sensor import TrialDraws, TrueState

from helpers import example_dict

IMAGING = {"probe": "L11-5v", "position_mm": [0.0, 30.0], "axis": [1.0, 0.0], "depth_mm": 70.0}
#: the needle's axis of the test loops: along x, so the loop drives the y error (lateral in the image)
ALONG_X = np.array([1.0, 0.0])


def scene_data(**trials) -> dict:
    data = example_dict()
    data["imaging"] = dict(IMAGING)
    data["tissue"]["mesh"].update(max_edge_mm=8.0, min_edge_mm=2.0)
    data["solver"]["kind"] = "newton"
    data["forward"] = data["forward"][:1]
    data["trials"] = {"count": 2, "profile": "ideal", **trials}
    return data


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    cfg = parse_config(yaml.safe_dump(scene_data()), "scene.yaml")
    scene, mesh, tissue = build_model(cfg)
    data = imaging_data(cfg.imaging, tmp_path_factory.mktemp("cache"))
    ideal = error_model(TrialsConfig(profile="ideal"))
    return cfg, scene, mesh, tissue, data, sensor_model(cfg, scene, ideal, data)


def at_rest(mesh, point, shift=(0.0, 0.0)) -> TrueState:
    d = np.asarray(shift, float)
    return TrueState(np.asarray(point, float) + d, mesh.nodes + d, mesh)


def test_the_run_tables_are_cached_and_shared(world, tmp_path):
    cfg, scene, mesh, tissue, data, model = world
    assert model.exact is False and model.tables is imaging_tables_for(cfg.imaging, data)
    cache = tmp_path / "cache"
    again = imaging_data(cfg.imaging, cache)
    assert len(list(cache.glob("ultrasound-psf-*.npz"))) == 1
    read = imaging_data(cfg.imaging, cache)  # from the file, the same arrays
    assert read["probe"] == again["probe"]
    assert all(np.array_equal(read["psf"][k], again["psf"][k]) for k in again["psf"])


def test_first_frame_localises_the_lesion(world):
    cfg, scene, mesh, tissue, data, model = world
    errors = []
    for k, target in enumerate(scene.targets):
        for seed in range(3):
            y = model.nominal(seed, k, target.rest).measure(at_rest(mesh, target.rest))
            errors.append(np.hypot(*(y - target.rest)))
    errors = np.array(errors)
    assert np.sqrt(np.mean(errors ** 2)) <= 0.15 and errors.max() <= 0.3, errors


@pytest.fixture(scope="module")
def nominal_loop(world):
    """The closed loop of T2 to 1.5 mm below its rest position, seen by the ideal ultrasound, every frame kept."""
    cfg, scene, mesh, tissue, data, model = world
    target = scene.targets[1]
    desired = np.asarray(target.rest) + np.array([0.0, -1.5])
    sensor = replace(model, full_frames=True).nominal(cfg.seed, 1, desired, record=True)
    run = control.TargetRun(target=target.name, sensor=sensor, direction=ALONG_X)
    return control.run_target(tissue, target.rest, desired, cfg.controller, run), sensor, desired


def test_the_loop_ends_within_reach_of_the_truth(nominal_loop, world):
    result, sensor, desired = nominal_loop
    cfg = world[0]
    assert result.stop_reason == "tolerance" and sensor.lost_frames == 0
    assert np.hypot(*(result.hist_measured[-1] - result.hist_true[-1])) <= 0.15
    assert result.miss_mm <= cfg.controller.tolerance_mm + 0.15
    # the history's measurements are the ultrasound's frames
    assert len(sensor.recorded.frames) == len(result.hist_measured) == sensor.frames
    assert np.array_equal(np.array(sensor.recorded.tracked), result.hist_measured)
    assert sensor.recorded.frames[0].shape == sensor.model.tables.grid.shape


def test_tracking_error_over_a_manipulation(nominal_loop):
    result, sensor, desired = nominal_loop
    tracked, true = np.array(sensor.recorded.tracked), np.array(sensor.recorded.true)
    assert np.hypot(*(true[-1] - true[0])) > 1.0  # the lesion moved
    displacement_error = np.hypot(*((tracked - tracked[0]) - (true - true[0])).T)
    assert np.percentile(displacement_error, 95) <= 0.1, displacement_error
    assert np.percentile(np.hypot(*(tracked - true).T), 95) <= 0.25


def test_time_of_flight_moves_the_lesion_along_the_beam(world):
    """Tissue at 1450 m/s imaged at 1540: the lesion shows depth x (1540/1450 - 1) deeper, on the same speckle."""
    cfg, scene, mesh, tissue, data, model = world
    target = scene.targets[0]
    slow = replace(model, sound_speed_m_per_s=1450.0).nominal(cfg.seed, 0, target.rest)
    matched = model.nominal(cfg.seed, 0, target.rest)
    state = at_rest(mesh, target.rest)
    y_slow = slow.measure(state)
    matched._scene = slow._scene  # the same scatterers (drawn for the deeper region)
    y_matched = matched.measure(state)
    depth = (np.asarray(target.rest) - np.asarray(cfg.imaging.position_mm)) @ ALONG_X
    shift = y_slow - y_matched
    assert shift @ ALONG_X == pytest.approx(depth * (1540.0 / 1450.0 - 1.0), abs=0.05)
    assert abs(shift[1]) <= 0.05


def _slab(scene, mesh):
    from scissor_cli.layer3d.slab import SlabSpec, build_slab

    return build_slab(scene, mesh, SlabSpec(12.0, 6.0, max_layer_mm=3.0))


def test_the_slab_carries_scatterers_and_out_of_plane_motion_decorrelates(world):
    from scissor_cli.sensing.ultrasound.scatterer_motion import carry_on

    cfg, scene, mesh, tissue, data, model = world
    slab = _slab(scene, mesh)
    target = scene.targets[0]
    sensor = model.nominal(cfg.seed, 0, target.rest)
    rest = TrueState(np.asarray(target.rest), slab.rest, slab.mesh)
    sensor.measure(rest)
    pos, elevation, _ = sensor._scene._draws[True]
    assert np.ptp(elevation) > 1.0 and np.abs(elevation).max() <= 6.0  # a band across the plane, inside the slab
    carried = carry_on(slab.mesh, pos, elevation)
    lat, dep, ele = carried.to_probe(slab.rest, sensor.true_pose)
    q = sensor.true_pose.to_probe(pos[carried.kept])
    assert np.allclose(np.column_stack([lat, dep]), q, atol=1e-9) and np.allclose(ele, elevation[carried.kept])
    moved = carried.to_probe(slab.rest + np.array([0.3, -0.2, 0.4]), sensor.true_pose)
    assert np.allclose(moved[2] - ele, 0.4) and np.allclose(moved[0] - lat, -0.2)  # lateral = layer y here

    g = sensor.grid
    shift = np.array([2 * g.dz_mm, -g.dx_mm, 0.0])  # whole pixels (depth along x, lateral along y): NCC peaks at 1
    in_plane = sensor.reseeded(np.random.default_rng(1))
    y = in_plane.measure(TrueState(np.asarray(target.rest) + shift[:2], slab.rest + shift, slab.mesh))
    across = sensor.reseeded(np.random.default_rng(1))
    across.measure(TrueState(np.asarray(target.rest) + shift[:2], slab.rest + shift + [0, 0, 0.4], slab.mesh))
    assert in_plane.correlation > 0.95 and across.correlation < in_plane.correlation - 0.2
    assert np.allclose(y - sensor.believed_pose.to_layer(sensor._last_mm), shift[:2], atol=0.03)


def test_trials_are_deterministic(world):
    cfg, scene, mesh, tissue, data, model = world
    prosthesis = sensor_model(cfg, scene, error_model(TrialsConfig(profile="prosthesis")), data)
    target = scene.targets[0]
    states = [at_rest(mesh, target.rest, (0.05 * k, -0.1 * k)) for k in range(3)]

    def readings(trial):
        draws = TrialDraws(np.zeros(2), np.random.default_rng(0), (7, 0, trial), goal_mm=np.asarray(target.rest))
        s = prosthesis.for_trial(draws)
        return np.array([s.measure(st) for st in states]), s

    a, sa = readings(3)
    b, sb = readings(3)
    c, sc = readings(4)
    assert np.array_equal(a, b)
    assert sa.tissue_sound_speed_m_per_s == sb.tissue_sound_speed_m_per_s != sc.tissue_sound_speed_m_per_s
    assert not np.array_equal(sa.believed_pose.position_mm, sc.believed_pose.position_mm)
    assert np.abs(a - c).max() > 1e-3


def test_a_lost_lesion_is_held_and_counted(world):
    cfg, scene, mesh, tissue, data, model = world
    target = scene.targets[0]
    sensor = model.nominal(cfg.seed, 0, target.rest)
    first = sensor.measure(at_rest(mesh, target.rest))
    held = sensor.measure(at_rest(mesh, target.rest, (0.0, 25.0)))  # the lesion leaves the window
    assert np.array_equal(first, held) and sensor.lost_frames == 1 and sensor.frames == 2


def test_a_reseeded_copy_tracks_on_its_own(world):
    cfg, scene, mesh, tissue, data, model = world
    target = scene.targets[0]
    sensor = model.nominal(cfg.seed, 0, target.rest)
    first = sensor.measure(at_rest(mesh, target.rest))
    copy = sensor.reseeded(np.random.default_rng(5))
    moved = copy.measure(at_rest(mesh, target.rest, (0.4, 0.0)))
    assert np.allclose(moved - first, [0.4, 0.0], atol=0.03)
    back = sensor.measure(at_rest(mesh, target.rest, (0.05, 0.0)))  # the original's tracker is where it was
    assert np.allclose(back - first, [0.05, 0.0], atol=0.03) and sensor.frames == 3 and copy.recorded is None


def test_the_camera_without_imaging():
    from scissor_cli.experiments.trials import TrialContext
    from scissor_cli.sensing.camera import CameraModel

    data = scene_data()
    del data["imaging"]
    ctx = TrialContext(resolved_yaml(parse_config(yaml.safe_dump(data), "scene.yaml")))
    assert isinstance(ctx.sensors, CameraModel)


def test_profiles_and_budget_rows_with_imaging():
    from scissor_cli.experiments.error_budget import budget_plan, identical_trials

    for values in PROFILES.values():
        assert {"sound_speed_sd_m_per_s", "probe_position_sd_mm", "probe_angle_sd_deg",
                "electronic_noise_scale"} <= set(values)
    cfg = parse_config(yaml.safe_dump(scene_data(profile="prosthesis", budget=True)), "scene.yaml")
    em = error_model(cfg.trials)
    assert (em.sound_speed_sd_m_per_s, em.probe_position_sd_mm, em.probe_angle_sd_deg) == (10.0, 0.2, 0.5)
    plan = budget_plan(cfg)
    assert {"sound_speed", "probe_calibration", "electronic_noise", "speckle"} <= set(plan.rows)
    assert not {"camera", "localisation"} & set(plan.rows)
    assert plan.rows["speckle"].imaging is not None and plan.rows["speckle"].trials.sound_speed_sd_m_per_s == 0
    assert plan.rows["none"].imaging is None and plan.rows["none"].trials.profile == "ideal"
    row = plan.rows["probe_calibration"].trials
    assert (row.probe_position_sd_mm, row.probe_angle_sd_deg, row.E_log_sd,
            row.electronic_noise_scale) == (0.2, 0.5, 0, 0)
    # the speckle is drawn per trial: only the exact sensor's `none` row has identical trials
    assert [name for name, row in plan.rows.items() if identical_trials(row)] == ["none"]


def test_a_trial_reads_the_ultrasound(world):
    from scissor_cli.experiments.trials import TargetTask, TrialContext

    cfg, scene, mesh, tissue, data, model = world
    ctx = TrialContext(resolved_yaml(cfg))
    target = scene.targets[1]
    task = TargetTask(1, target.name, np.asarray(target.rest), np.asarray(target.rest) + np.array([0.0, -1.5]),
                      np.zeros(1), "right", np.array([-1.0, 0.0]), imaging=data)
    out = ctx.run(task, 0)
    assert out.ok and out.frames >= out.iterations + 1 and out.lost_frames == 0
    cols = out.history_columns
    measured = out.history[:, [cols.index("measured_x"), cols.index("measured_y")]]
    true = out.history[:, [cols.index("true_x"), cols.index("true_y")]]
    assert 0 < np.abs(measured - true).max() <= 0.3
    again = TrialContext(resolved_yaml(cfg)).run(task, 0)
    assert np.array_equal(again.history, out.history)


@pytest.mark.slow
def test_simus_model_localises_and_tracks(world):
    """`model: simus`: the reference in the loop's place, on a 1 mm lesion (a small first-frame search)."""
    cfg, scene, mesh, tissue, data, model = world
    simus = replace(model, image_model="simus", lesion_radius_mm=1.0)
    target = scene.targets[0]
    sensor = simus.nominal(cfg.seed, 0, target.rest)
    first = sensor.measure(at_rest(mesh, target.rest))
    assert np.hypot(*(first - target.rest)) <= 0.3
    moved = sensor.measure(at_rest(mesh, target.rest, (0.1, -0.15)))
    assert np.allclose(moved - first, [0.1, -0.15], atol=0.03) and sensor.lost_frames == 0


@pytest.mark.slow
def test_simulate_with_imaging_end_to_end(tmp_path):
    """`scissor simulate` with imaging: the nominal frames in /imaging, the trials' spreads, the budget's rows."""
    import subprocess
    import sys

    import h5py

    from helpers import write_scene

    data = scene_data(profile="prosthesis", budget=True)
    data["targets"] = data["targets"][1:]  # T2, with its desired position
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(write_scene(tmp_path, data)), "--out",
                           str(out), "--jobs", "2", "--quiet"], capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr
    with h5py.File(out / "results.h5") as f:
        assert f["imaging/T2/frames"].shape[1:] == (f["imaging/grid_depth_mm"].size, f["imaging/grid_lateral_mm"].size)
        attrs = f["imaging"].attrs
        assert attrs["probe"] == "L11-5v" and attrs["frame_time_s"] > 0
        assert attrs["validation_envelope_correlation"] > 0.93 and attrs["validation_tracking_difference_mm"] < 0.05
        t = f["trials"].attrs
        assert t["sound_speed_sd_m_per_s"] == 10.0 and "pixel_noise_px" not in t
        sources = list(f["budget"].attrs["sources"])
        assert {"sound_speed", "probe_calibration", "electronic_noise", "speckle", "none"} <= set(sources)
        assert not {"camera", "localisation"} & set(sources)
    assert list(tmp_path.glob(".scissor-cache/ultrasound-psf-*.npz"))
