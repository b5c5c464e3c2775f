"""Tests of the ultrasound probe, its pose and grid, and the scatterer draw (scissor_cli.sensing.ultrasound).

Cheap: no image formation. The probe names are checked against what
pymust.getparam actually accepts.
"""

import math

import numpy as np
import pytest

from scissor_cli.sensing.ultrasound import (
    ECHOGENICITY_DB,
    LINEAR_PROBES,
    ImageGrid,
    ProbePose,
    draw_scatterers,
    image_grid,
    probe_params,
)


@pytest.mark.parametrize("name", LINEAR_PROBES)
def test_every_listed_probe_is_a_flat_array_pymust_knows(name):
    import pymust

    p = probe_params(name.lower())  # names are case-insensitive, as in pymust
    raw = pymust.getparam(name)
    assert math.isinf(raw.radius)
    assert p.name == name
    assert p.pitch_mm == pytest.approx(raw.pitch * 1e3)
    assert p.element_width_mm + p.kerf_mm == pytest.approx(p.pitch_mm)
    assert p.element_height_mm > 0 and p.elevation_focus_mm > 0
    param = p.pymust_param(1540.0)
    assert param.c == 1540.0 and param.Nelements == p.n_elements and math.isinf(param.radius)


def test_unknown_and_non_linear_probes_raise_listing_the_allowed_ones():
    for bad in ("XYZ-1", "C5-2v", "L9-4/38", ""):
        with pytest.raises(ValueError, match="allowed: L11-5v, L12-3v, P4-2v"):
            probe_params(bad)


def test_pose_round_trip_and_frame_convention():
    pose = ProbePose(np.array([0.0, 30.0]), np.array([2.0, 0.0]))  # axis is normalised
    np.testing.assert_allclose(pose.axis, [1.0, 0.0])
    np.testing.assert_allclose(pose.lateral, [0.0, 1.0])  # the axis turned +90 degrees
    # a point 10 mm along the beam and 3 mm along the lateral direction
    q = pose.to_probe(np.array([[10.0, 33.0]]))
    np.testing.assert_allclose(q, [[3.0, 10.0]], atol=1e-12)
    rng = np.random.default_rng(0)
    tilted = ProbePose(np.array([12.0, -4.0]), np.array([0.3, -0.8]))
    pts = rng.uniform(-50, 50, (20, 2))
    np.testing.assert_allclose(tilted.to_layer(tilted.to_probe(pts)), pts, atol=1e-12)
    assert np.linalg.det(np.stack([tilted.lateral, tilted.axis])) == pytest.approx(-1.0)


def test_pose_rejects_bad_vectors():
    with pytest.raises(ValueError, match="axis must not be zero"):
        ProbePose(np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match="finite 2-vectors"):
        ProbePose(np.array([0.0, np.nan]), np.array([1.0, 0.0]))


def test_image_grid_sizes_and_pixel_round_trip():
    p = probe_params("L11-5v")
    g = image_grid(p, 70.0, 1540.0)
    assert g.dx_mm == pytest.approx(p.pitch_mm / 2)
    assert g.dz_mm == pytest.approx(1540.0 * 1e3 / p.center_frequency_hz / 2)
    assert g.shape == (len(g.depth_mm), 2 * p.n_elements)
    assert g.depth_mm[0] == 0.0 and 70.0 - g.dz_mm < g.depth_mm[-1] <= 70.0
    assert g.lateral_mm[-1] - g.lateral_mm[0] == pytest.approx(p.aperture_mm - g.dx_mm)
    pts = np.array([[1.234, 20.5], [-10.0, 3.3]])
    np.testing.assert_allclose(g.to_mm(g.to_pixel(pts)), pts, atol=1e-12)


def test_bad_speeds_depths_and_points_raise():
    p = probe_params("L11-5v")
    for c in (0.0, -1540.0, float("nan")):
        with pytest.raises(ValueError, match="sound speed must be a positive finite speed"):
            image_grid(p, 70.0, c)
        with pytest.raises(ValueError, match="sound speed"):
            p.pymust_param(c)
    with pytest.raises(ValueError, match="imaging depth must be positive"):
        image_grid(p, 0.0, 1540.0)
    g = ImageGrid(np.arange(5) * 0.15, np.arange(7) * 0.1)
    with pytest.raises(ValueError, match="outside the image"):
        g.require_inside(np.array([0.3, 5.0]), what="target")


def _draw(seed, **kw):
    args = dict(region_mm=np.array([[-10.0, 0.0], [10.0, 20.0]]), density_per_mm2=50.0)
    args.update(kw)
    return draw_scatterers(np.random.default_rng(seed), **args)


def test_scatterer_draw_is_deterministic_and_seed_dependent():
    a, b, c = _draw(1), _draw(1), _draw(2)
    for f in ("positions_mm", "elevation_mm", "amplitude"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert len(a) != len(c) or not np.array_equal(a.positions_mm, c.positions_mm)
    assert a.amplitude.dtype == np.float32


def test_scatterer_density_band_and_gaussian_amplitudes():
    s = _draw(3, elevation_half_mm=1.5)
    n_expected = 50.0 * 400.0
    assert abs(len(s) - n_expected) < 5 * math.sqrt(n_expected)  # Poisson count
    assert np.all((s.positions_mm >= [-10, 0]) & (s.positions_mm <= [10, 20]))
    assert np.all(np.abs(s.elevation_mm) <= 1.5) and s.elevation_mm.std() == pytest.approx(1.5 / math.sqrt(3), rel=0.05)
    assert s.amplitude.mean() == pytest.approx(0.0, abs=0.05)
    assert s.amplitude.std() == pytest.approx(1.0, rel=0.05)
    # neighbours in the arrays are neighbours in space (raster of 1 mm tiles)
    assert np.median(np.hypot(*np.diff(s.positions_mm, axis=0).T)) < 1.0


def test_polygon_region_keeps_only_inside_points():
    tri = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    s = _draw(4, region_mm=tri)
    assert np.all(s.positions_mm.sum(axis=1) <= 10.0 + 1e-9)
    assert abs(len(s) - 50.0 * 50.0) < 5 * math.sqrt(2500.0)


def test_lesion_sphere_and_obstacles_set_echogenicity():
    vessel = np.array([[-8.0, 2.0], [-4.0, 2.0], [-4.0, 6.0], [-8.0, 6.0]])
    plain = _draw(5, elevation_half_mm=2.0)
    s = _draw(5, elevation_half_mm=2.0, lesion_center_mm=np.array([2.0, 10.0]), lesion_radius_mm=3.0,
              lesion_db=-10.0, obstacles=[(vessel, ECHOGENICITY_DB["vessel_lumen"])])
    np.testing.assert_array_equal(plain.positions_mm, s.positions_mm)  # the same draws whatever the contents
    ratio = s.amplitude / np.where(plain.amplitude == 0, 1, plain.amplitude)
    p, y = s.positions_mm, s.elevation_mm
    in_lesion = np.sum((p - [2.0, 10.0]) ** 2, axis=1) + y ** 2 <= 9.0
    in_vessel = (p[:, 0] > -8) & (p[:, 0] < -4) & (p[:, 1] > 2) & (p[:, 1] < 6)
    np.testing.assert_allclose(ratio[in_lesion], 10 ** (-10 / 20), rtol=1e-6)
    np.testing.assert_allclose(ratio[in_vessel], 10 ** (-40 / 20), rtol=1e-6)
    np.testing.assert_allclose(ratio[~in_lesion & ~in_vessel], 1.0, rtol=1e-6)
    # a sphere: points inside the disc but far out of plane are background
    disc_only = (np.sum((p - [2.0, 10.0]) ** 2, axis=1) <= 9.0) & ~in_lesion
    assert disc_only.any() and np.allclose(ratio[disc_only], 1.0)
    anechoic = _draw(5, obstacles=[(vessel, -math.inf)])
    assert np.all(anechoic.amplitude[(anechoic.positions_mm[:, 0] > -8) & (anechoic.positions_mm[:, 0] < -4)
                                     & (anechoic.positions_mm[:, 1] > 2) & (anechoic.positions_mm[:, 1] < 6)] == 0)


def test_scatterer_bad_inputs_raise():
    with pytest.raises(ValueError, match="density must be positive"):
        _draw(0, density_per_mm2=0.0)
    with pytest.raises(ValueError, match="elevation half-width"):
        _draw(0, elevation_half_mm=-1.0)
    with pytest.raises(ValueError, match="region"):
        _draw(0, region_mm=np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="positive width and height"):
        _draw(0, region_mm=np.array([[0.0, 0.0], [0.0, 5.0]]))
    with pytest.raises(ValueError, match="echogenicity"):
        _draw(0, obstacles=[(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), float("nan"))])
