"""Tests of the fast B-mode model and the speckle tracking on its frames (scissor_cli.sensing.ultrasound).

One PSF is measured on SIMUS for the module (L11-5v, 60 mm); the frames
are full images at the default scatterer density. Checks: determinism,
Rayleigh statistics, the time-of-flight law, elevation decorrelation,
noise and time-gain, the PSF cache round trip, rigid and smooth-motion
tracking, first-frame localisation, and the bad inputs.
"""

import math

import numpy as np
import pytest

from scissor_cli.sensing.ultrasound import (
    PsfModel,
    SpeckleTracker,
    block_match,
    build_psf,
    draw_scatterers,
    elevation_width_mm,
    fast_frame,
    frame_kernels,
    image_grid,
    localise_lesion,
    log_compress,
    probe_params,
)

DEPTH_MM = 60.0
RAYLEIGH_MEAN_OVER_STD = math.sqrt(math.pi / (4 - math.pi))  # 1.913


@pytest.fixture(scope="module")
def model():
    probe = probe_params("L11-5v")
    psf = build_psf(probe, 1540.0, DEPTH_MM)
    grid = image_grid(probe, DEPTH_MM, 1540.0)
    return probe, psf, grid, frame_kernels(psf, grid)


def tissue(model, seed, lesion=(0.0, 30.0), radius=2.0, db=-10.0, band=0.0, per_cell=20.0):
    """Scatterers (probe frame = layer frame here) over the image and a margin, with a lesion."""
    _, psf, grid, _ = model
    region = np.array([[grid.lateral_mm[0] - 1.5, -1.0], [grid.lateral_mm[-1] + 1.5, grid.depth_mm[-1] + 1.0]])
    rng = np.random.default_rng(seed)
    scale = max(1.0, 2 * band / 0.7)  # keep the in-beam density when the band is wide
    return draw_scatterers(rng, region, psf.density_per_mm2(per_cell) * scale, band,
                           None if lesion is None else np.array(lesion), radius, db)


def image(model, sc, positions=None, elevation=None, c_t=1540.0, **kw):
    p = sc.positions_mm if positions is None else positions
    y = sc.elevation_mm if elevation is None else elevation
    return fast_frame(model[3], p[:, 0], p[:, 1], y, sc.amplitude, c_t, **kw)


def test_frames_are_deterministic_and_seed_dependent(model):
    sc = tissue(model, 1)
    a = image(model, sc, snr_db=30.0, rng=np.random.default_rng(9))
    b = image(model, sc, snr_db=30.0, rng=np.random.default_rng(9))
    assert a.dtype == np.float32 and a.shape == model[2].shape
    np.testing.assert_array_equal(a, b)
    c = image(model, tissue(model, 2), snr_db=30.0, rng=np.random.default_rng(9))
    # speckle of another draw: uncorrelated once the common gains (and the lesion) are left out
    assert abs(np.corrcoef(_speckle(a).ravel(), _speckle(c).ravel())[0, 1]) < 0.05


def _speckle(env):
    """The envelope 10-25 mm deep (above the lesion), central columns, each row centred and scaled."""
    e = env[100:250, 64:192].astype(float)
    return (e - e.mean(axis=1, keepdims=True)) / e.std(axis=1, keepdims=True)


def test_pure_speckle_is_rayleigh(model):
    grid = model[2]
    env = image(model, tissue(model, 3, lesion=None)).astype(float)
    region = env[(grid.depth_mm > 15) & (grid.depth_mm < 55)][:, np.abs(grid.lateral_mm) < 12]
    region = region / np.sqrt(np.mean(region ** 2, axis=1, keepdims=True))  # remove the depth gain row by row
    # 20 scatterers per cell with Gaussian amplitudes sit a little below the Rayleigh limit
    assert region.mean() / region.std() == pytest.approx(RAYLEIGH_MEAN_OVER_STD, abs=0.06)


def _peak_depth(env, grid):
    i, j = np.unravel_index(int(np.argmax(env)), env.shape)
    c = env[i - 1:i + 2, j].astype(float)
    return grid.depth_mm[i] + grid.dz_mm * 0.5 * (c[0] - c[2]) / (c[0] - 2 * c[1] + c[2])


@pytest.mark.parametrize("c_t", [1450.0, 1540.0, 1600.0])
def test_time_of_flight_scales_apparent_depth(model, c_t):
    grid, k = model[2], model[3]
    env = fast_frame(k, np.array([0.0]), np.array([50.0]), np.zeros(1), np.ones(1), c_t)
    # 1450 m/s in tissue, 1540 m/s in the scanner: a point at 50 mm shows 3.1 mm deeper
    assert _peak_depth(env, grid) == pytest.approx(50.0 * 1540.0 / c_t, abs=0.05)


def test_elevation_motion_decorrelates_speckle(model):
    probe, psf, grid, k = model
    sc = tissue(model, 4, lesion=None, band=3.0, per_cell=10.0)
    rows = (grid.depth_mm > 28) & (grid.depth_mm < 32)
    flat = lambda e: e / e.mean(axis=1, keepdims=True)  # noqa: E731  (the depth gain's trend would add correlation)
    ref = flat(image(model, sc)[rows].astype(float) ** 2)
    coef = complex(np.interp(30.0, grid.depth_mm, k.elevation_coef_re),
                   np.interp(30.0, grid.depth_mm, k.elevation_coef_im))
    fwhm = float(psf.elevation_fwhm_mm(30.0))
    for d in (0.1 * fwhm, 0.25 * fwhm, 0.5 * fwhm):
        moved = flat(image(model, sc, elevation=sc.elevation_mm + d)[rows].astype(float) ** 2)
        # intensity correlation of a shifted complex-Gaussian beam exp(-(a + ib) y^2): exp(-d^2 (a^2 + b^2) / a)
        theory = math.exp(-d * d * abs(coef) ** 2 / coef.real)
        assert np.corrcoef(ref.ravel(), moved.ravel())[0, 1] == pytest.approx(theory, abs=0.1)
    # SIMUS's beam (fitted) and the Gaussian-beam formula agree on the thickness near the focus
    w = float(elevation_width_mm(probe, 1540.0, probe.elevation_focus_mm))
    assert float(psf.elevation_fwhm_mm(probe.elevation_focus_mm)) == pytest.approx(1.18 * w, rel=0.35)


def test_noise_level_follows_snr_and_tgc_compensates_attenuation(model):
    grid = model[2]
    sc = tissue(model, 5, lesion=None)
    clean = image(model, sc).astype(float)
    noisy = image(model, sc, snr_db=10.0, rng=np.random.default_rng(0)).astype(float)
    assert np.mean(noisy ** 2) / np.mean(clean ** 2) == pytest.approx(1.1, abs=0.01)
    attenuated = image(model, sc, attenuation_db_per_cm_mhz=0.5).astype(float)
    rows = (grid.depth_mm > 5) & (grid.depth_mm < 55)
    ratio = np.mean(attenuated[rows] ** 2, axis=1) / np.mean(clean[rows] ** 2, axis=1)
    assert np.all(np.abs(ratio - 1.0) < 0.05)
    # the noise enters before the time-gain compensation: deep rows are noisier
    noisy_att = image(model, sc, snr_db=30.0, rng=np.random.default_rng(0), attenuation_db_per_cm_mhz=0.5)
    excess = np.mean(noisy_att.astype(float) ** 2, axis=1) / np.mean(clean ** 2, axis=1) - 1
    assert excess[grid.depth_mm > 50].mean() > 10 * excess[(grid.depth_mm > 10) & (grid.depth_mm < 15)].mean()


def test_psf_survives_its_cache_arrays(model):
    _, psf, grid, k = model
    again = PsfModel.from_arrays({name: np.array(a) for name, a in psf.to_arrays().items()})
    sc = tissue(model, 6)
    np.testing.assert_array_equal(image(model, sc), image((None, None, grid, frame_kernels(again, grid)), sc))


def test_log_compress_range():
    env = np.array([[0.0, 1e-6, 0.5, 1.0]], np.float32)
    b = log_compress(env, 40.0)
    np.testing.assert_allclose(b, [[-40.0, -40.0, 20 * np.log10(0.5), 0.0]], atol=1e-5)
    with pytest.raises(ValueError, match="dynamic range"):
        log_compress(env, 0.0)


@pytest.mark.parametrize("shift", [(0.037, 0.051), (-0.11, 0.023), (0.21, -0.077), (0.0, 0.33), (-0.42, -0.19)])
def test_rigid_subpixel_shifts_are_tracked(model, shift):
    grid = model[2]
    sc = tissue(model, 7)
    rng = np.random.default_rng(1)
    ref = image(model, sc, snr_db=30.0, rng=rng)
    cur = image(model, sc, positions=sc.positions_mm + np.array(shift), snr_db=30.0, rng=rng)
    d, peak = block_match(ref, cur, grid, np.array([0.0, 30.0]))
    assert peak > 0.7
    np.testing.assert_allclose(d, shift, atol=0.02)


#: the tracked lesion's rest position (mm), the centre of the deformations below
LESION_MM = (0.0, 30.0)


def _affine(p, t):
    a = np.array([[0.03, 0.02], [-0.01, -0.05]])  # a few % strain and shear
    return p + t * ((p - np.array(LESION_MM)) @ a.T + np.array([3.0, 4.0]))


def _bump(p, t):
    w = np.exp(-np.sum((p - np.array(LESION_MM) - np.array([-4.0, 3.0])) ** 2, axis=1) / (2 * 15.0 ** 2))
    return p + t * w[:, None] * np.array([6.0, 4.0])


@pytest.mark.parametrize("field", [_affine, _bump], ids=["affine", "gaussian-bump"])
def test_smooth_deformation_sequence_is_tracked(model, field):
    grid = model[2]
    sc = tissue(model, 8)
    rng = np.random.default_rng(2)
    c = np.array(LESION_MM)
    tracker = SpeckleTracker(image(model, sc, snr_db=30.0, rng=rng), grid, c)
    errors = []
    for k in range(1, 21):
        est = tracker.update(image(model, sc, positions=field(sc.positions_mm, k / 20), snr_db=30.0, rng=rng))
        errors.append(np.hypot(*(est.position_mm - field(c[None], k / 20)[0])))
    assert np.hypot(*(field(c[None], 1.0)[0] - c)) >= 5.0  # the lesion moves several mm
    assert np.percentile(errors, 95) <= 0.1


def test_first_frame_localisation(model):
    grid = model[2]
    errors = []
    for seed in range(6):
        rr = np.random.default_rng(100 + seed)
        true = np.array([rr.uniform(-5, 5), rr.uniform(20, 45)])
        env = image(model, tissue(model, 20 + seed, lesion=true), snr_db=30.0, rng=rr)
        est = localise_lesion(env, grid, true + rr.uniform(-1.5, 1.5, 2), 2.0)
        errors.append(np.hypot(*(est - true)))
    # speckle limits the precision of a -10 dB, 2 mm disc to about a tenth of a mm
    assert np.sqrt(np.mean(np.square(errors))) <= 0.15 and max(errors) <= 0.3
    # a hyperechoic lesion is a bright disc
    true = np.array([1.3, 33.2])
    env = image(model, tissue(model, 30, lesion=true, db=6.0), snr_db=30.0, rng=np.random.default_rng(3))
    assert np.hypot(*(localise_lesion(env, grid, true + 0.8, 2.0, lesion_db=6.0) - true)) <= 0.3


def test_bad_inputs_raise(model):
    grid, k = model[2], model[3]
    one = np.ones(1)
    with pytest.raises(ValueError, match="tissue sound speed must be a positive finite speed"):
        fast_frame(k, one, one, one, one, 0.0)
    with pytest.raises(ValueError, match="needs a random generator"):
        fast_frame(k, one, one, one, one, 1540.0, snr_db=30.0)
    with pytest.raises(ValueError, match="alike"):
        fast_frame(k, one, np.ones(2), one, one, 1540.0)
    with pytest.raises(ValueError, match="1 scatterers have a non-finite position or amplitude"):
        fast_frame(k, np.array([0.0, np.nan]), np.ones(2), np.zeros(2), np.ones(2), 1540.0)
    empty = np.zeros(0)
    assert not fast_frame(k, empty, empty, empty, empty, 1540.0).any()  # no tissue, no echo
    far = fast_frame(k, np.array([0.0, 1e30]), np.array([1e30, 30.0]), np.zeros(2), np.ones(2), 1540.0)
    assert not far.any()  # both outside the image
    with pytest.raises(ValueError, match="attenuation"):
        fast_frame(k, one, one, one, one, 1540.0, attenuation_db_per_cm_mhz=-1.0)
    env = np.ones(grid.shape, np.float32)
    with pytest.raises(ValueError, match="outside the image"):
        block_match(env, env, grid, np.array([25.0, 30.0]))
    with pytest.raises(ValueError, match="outside the image"):
        localise_lesion(env, grid, np.array([0.0, 80.0]), 2.0)
    with pytest.raises(ValueError, match="leaves the image"):
        localise_lesion(env, grid, np.array([0.0, 1.0]), 2.0)
    with pytest.raises(ValueError, match="no contrast"):
        localise_lesion(env, grid, np.array([0.0, 30.0]), 2.0, lesion_db=0.0)
    with pytest.raises(ValueError, match="shape"):
        SpeckleTracker(env[:10], grid, np.array([0.0, 30.0]))
    with pytest.raises(ValueError, match="sound speed"):
        build_psf("L11-5v", -1.0, 60.0)
    with pytest.raises(ValueError, match="build it for the imaging depth"):
        frame_kernels(model[1], image_grid(model[0], 90.0, 1540.0))
