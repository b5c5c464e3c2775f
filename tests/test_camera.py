"""Tests of scissor_cli.camera: conventions, exact round trips (straight and
tilted), the rounding bound, the noise statistics and reproducibility."""

from pathlib import Path

import numpy as np
import pytest

from scissor_cli.config import CameraConfig, load_config
from scissor_cli.sensing.camera import Camera, intrinsics, looking_down, rigid_transform

ROOT = Path(__file__).resolve().parents[1]
# configs/ is the documented place; the packaged copy is the fallback.
EXAMPLE = next(
    p for p in (ROOT / "configs" / "example.yaml", ROOT / "scissor_cli" / "scenes" / "example.yaml") if p.exists()
)


@pytest.fixture(scope="module")
def camera():
    return Camera.from_config(load_config(EXAMPLE).camera)


def layer_points(n, rng):
    """n random points (n, 2) mm over the example layer, 100 × 60 mm."""
    return rng.uniform([0.0, 0.0], [100.0, 60.0], (n, 2))


def rotation(axis, angle_rad):
    """Rodrigues rotation (3, 3) about a unit axis."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * Kx + (1 - np.cos(angle_rad)) * Kx @ Kx


def tilted_camera():
    """A camera off to the side, aimed at the layer's middle (optical axis ~45° from −z), rolled 10°."""
    centre = np.array([-250.0, -60.0, 300.0])
    z_c = np.array([50.0, 30.0, 0.0]) - centre
    z_c /= np.linalg.norm(z_c)
    x_c = np.array([1.0, 0.0, 0.0]) - z_c[0] * z_c
    x_c /= np.linalg.norm(x_c)
    R = np.vstack([x_c, np.cross(z_c, x_c), z_c])  # rows: camera axes in the layer frame
    R = rotation([0, 0, 1], np.radians(10.0)) @ R  # roll about the optical axis
    return Camera(intrinsics(8.0, [0.0048, 0.0052], [640.0, 500.0]), rigid_transform(R, -R @ centre), 0.5)


def test_conventions_of_the_config_camera(camera):
    cfg = CameraConfig()
    # The point under the optical centre images at the principal point.
    np.testing.assert_allclose(camera.project([[50.0, 30.0]]), [[640.0, 512.0]], atol=1e-12)
    # +x on the layer is +u, +y on the layer is −v.
    du = camera.project([[51.0, 30.0]]) - camera.project([[50.0, 30.0]])
    dv = camera.project([[50.0, 31.0]]) - camera.project([[50.0, 30.0]])
    assert du[0, 0] > 0 and abs(du[0, 1]) < 1e-12
    assert dv[0, 1] < 0 and abs(dv[0, 0]) < 1e-12
    # One pixel covers dx·Z/f = 0.0048·400/8 = 0.24 mm.
    np.testing.assert_allclose(camera.mm_per_pixel, [0.24, 0.24], rtol=1e-12)
    np.testing.assert_allclose(1.0 / du[0, 0], 0.24, rtol=1e-12)
    np.testing.assert_allclose(camera.centre, [50.0, 30.0, 400.0], atol=1e-12)
    assert camera.pixel_noise_px == cfg.pixel_noise_px == 0.5
    np.testing.assert_allclose(np.linalg.det(camera.rotation), 1.0)
    np.testing.assert_array_equal(camera.T_cb, looking_down(cfg.position_mm))


@pytest.mark.parametrize("which", ["straight", "tilted"])
def test_round_trip_is_exact_without_noise_or_rounding(camera, which):
    cam = camera if which == "straight" else tilted_camera()
    pts = layer_points(500, np.random.default_rng(1))
    back = cam.back_project(cam.project(pts))
    np.testing.assert_allclose(back, pts, rtol=0, atol=1e-9)


def test_tilted_camera_is_really_tilted():
    cam = tilted_camera()
    tilt = np.degrees(np.arccos(-cam.rotation[2, 2]))  # optical axis vs −z
    assert tilt > 20
    # A (K, 3) point off the plane projects like the formula z_c [u v 1] = Ω T_cb [X 1].
    P = np.array([[10.0, 20.0, 5.0]])
    h = cam.intrinsics @ (cam.T_cb @ np.append(P[0], 1.0))[:3]
    np.testing.assert_allclose(cam.project(P)[0], h[:2] / h[2], rtol=1e-12)


def test_rounding_alone_errs_by_at_most_half_a_pixel(camera):
    rng = np.random.default_rng(2)
    pts = layer_points(5000, rng)
    err = camera.measure(pts, rng, noise_px=0.0) - pts
    assert np.all(np.abs(err) <= 0.5 * camera.mm_per_pixel + 1e-9)
    # and the bound is reached: the quantisation really happens
    assert np.max(np.abs(err)) > 0.45 * camera.mm_per_pixel.min()


@pytest.mark.parametrize("sigma_px", [0.5, 2.0])
def test_noise_spread_matches_sigma_plus_rounding(camera, sigma_px):
    # Random sub-pixel offsets make the rounding error uniform on ±½ px and
    # independent of the noise, so each axis errs with variance σ² + 1/12 px².
    rng = np.random.default_rng(3)
    n = 40_000
    pts = layer_points(n, rng)
    err = camera.measure(pts, rng, noise_px=sigma_px) - pts
    expected = np.sqrt(sigma_px**2 + 1.0 / 12.0) * camera.mm_per_pixel
    np.testing.assert_allclose(err.std(axis=0), expected, rtol=0.02)
    np.testing.assert_allclose(err.mean(axis=0), 0.0, atol=4 * expected.max() / np.sqrt(n))


def test_default_noise_is_the_cameras(camera):
    pts = layer_points(100, np.random.default_rng(4))
    a = camera.measure(pts, np.random.default_rng(5))
    b = camera.measure(pts, np.random.default_rng(5), noise_px=camera.pixel_noise_px)
    np.testing.assert_array_equal(a, b)


def test_same_seed_same_numbers(camera):
    pts = layer_points(200, np.random.default_rng(6))
    a = camera.measure(pts, np.random.default_rng(42))
    b = camera.measure(pts, np.random.default_rng(42))
    c = camera.measure(pts, np.random.default_rng(43))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_points_behind_the_camera_are_rejected(camera):
    with pytest.raises(ValueError):
        camera.project([[50.0, 30.0, 500.0]])
    side = Camera(camera.intrinsics, rigid_transform(rotation([1, 0, 0], np.pi / 2) @ camera.rotation, [0, 0, 0]))
    with pytest.raises(ValueError):
        side.back_project([[640.0, 512.0]])
