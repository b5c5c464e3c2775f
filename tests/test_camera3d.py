"""Tests of the 3-D cameras (scissor_cli.sensing.camera3d, camera3d_sensor; docs/model.md §19 "Sensing"):
the pose against the 2-D camera and hand-made points, one camera's reading (rounding bound, no depth, NaN,
parallax, bias), triangulation (rounding bound, noise against its propagation, bias), the config check, the
model's draws and determinism."""

import numpy as np
import pytest

from scissor_cli.config import CameraConfig
from scissor_cli.config.body_sections import BodyCameraConfig
from scissor_cli.geometry3d import inside_spheroid_cap
from scissor_cli.sensing.camera import Camera, CameraSensor
from scissor_cli.sensing.camera3d import (
    camera_problems,
    footprint_mm,
    observed_pixels,
    optical_axis,
    posed_camera,
    reading_covariance,
    triangulate,
    view_rotation,
)
from scissor_cli.sensing.camera3d_sensor import BIAS_STREAM, BodyCameraModel, BodyCameraSensor
from scissor_cli.sensing.sensor import TrialDraws, TrueState

RADIUS, HEIGHT = 60.0, 35.0  # the example dome
ABOVE = BodyCameraConfig(position_mm=[0.0, 0.0, 400.0])
BESIDE = BodyCameraConfig(position_mm=[400.0, 0.0, 15.0], look_at_mm=[0.0, 0.0, 15.0])
REF = np.array([0.0, 0.0, 15.0])


def dome_points(n, rng):
    """n random points (n, 3) mm inside the example dome."""
    p = rng.uniform([-RADIUS, -RADIUS, 0.0], [RADIUS, RADIUS, HEIGHT], (8 * n, 3))
    return p[inside_spheroid_cap(p, RADIUS, HEIGHT)][:n]


def cam(position, look_at=None, noise=0.0):
    return posed_camera(BodyCameraConfig(position_mm=position, look_at_mm=look_at, pixel_noise_px=noise))


# ---- pose and projection


def test_default_pose_is_the_2d_cameras():
    flat = Camera.from_config(CameraConfig(position_mm=[0.0, 0.0, 400.0]))
    pts = np.column_stack([np.random.default_rng(0).uniform(-60, 60, (50, 2)), np.zeros(50)])
    for posed in (posed_camera(ABOVE), cam([0.0, 0.0, 400.0], [0.0, 0.0, 0.0])):  # None, and looking at below
        np.testing.assert_array_equal(posed.T_cb, flat.T_cb)
        np.testing.assert_array_equal(posed.project(pts), flat.project(pts[:, :2]))


def test_a_camera_sees_what_it_looks_at_at_the_principal_point():
    side = cam([400.0, 0.0, 50.0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(side.project([[0.0, 0.0, 0.0]]), [[640.0, 512.0]], atol=1e-9)
    np.testing.assert_allclose(optical_axis(side), [-400.0, 0.0, -50.0] / np.hypot(400.0, 50.0), atol=1e-15)
    # hand-made: a point 1 mm off the axis along y at the look-at point's depth moves 1 mm / footprint in v only
    fp = np.hypot(400.0, 50.0) * 0.0048 / 8.0
    np.testing.assert_allclose(side.project([[0.0, 1.0, 0.0]]) - [[640.0, 512.0]], [[0.0, -1.0 / fp]], atol=1e-9)


def test_the_tilt_convention():
    """The looking-down frame tilted onto the axis: right-handed, z_c the axis, continuous towards straight down."""
    beside = cam([400.0, 0.0, 15.0], [0.0, 0.0, 15.0])
    np.testing.assert_allclose(beside.rotation, [[0, 0, -1], [0, -1, 0], [-1, 0, 0]], atol=1e-15)
    # so a point higher up appears at smaller u, one towards +y at smaller v
    uv = beside.project([[0.0, 0.0, 15.0], [0.0, 0.0, 16.0], [0.0, 1.0, 15.0]])
    assert uv[1, 0] < uv[0, 0] and abs(uv[1, 1] - uv[0, 1]) < 1e-9
    assert uv[2, 1] < uv[0, 1] and abs(uv[2, 0] - uv[0, 0]) < 1e-9
    rng = np.random.default_rng(1)
    for a in rng.standard_normal((200, 3)):
        R = view_rotation(a)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(R[2], a / np.linalg.norm(a), atol=1e-12)
    down = np.diag([1.0, -1.0, -1.0])
    for eps in (1e-2, 1e-4, 1e-8):
        for azimuth in np.linspace(0.0, 2.0 * np.pi, 7):
            a = [eps * np.cos(azimuth), eps * np.sin(azimuth), -1.0]
            assert np.abs(view_rotation(a) - down).max() < 2.0 * eps
    np.testing.assert_allclose(view_rotation([0.0, 0.0, 1.0]), np.eye(3))  # straight up: the half turn about x
    with pytest.raises(ValueError):
        view_rotation([0.0, 0.0, 0.0])


# ---- one camera


def test_one_camera_above_reads_x_y_to_the_rounding_and_not_z():
    rng = np.random.default_rng(2)
    pts = dome_points(400, rng)
    pts[:, 2] = REF[2]  # on the reading plane: only the rounding is left
    sensor = BodyCameraSensor((posed_camera(ABOVE),), REF, noise_px=(0.0,), rng=np.random.default_rng(3))
    read = sensor.read_points(pts)
    half = 0.5 * footprint_mm(sensor.cameras[0], pts)
    err = np.abs(read - pts)
    assert np.all(err[:, :2] <= half[:, None] + 1e-9)
    assert err[:, :2].max() > 0.8 * half.max()  # the rounding is there
    np.testing.assert_allclose(read[:, 2], REF[2], atol=1e-9)
    r = sensor.reading(TrueState(np.array([10.0, 20.0, 15.0])))
    assert np.isnan(r.position[2]) and np.all(np.isfinite(r.position[:2]))
    np.testing.assert_array_equal(r.position[:2], r.point[:2])
    np.testing.assert_array_equal(r.seen, np.diag([1.0, 1.0, 0.0]))
    m = sensor.measure(TrueState(np.array([10.0, 20.0, 5.0])))
    assert m.shape == (3,) and np.isnan(m[2])


def test_one_camera_does_not_see_depth_along_its_view():
    a_cam = cam([300.0, -200.0, 250.0], REF.tolist())
    a = optical_axis(a_cam)
    sensor = BodyCameraSensor((a_cam,), REF, exact=True)
    truth = REF + np.linspace(-10.0, 10.0, 9)[:, None] * a  # moving along the view
    np.testing.assert_allclose(sensor.read_points(truth), np.tile(REF, (9, 1)), atol=1e-9)
    r = sensor.reading(TrueState(truth[0]))
    assert np.all(np.isfinite(r.position))  # oblique: no coordinate is NaN, the point is reported whole
    np.testing.assert_allclose(r.seen @ a, 0.0, atol=1e-15)
    np.testing.assert_allclose(r.observed_error(REF), 0.0, atol=1e-9)
    # across the view it sees: a move v ⟂ a is read as v
    v = np.cross(a, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(sensor.read_points(REF + 3.0 * v)[0], REF + 3.0 * v, atol=1e-9)


def test_the_nan_axis_is_the_one_within_a_degree_of_the_view():
    for tilt_deg, nan in ((0.5, [False, False, True]), (2.0, [False, False, False])):
        look = [400.0 * np.tan(np.radians(tilt_deg)), 0.0, 0.0]
        sensor = BodyCameraSensor((cam([0.0, 0.0, 400.0], look),), [0.0, 0.0, 0.0], exact=True)
        np.testing.assert_array_equal(np.isnan(sensor.measure(TrueState(np.array([1.0, 2.0, 0.0])))), nan)
    side = BodyCameraSensor((posed_camera(BESIDE),), REF, exact=True)
    np.testing.assert_array_equal(np.isnan(side.measure(TrueState(REF))), [True, False, False])


def test_parallax_of_a_lesion_off_the_reading_plane():
    """A lesion δ below the reference's plane, seen at angle θ from the axis, reads off by δ tan θ in the plane."""
    sensor = BodyCameraSensor((posed_camera(ABOVE),), REF, exact=True)
    p = sensor.read_points([[30.0, 0.0, 5.0]])[0]
    np.testing.assert_allclose(p[:2] - [30.0, 0.0], [-10.0 * 30.0 / 395.0, 0.0], atol=1e-12)


def test_one_camera_matches_the_2d_camera_on_the_layer_plane():
    cfg2 = CameraConfig()  # at (50, 30, 400) looking down
    flat = Camera.from_config(cfg2)
    body = BodyCameraSensor((posed_camera(BodyCameraConfig(**cfg2.model_dump())),), [0.0, 0.0, 0.0],
                            noise_px=(0.7,), rng=np.random.default_rng(9))
    pts = np.random.default_rng(8).uniform([0.0, 0.0], [100.0, 60.0], (300, 2))
    ours = body.read_points(np.column_stack([pts, np.zeros(len(pts))]))
    np.testing.assert_allclose(ours[:, :2], flat.measure(pts, np.random.default_rng(9), 0.7), atol=1e-9)
    flat_sensor = CameraSensor(flat, noise_px=0.7)
    assert body.noise_mm == pytest.approx(flat_sensor.noise_mm, rel=1e-12)


def test_one_cameras_bias_moves_only_what_it_sees():
    sensor = BodyCameraSensor((posed_camera(ABOVE),), REF, biases_mm=[[1.0, -2.0, 3.0]], noise_px=(0.0,),
                              rng=np.random.default_rng(0))
    p = np.array([[5.0, 6.0, 15.0]])
    fp = footprint_mm(sensor.cameras[0], p)[0]
    assert np.all(np.abs(sensor.read_points(p)[0] - (p[0] + [1.0, -2.0, 0.0])) <= 0.5 * fp + 1e-9)


# ---- several cameras


def test_two_cameras_triangulate_points_to_the_rounding():
    pts = dome_points(500, np.random.default_rng(4))
    sensor = BodyCameraSensor((posed_camera(ABOVE), posed_camera(BESIDE)), noise_px=(0.0, 0.0),
                              rng=np.random.default_rng(5))
    err = np.linalg.norm(sensor.read_points(pts) - pts, axis=1)
    fp = np.max([footprint_mm(c, pts) for c in sensor.cameras], axis=0)
    assert np.all(err <= fp)
    assert err.max() > 0.5 * fp.min()  # the rounding is there
    r = sensor.reading(TrueState(pts[0]))
    assert np.all(np.isfinite(r.position))
    np.testing.assert_array_equal(r.seen, np.eye(3))
    exact = BodyCameraSensor(sensor.cameras, exact=True)
    np.testing.assert_allclose(exact.read_points(pts), pts, atol=1e-9)


@pytest.mark.parametrize("configs", [
    [ABOVE, BESIDE],
    [ABOVE, BESIDE, BodyCameraConfig(position_mm=[-200.0, 300.0, 250.0], look_at_mm=[0.0, 0.0, 10.0])],
    [BodyCameraConfig(position_mm=[0.0, -150.0, 380.0], look_at_mm=REF.tolist()),
     BodyCameraConfig(position_mm=[0.0, 150.0, 380.0], look_at_mm=REF.tolist())],  # 43° apart
])
def test_triangulation_noise_matches_its_propagation(configs):
    sigma, n = 1.5, 4000
    cams = tuple(posed_camera(c) for c in configs)
    p = np.array([7.0, -4.0, 12.0])
    sensor = BodyCameraSensor(cams, p, noise_px=(sigma,) * len(cams), rng=np.random.default_rng(6))
    err = sensor.read_points(np.tile(p, (n, 1))) - p
    cov = reading_covariance(cams, p, (sigma,) * len(cams))
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) == pytest.approx(np.sqrt(np.trace(cov)), rel=0.15)
    # the worst direction's σ is the sensor's noise_mm, and the readings' spread along it agrees
    w, V = np.linalg.eigh(cov)
    assert sensor.noise_mm == pytest.approx(np.sqrt(w[-1]), rel=1e-12)
    assert np.std(err @ V[:, -1]) == pytest.approx(sensor.noise_mm, rel=0.15)


def test_triangulated_bias_comes_from_each_camera_across_its_view():
    """Above (looking −z) sees x, y; beside (looking −x) sees y, z: x from above, z from beside, y their mean."""
    b = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, -0.8]])
    sensor = BodyCameraSensor((posed_camera(ABOVE), posed_camera(BESIDE)), biases_mm=b, exact=False,
                              noise_px=(0.0, 0.0), rng=np.random.default_rng(0))
    shift = np.array([b[0, 0], 0.5 * (b[0, 1] + b[1, 1]), b[1, 2]])
    p = np.array([[0.0, 0.0, 15.0]])
    fp = max(footprint_mm(c, p)[0] for c in sensor.cameras)
    assert np.linalg.norm(sensor.read_points(p)[0] - p[0] - shift) <= fp


def test_parallel_rays_are_refused():
    with pytest.raises(ValueError, match="parallel"):
        triangulate(np.array([[0.0, 0.0, 400.0], [10.0, 0.0, 400.0]]),
                    np.array([[[0.0, 0.0, -1.0]], [[0.0, 0.0, -1.0]]]))
    d = np.array([[[0.0, 0.0, -1.0]], [[np.sin(np.radians(6.0)), 0.0, -np.cos(np.radians(6.0))]]])
    triangulate(np.array([[0.0, 0.0, 400.0], [-40.0, 0.0, 400.0]]), d)  # 6° apart: solved


def test_camera_problems():
    assert camera_problems([ABOVE, BESIDE]) == []
    assert camera_problems([ABOVE]) == []
    near = BodyCameraConfig(position_mm=[30.0, 0.0, 400.0], look_at_mm=[0.0, 0.0, 15.0])  # 4.5° from ABOVE
    far = BodyCameraConfig(position_mm=[60.0, 0.0, 400.0], look_at_mm=[0.0, 0.0, 15.0])  # 8.9°
    (msg,) = camera_problems([ABOVE, near])
    assert "triangulate" in msg and "4.5°" in msg
    assert camera_problems([ABOVE, far]) == []
    assert camera_problems([ABOVE, near, BESIDE]) == []  # a third camera far off makes it well posed
    below = BodyCameraConfig(position_mm=[0.0, 0.0, -400.0], look_at_mm=[0.0, 0.0, 0.0])
    assert len(camera_problems([ABOVE, below])) == 1  # opposite views are parallel lines
    # two cameras at one point looking different ways: only the sight lines to the lesion show it
    turned = BodyCameraConfig(position_mm=[0.0, 0.0, 400.0], look_at_mm=[100.0, 0.0, 15.0])
    assert camera_problems([ABOVE, turned]) == []
    assert len(camera_problems([ABOVE, turned], [REF])) == 1
    (msg,) = camera_problems([BodyCameraConfig(position_mm=[0.0, 0.0, 400.0], look_at_mm=[0.0, 0.0, 400.0])])
    assert "cameras[0]" in msg and "no view" in msg
    (msg,) = camera_problems([BESIDE], [[500.0, 0.0, 15.0]])
    assert "behind" in msg


# ---- the model and determinism


def test_the_models_biases():
    model = BodyCameraModel.from_config([ABOVE, BESIDE], pixel_noise_px=0.5, localisation_error_mm=0.3)
    z = np.array([0.4, -1.1])
    draws = TrialDraws(z, np.random.default_rng(1), key=(7, 0, 3), goal_mm=REF)
    b = model.biases(draws)
    assert b.shape == (2, 3)
    np.testing.assert_allclose(b[0, :2], 0.3 * z)  # the first camera's x, y are the 2-D camera's bias
    rest = np.random.default_rng((7, 0, 3, BIAS_STREAM)).standard_normal(4)
    np.testing.assert_allclose(b.ravel()[2:], 0.3 * rest)
    other = model.biases(TrialDraws(z, np.random.default_rng(1), key=(7, 0, 4)))
    assert np.array_equal(other.ravel()[:2], b.ravel()[:2]) and not np.allclose(other.ravel()[2:], b.ravel()[2:])
    sensor = model.for_trial(draws)
    np.testing.assert_array_equal(sensor.biases_mm, b)
    assert sensor.noise_px == (0.5, 0.5)
    np.testing.assert_array_equal(sensor.reference_mm, REF)
    one = BodyCameraModel.from_config(ABOVE, None, 0.3)
    assert one.for_trial(draws).noise_px == (ABOVE.pixel_noise_px,)
    with pytest.raises(ValueError, match="reference"):
        one.for_trial(TrialDraws(z, np.random.default_rng(1)))


def test_nominal_and_ideal_read_without_error():
    model = BodyCameraModel.from_config([ABOVE, BESIDE], pixel_noise_px=2.0, localisation_error_mm=1.0, ideal=True)
    assert model.exact
    p = np.array([3.3, -7.1, 21.7])
    s = model.for_trial(TrialDraws(np.array([3.0, 3.0]), np.random.default_rng(0), key=(1, 2, 3)))
    np.testing.assert_allclose(s.measure(TrueState(p)), p, atol=1e-9)
    assert s.noise_mm == 0.0
    one = BodyCameraModel.from_config(ABOVE, 2.0, 1.0).nominal(goal_mm=[0.0, 0.0, 21.7])
    m = one.measure(TrueState(p))
    np.testing.assert_allclose(m[:2], p[:2], atol=1e-9)
    assert np.isnan(m[2])


def test_same_seed_same_readings_and_reseeding_changes_only_the_frame_noise():
    model = BodyCameraModel.from_config([ABOVE, BESIDE], pixel_noise_px=1.0, localisation_error_mm=0.5)

    def trial(seed):
        return model.for_trial(TrialDraws(np.array([0.2, -0.3]), np.random.default_rng(seed), key=(1, 0, 0)))

    pts = dome_points(50, np.random.default_rng(10))
    a, b, c = trial(42).read_points(pts), trial(42).read_points(pts), trial(43).read_points(pts)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    s = trial(42)
    r = s.reseeded(np.random.default_rng(99))
    np.testing.assert_array_equal(r.biases_mm, s.biases_mm)
    assert r.noise_mm == s.noise_mm and r.noise_px == s.noise_px
    assert not np.array_equal(r.read_points(pts), a)
    # over many frames the reseeded sensor's readings centre where the original's do (same bias)
    p = np.tile(pts[0], (3000, 1))
    np.testing.assert_allclose(r.read_points(p).mean(0), s.read_points(p).mean(0), atol=0.02)
    # without pixel noise only the bias and rounding are left: reseeding changes nothing
    quiet = BodyCameraModel.from_config([ABOVE, BESIDE], pixel_noise_px=0.0, localisation_error_mm=0.5)
    q = quiet.for_trial(TrialDraws(np.array([0.2, -0.3]), np.random.default_rng(1), key=(1, 0, 0)))
    np.testing.assert_array_equal(q.read_points(pts), q.reseeded(np.random.default_rng(2)).read_points(pts))


def test_a_reading_draws_two_normals_per_point_and_camera_whatever_the_noise():
    cams = (posed_camera(ABOVE), posed_camera(BESIDE))
    pts = dome_points(5, np.random.default_rng(11))
    states = []
    for sigma in (0.0, 3.0):
        rng = np.random.default_rng(12)
        observed_pixels(cams, pts, rng, (sigma, sigma))
        states.append(rng.standard_normal())
    assert states[0] == states[1]
    assert states[0] == np.random.default_rng(12).standard_normal(2 * 2 * 5 + 1)[-1]
