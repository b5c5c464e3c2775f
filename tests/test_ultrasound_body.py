"""Ultrasound with the probe on the skin of a 3-D body (docs/ultrasound.md, "On the body (3-D)"): the pose on the
mesh's skin, scatterers drawn in and carried by the tetrahedra, first-frame localisation mapped back to the body
with the elevation not seen, determinism, and every bad pose refused (exit 2) by `scissor validate`.

The scene is tests/test_body_loop.py's small dome with its lesion T1 only, the probe on top of it looking down,
its lateral axis the needle's (in-plane guidance: the image plane is the needle's vertical plane, x-z).
"""

from __future__ import annotations

import copy
import csv
import math

import h5py
import numpy as np
import pytest
import yaml

from scissor_cli import geometry3d as g3
from scissor_cli.config import ConfigError, parse_config
from scissor_cli.config.body_imaging import PROBE_ELEVATION, PROBE_FREQUENCY_HZ, elevation_reach_mm
from scissor_cli.mesh.probe import locate_in_tetrahedra
from scissor_cli.sensing.sensor import TrialDraws, TrueState
from scissor_cli.sensing.ultrasound import build_psf, elevation_width_mm, imaging_tables, probe_params
from scissor_cli.sensing.ultrasound.body_pose import skin_pose, skin_surface
from scissor_cli.sensing.ultrasound.body_sensor import body_ultrasound_model

from figure_checks import assert_png_drawn
from helpers import cli_here, simulate_here, write_scene
from test_body_loop import SCENE
from test_cli import run_cli

DEPTH_MM = 30.0
IMAGING = {"position_mm": [5.0, 10.0, 24.5], "axis": [0.0, 0.0, -1.0], "depth_mm": DEPTH_MM}


def scene(**imaging) -> dict:
    data = copy.deepcopy(SCENE)
    # the default grading: the pose is moved onto the skin's facets, which the finer mesh keeps within 0.1 mm of
    # the lesion's plane (test_the_pose_is_moved_onto_the_skin_and_its_frame_is_orthonormal)
    del data["tissue"]["mesh"]["grading"]
    data["targets"] = data["targets"][:1]
    data["imaging"] = {**IMAGING, **imaging}
    return data


@pytest.fixture(scope="module")
def body():
    """(config, mesh, the run's ultrasound model) of the scene."""
    from scissor_cli.experiments.build import body_model  # noqa: PLC0415

    cfg = parse_config(yaml.safe_dump(scene()), "scene.yaml")
    _, mesh, _ = body_model(cfg)
    probe = probe_params(cfg.imaging.probe)
    tables = imaging_tables(probe, build_psf(probe, cfg.imaging.assumed_sound_speed_m_per_s, DEPTH_MM), DEPTH_MM)
    model = body_ultrasound_model(cfg.imaging, mesh, cfg.targets, cfg.obstacles, tables, cfg.needle.direction)
    return cfg, mesh, model


def test_the_config_tables_are_pymusts():
    for name, (height, focus) in PROBE_ELEVATION.items():
        p = probe_params(name)
        assert (p.element_height_mm, p.elevation_focus_mm, p.center_frequency_hz) == pytest.approx(
            (height, focus, PROBE_FREQUENCY_HZ[name]))
        for z in (5.0, 20.0, 45.0):  # the check's beam is psf's Gaussian beam
            w = float(elevation_width_mm(p, 1540.0, z))
            assert elevation_reach_mm(name, z, 1540.0, 0.0) == pytest.approx(w * math.sqrt(math.log(2.0) / 2.0))


def test_the_pose_is_moved_onto_the_skin_and_its_frame_is_orthonormal(body):
    cfg, mesh, model = body
    surface = skin_surface(mesh)
    skin = surface.triangles[~surface.held]
    on, _, face = g3.nearest_on_surface(np.array([[5.0, 10.0, 30.0]]), mesh.nodes, skin)
    a, b, c = mesh.nodes[skin[face[0]]]
    outward = np.cross(b - a, c - a)
    outward /= np.linalg.norm(outward)
    given = on[0] + 1.5 * outward  # 1.5 mm off the skin, along its normal
    pose, moved = skin_pose(mesh, given, needle_direction=cfg.needle.direction)
    assert moved == pytest.approx(1.5, abs=1e-6)
    assert g3.nearest_on_surface(pose.origin_mm[None], mesh.nodes, skin)[1][0] < 1e-9  # on the skin
    R = pose.rotation
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(pose.elevation, np.cross(pose.lateral, pose.axis))
    assert pose.axis @ outward < -0.95  # the default axis: inward, near the face's normal
    assert abs(pose.elevation @ cfg.needle.direction) < 1e-12  # in-plane guidance: the needle in the image
    q = np.random.default_rng(1).normal(size=(5, 3))
    assert np.allclose(pose.to_probe(pose.to_body(q)), q)
    # the scene's own pose: straight down from the top, the lesion in its plane (to the shift of the configured
    # point onto the meshed skin's nearest facet: a fraction of a mm, far inside the elevation beam)
    assert np.allclose(model.pose.axis, [0, 0, -1]) and np.allclose(model.pose.lateral, [-1, 0, 0])
    assert abs(model.pose.to_probe(np.array(cfg.targets[0].position_mm))[2]) < 0.25


def test_point_location_agrees_with_the_exhaustive_search(body):
    from scissor_cli.mesh.probe import locate_in_simplices  # noqa: PLC0415

    _, mesh, _ = body
    p = np.random.default_rng(2).uniform([-42, -42, -3], [42, 42, 28], (800, 3))
    tet, bary = locate_in_tetrahedra(mesh.nodes, mesh.tetrahedra, p)
    _, best = locate_in_simplices(mesh.nodes, mesh.tetrahedra, p, extrapolate=True)
    assert np.array_equal(tet >= 0, best.min(axis=1) >= -1e-9) and 0.2 < np.mean(tet >= 0) < 0.8
    inside = tet >= 0
    back = np.einsum("kj,kjd->kd", bary[inside], mesh.nodes[mesh.tetrahedra[tet[inside]]])
    assert np.allclose(back, p[inside], atol=1e-9)


def _rest_state(mesh, cfg, shift=(0.0, 0.0, 0.0)) -> TrueState:
    rest, shift = np.asarray(cfg.targets[0].position_mm, float), np.asarray(shift, float)
    return TrueState(rest + shift, mesh.nodes + shift, mesh)


def test_first_frame_localises_the_lesion_in_plane(body):
    """The issue's criterion: three speckle draws, in-plane rms error ≤ 0.15 mm and each ≤ 0.3 mm; the elevation
    (here y) is not seen."""
    cfg, mesh, model = body
    state = _rest_state(mesh, cfg)
    errors = []
    for seed in range(3):
        sensor = model.nominal(state.target_mm, 0, seed=seed)
        y = sensor.measure(state)
        assert np.isnan(y[1]) and np.all(np.isfinite(y[[0, 2]])) and sensor.unseen.tolist() == [False, True, False]
        assert np.allclose(sensor.seen, np.diag([1.0, 0.0, 1.0]))
        errors.append(float(np.linalg.norm(y[[0, 2]] - state.target_mm[[0, 2]])))
    print("first-frame in-plane errors (mm):", np.round(errors, 4))
    assert math.sqrt(np.mean(np.square(errors))) <= 0.15 and max(errors) <= 0.3


def test_frames_are_deterministic_and_carried_by_the_tetrahedra(body):
    cfg, mesh, model = body
    state = _rest_state(mesh, cfg)
    draws = lambda trial: TrialDraws(np.zeros(2), np.random.default_rng(0), (5, 0, trial), state.target_mm)  # noqa
    a, b, c = (model.for_trial(draws(k)).frame(state) for k in (0, 0, 1))
    assert np.array_equal(a, b)  # same key: same scatterers, pose, noise
    # another trial: other speckle (the envelopes still share the lesion and the depth gain)
    assert abs(np.corrcoef(a.ravel(), c.ravel())[0, 1]) < 0.5
    # a rigid in-plane shift of the body moves the localised lesion by that shift
    shift = np.array([0.6, 0.0, -0.4])
    first = model.nominal(state.target_mm, 0, seed=7).measure(state)
    moved = model.nominal(state.target_mm, 0, seed=7).measure(_rest_state(mesh, cfg, shift))
    assert np.allclose((moved - first)[[0, 2]], shift[[0, 2]], atol=0.03)


@pytest.mark.parametrize("change, words", [
    ({"position_mm": [5.0, 10.0, 40.0]}, ["imaging.position_mm", "off the skin"]),
    ({"axis": [0.0, 0.0, 1.0]}, ["imaging.axis", "pointing out"]),
    ({"axis": [0.0, 0.866, -0.5]}, ["imaging.axis", "60°"]),
    ({"lateral_axis": [0.6, 0.0, 0.8]}, ["imaging.lateral_axis", "perpendicular"]),
    ({"position_mm": [5.0, 17.0, 23.0]}, ["imaging.position_mm", "lesion outside the image", "elevation"]),
    ({"position_mm": [-22.0, 10.0, 19.9], "axis": None}, ["imaging.position_mm", "lesion outside the image",
                                                         "lateral"]),
    ({"depth_mm": 10.0}, ["imaging.depth_mm", "lesion outside the image"]),
    ({"axis": [0.0, 0.0, -2.0]}, ["imaging.axis", "unit vector"]),
    ({"model": "simus"}, ["imaging.model", "fast"]),
])
def test_a_bad_pose_is_one_message_naming_the_field(change, words):
    with pytest.raises(ConfigError) as info:
        parse_config(yaml.safe_dump(scene(**change)), "scene.yaml")
    for w in words:
        assert w in str(info.value), (w, str(info.value))


def test_validate_exits_2_on_each_bad_pose_without_a_traceback(tmp_path):
    bad = [{"position_mm": [5.0, 10.0, 40.0]}, {"axis": [0.0, 0.0, 1.0]}, {"position_mm": [5.0, 17.0, 23.0]},
           {"lateral_axis": [0.6, 0.0, 0.8]}]
    for k, change in enumerate(bad):  # in this process (`cli_here`); the last one as a process
        r = cli_here("validate", write_scene(tmp_path, scene(**change), f"bad{k}.yaml"))
        assert r.exit_code == 2 and isinstance(r.exception, SystemExit), r.output
        assert "imaging." in r.stderr and "Traceback" not in r.output, r.output
    text = write_scene(tmp_path, scene(), "nan.yaml").read_text().replace("24.5", ".nan")
    (tmp_path / "nan.yaml").write_text(text)
    r = run_cli("validate", tmp_path / "nan.yaml")
    assert r.returncode == 2 and "imaging.position_mm" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_simulate_runs_the_body_loop_on_the_ultrasound(tmp_path):
    """`scissor simulate` end to end: the nominal manipulation and a trial read the probe; the history's y (the
    elevation) is NaN, x and z are the ultrasound's. The nominal manipulation's frames are /imaging/T1 in the
    body's frame (K, 3) with the B-mode figure, and `report` reads the run."""
    data = scene()
    data["trials"] = {"count": 1, "profile": "ideal"}
    with h5py.File(simulate_here(tmp_path, data) / "results.h5", "r") as f:
        assert f["/"].attrs["status"] == "complete" and f["trials"].attrs["sensor"] == "ultrasound"
        history = f["trials/T1/history/0"]
        columns = list(history.attrs["columns"])
        table = history[()]
        assert np.all(np.isnan(table[:, columns.index("measured_y")]))
        seen = table[:, [columns.index("measured_x"), columns.index("measured_z")]]
        true = table[:, [columns.index("true_x"), columns.index("true_z")]]
        assert np.all(np.isfinite(seen)) and np.max(np.abs(seen - true)) < 0.3
        assert f["trials/T1/frames"][0] >= len(table) and f["trials/T1/lost_frames"][0] == 0
        im = f["imaging"]
        frames, tracked, true = im["T1/frames"], im["T1/tracked"][()], im["T1/true"][()]
        assert frames.shape[1:] == (im["grid_depth_mm"].size, im["grid_lateral_mm"].size)
        assert tracked.shape == true.shape == (frames.shape[0], 3) and frames.shape[0] >= 2
        assert np.shape(im.attrs["lateral_axis"]) == (3,) and np.shape(im.attrs["position_mm"]) == (3,)
        # the scanner reports the lesion in the image plane, at the plan's elevation (the true one's is not seen)
        lateral, axis = np.asarray(im.attrs["lateral_axis"]), np.asarray(im.attrs["axis"])
        in_plane = (tracked - true) @ np.stack([lateral, axis]).T
        assert np.max(np.abs(in_plane)) < 0.3
        assert np.max(frames[-1]) > 0.0
    assert_png_drawn(tmp_path / "run" / "imaging_T1.png")
    r = cli_here("report", tmp_path / "run", "--out", tmp_path / "report")
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader((tmp_path / "report" / "summary.csv").open()))
    assert rows and all(row["controller"] == "body" and row["sensor"] == "ultrasound" for row in rows)
