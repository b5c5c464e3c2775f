"""Tests of the SIMUS reference and of the fast model against it (scissor_cli.sensing.ultrasound).

SIMUS costs a few milliseconds per scatterer: single points, a beamformer
check on a few, and one validation patch (about ten seconds); the larger
variants are marked slow.

Thresholds: the fast model's envelope correlates with SIMUS's above 0.93
on a patch of in-plane scatterers (the separable rank-2 PSF, the fitted
splines and the lateral-gain-only edges are its approximations), and the
displacement both give to the block matcher agrees within 0.05 mm.
"""

import numpy as np
import pytest

from scissor_cli.sensing.ultrasound import (
    ImageGrid,
    build_psf,
    fast_frame,
    frame_kernels,
    image_grid,
    probe_params,
    simus_frame,
    validate_fast,
)
from scissor_cli.sensing.ultrasound.simus_ref import beamform, receive_fnumber, simus_iq

ENVELOPE_CORRELATION_MIN = 0.93
TRACKING_DIFFERENCE_MAX_MM = 0.05


@pytest.fixture(scope="module")
def probe():
    return probe_params("L11-5v")


@pytest.fixture(scope="module")
def model(probe):
    psf = build_psf(probe, 1540.0, 40.0)
    grid = image_grid(probe, 40.0, 1540.0)
    return psf, grid, frame_kernels(psf, grid)


def test_beamform_is_pymust_dasmtx(probe):
    import pymust

    rng = np.random.default_rng(0)
    iq = simus_iq(probe, rng.uniform(-3, 3, 12), rng.uniform(20, 26, 12), np.zeros(12), rng.standard_normal(12), 1450.0)
    X, Z = np.meshgrid(np.arange(-15, 16) * 0.15, 19.0 + np.arange(70) * 0.1)
    mine = beamform(iq, probe, X, Z, 1540.0)
    param = probe.pymust_param(1540.0)
    param.fnumber = None
    M = pymust.dasmtx(iq, X * 1e-3, Z * 1e-3, np.zeros((1, probe.n_elements)), param)
    theirs = (M.tocsr() @ iq.flatten(order="F")).reshape(X.shape, order="F")
    assert param.fnumber == pytest.approx(receive_fnumber(probe, 1540.0))
    np.testing.assert_allclose(mine, theirs, atol=1e-9 * np.abs(theirs).max())


@pytest.mark.parametrize("c_t", [1450.0, 1540.0])
def test_simus_point_obeys_the_time_of_flight_law(probe, c_t):
    expected = 50.0 * 1540.0 / c_t  # 53.1 mm for 1450 m/s tissue
    sub = ImageGrid(np.arange(-10, 11) * 0.15, expected - 1.0 + np.arange(21) * 0.1)
    env = simus_frame(probe, sub, np.zeros(1), np.array([50.0]), np.zeros(1), np.ones(1), c_t, 1540.0)
    i = int(np.argmax(env.max(axis=1)))
    col = env.max(axis=1)
    peak = sub.depth_mm[i] + 0.1 * 0.5 * (col[i - 1] - col[i + 1]) / (col[i - 1] - 2 * col[i] + col[i + 1])
    assert peak == pytest.approx(expected, abs=0.05)


def test_fast_point_matches_simus_point(probe, model):
    psf, grid, k = model
    rows, cols = (np.abs(grid.depth_mm - 25.0) < 1.0), (np.abs(grid.lateral_mm - 2.0) < 2.0)
    sub = ImageGrid(grid.lateral_mm[cols], grid.depth_mm[rows])
    ref = simus_frame(probe, sub, np.array([2.03]), np.array([25.02]), np.zeros(1), np.ones(1), 1540.0, 1540.0)
    fast = fast_frame(k, np.array([2.03]), np.array([25.02]), np.zeros(1), np.ones(1), 1540.0)[np.ix_(rows, cols)]
    assert np.corrcoef(ref.ravel(), fast.ravel())[0, 1] > 0.97


def test_fast_model_agrees_with_simus_on_a_patch(probe, model):
    psf, _, k = model
    v = validate_fast(probe, psf, k, np.random.default_rng(7), np.array([1.0, 30.0]), np.array([0.23, 0.17]))
    assert v.envelope_correlation > ENVELOPE_CORRELATION_MIN
    assert v.tracking_difference_mm < TRACKING_DIFFERENCE_MAX_MM
    np.testing.assert_allclose(v.tracked_simus_mm, v.true_mm, atol=0.03)


@pytest.mark.slow
@pytest.mark.parametrize("strain, band", [(np.array([[0.02, 0.01], [0.0, -0.03]]), 0.0), (None, 0.5)],
                         ids=["affine", "elevation-band"])
def test_fast_model_agrees_with_simus_under_strain_and_out_of_plane(probe, model, strain, band):
    psf, _, k = model
    v = validate_fast(probe, psf, k, np.random.default_rng(8), np.array([-1.0, 25.0]), np.array([0.3, -0.25]),
                      strain, elevation_half_mm=band)
    assert v.envelope_correlation > ENVELOPE_CORRELATION_MIN - 0.03 * (band > 0)
    assert v.tracking_difference_mm < TRACKING_DIFFERENCE_MAX_MM
