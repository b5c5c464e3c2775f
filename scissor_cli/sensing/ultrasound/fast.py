"""The fast B-mode model: scatterers -> envelope on the image grid in milliseconds (docs/ultrasound.md §3).

In the baseband (IQ) domain, after the scanner's carrier is removed, a
frame is a sum over scatterers s with true depth z_s, lateral x_s,
elevation y_s and amplitude a_s:

    IQ(x, z) = G(x, z) sum_s a_s w_s exp(-i 2 k_t z_s) h_z(x - x_s, z - z'_s)

* z'_s = z_s c_a / c_t is the apparent depth: echoes come back at the
  tissue's speed c_t, the scanner converts time to depth with its own c_a;
* k_t = 2 pi f_c / c_t, so the phase follows the true depth and speckle
  moves coherently with the scatterers;
* w_s = exp(-coef(z) y_s^2) exp(-alpha z_s): the elevation beam (a complex
  Gaussian fitted to SIMUS, `psf`) and optional attenuation;
* h_z is the PSF at the pixel's depth, a rank-R separable approximation
  (SVD of the interpolated SIMUS window, R = 2 by default) times its depth
  gain and phase; G is the lateral gain near the array's ends.

Evaluation: splat onto the grid (B-spline weights), one axial and one
lateral convolution per rank with per-row kernels (`fast_compiled`). Noise: a
white complex Gaussian added before the time-gain compensation, its power
10^(-snr/10) x the mean power of the compensated noiseless frame. The
envelope is |IQ|, linear; `log_compress` makes the displayed B-mode.

Not modelled: the lateral defocus of a mismatched sound speed (echoes are
only moved), the frequency downshift of attenuation, changes of the PSF's
shape across the image (only its gain).

What is drawn when: the kernels (`FrameKernels`) are per probe and grid,
built once; the scatterers are per trial; the noise is per frame, from the
caller's generator (always 2 x H x W uniforms when a generator is given,
whatever the noise level).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from scissor_cli.sensing.ultrasound import fast_compiled as kn
from scissor_cli.sensing.ultrasound.psf import PsfModel
from scissor_cli.sensing.ultrasound.transducer import ImageGrid, check_sound_speed

_NEPER_DB = 20.0 / math.log(10.0)


@dataclass(frozen=True)
class FrameKernels:
    """The fast model's per-probe, per-grid tables (float32 kernels of the rank-R separable PSF per image row)."""

    grid: ImageGrid
    assumed_sound_speed_m_per_s: float
    center_frequency_hz: float
    axial_re: np.ndarray  # (R, H, Ka) float32, gain and phase included
    axial_im: np.ndarray
    lateral_re: np.ndarray  # (R, H, Kl) float32
    lateral_im: np.ndarray
    gain_map: np.ndarray  # (H, W) float32
    elevation_coef_re: np.ndarray  # (H,) 1/mm^2, by apparent row
    elevation_coef_im: np.ndarray
    pad_rows: int
    pad_cols: int

    @property
    def rank(self) -> int:
        return self.axial_re.shape[0]

    def window(self, rows: slice, columns: slice) -> "FrameKernels":
        """The tables of a window of this grid (rows and columns of it): frames of only that part of the image.

        A window's frame equals the whole frame's pixels there (the same
        per-row kernels, gains and elevation beam; scatterers outside it
        still reach it through the padding), up to the noise, which is drawn
        for the window's pixels only.
        """
        g = self.grid
        rr = range(*rows.indices(len(g.depth_mm)))
        cc = range(*columns.indices(len(g.lateral_mm)))
        if rr.step != 1 or cc.step != 1 or len(rr) < 2 or len(cc) < 2:
            raise ValueError(f"a window needs at least 2 contiguous rows and columns, got {rows}, {columns}")
        rows, columns = slice(rr.start, rr.stop), slice(cc.start, cc.stop)
        c = np.ascontiguousarray
        return FrameKernels(
            grid=ImageGrid(g.lateral_mm[columns].copy(), g.depth_mm[rows].copy()),
            assumed_sound_speed_m_per_s=self.assumed_sound_speed_m_per_s,
            center_frequency_hz=self.center_frequency_hz,
            axial_re=c(self.axial_re[:, rows]), axial_im=c(self.axial_im[:, rows]),
            lateral_re=c(self.lateral_re[:, rows]), lateral_im=c(self.lateral_im[:, rows]),
            gain_map=c(self.gain_map[rows, columns]), elevation_coef_re=c(self.elevation_coef_re[rows]),
            elevation_coef_im=c(self.elevation_coef_im[rows]), pad_rows=self.pad_rows, pad_cols=self.pad_cols,
        )


def _bspline3(x: np.ndarray) -> np.ndarray:
    a = np.abs(x)
    return np.where(a < 1, 2 / 3 - a ** 2 + a ** 3 / 2, np.where(a < 2, (2 - a) ** 3 / 6, 0.0))


def _bspline1(x: np.ndarray) -> np.ndarray:
    return np.clip(1.0 - np.abs(x), 0.0, None)


def _spline_fit(offsets_mm: np.ndarray, profiles: np.ndarray, pixel_mm: float, half: int, basis) -> np.ndarray:
    """Kernels (..., 2 half + 1) whose spline sum_m k[m] B(v - m) fits profiles (..., n) sampled at offsets_mm (n,).

    Least squares over 16 sub-pixel offsets per pixel of the kernel's
    reach, the profile taken as 0 outside its window.
    """
    m = np.arange(-half, half + 1)
    reach = half + 2
    v = np.linspace(-reach, reach, 2 * reach * 16 + 1)
    B = basis(v[:, None] - m[None, :])
    u = v * pixel_mm
    inside = (u >= offsets_mm[0]) & (u <= offsets_mm[-1])
    # linear interpolation of every profile at u (offsets_mm is uniform)
    step = offsets_mm[1] - offsets_mm[0]
    pos = np.clip((u - offsets_mm[0]) / step, 0, len(offsets_mm) - 1.000001)
    i0 = np.floor(pos).astype(int)
    f = pos - i0
    samples = (profiles[..., i0] * (1 - f) + profiles[..., i0 + 1] * f) * inside
    return samples @ np.linalg.pinv(B).T


def frame_kernels(psf: PsfModel, grid: ImageGrid, rank: int = 2) -> FrameKernels:
    """The fast model's tables for one PSF and one grid (the grid's depth is apparent at the PSF's sound speed).

    Per image row: the PSF window interpolated linearly in depth, its rank-R
    SVD, each factor fitted in the splat's spline basis (cubic axially,
    linear laterally); the depth gain and phase go into the axial kernel.
    """
    if rank < 1:
        raise ValueError(f"PSF rank must be at least 1, got {rank}")
    if grid.depth_mm[-1] > psf.depths_mm[-1]:
        raise ValueError(f"the grid reaches {grid.depth_mm[-1]:.1f} mm, the PSF was measured to "
                         f"{psf.depths_mm[-1]:.1f} mm: build it for the imaging depth")
    lam = psf.sound_speed_m_per_s * 1e3 / psf.center_frequency_hz
    z = grid.depth_mm
    d = psf.depths_mm
    pos = np.clip(np.interp(z, d, np.arange(len(d))), 0, len(d) - 1.000001)
    i0 = np.floor(pos).astype(int)
    f = (pos - i0)[:, None, None]
    win = psf.windows[i0] * (1 - f) + psf.windows[i0 + 1] * f  # (H, nz, nx)
    U, s, Vh = np.linalg.svd(win, full_matrices=False)
    rank = min(rank, s.shape[1])
    # axial reach 2.5 wavelengths, lateral 85 % of the window: the main lobes and the first sidelobes
    half_ax = int(math.ceil(2.5 * lam / grid.dz_mm - 1e-9))
    half_lat = int(math.ceil(0.85 * psf.window_lateral_mm[-1] / grid.dx_mm))
    ax = np.moveaxis(U[:, :, :rank] * s[:, None, :rank], 2, 0)  # (R, H, nz)
    lat = np.moveaxis(Vh[:, :rank, :], 1, 0)  # (R, H, nx)
    k_ax = _spline_fit(psf.window_axial_mm, ax, grid.dz_mm, half_ax, _bspline3)
    k_lat = _spline_fit(psf.window_lateral_mm, lat, grid.dx_mm, half_lat, _bspline1)
    depth_factor = np.interp(z, d, psf.gain) * np.exp(1j * np.interp(z, d, psf.phase_rad))
    k_ax = k_ax * depth_factor[None, :, None]

    # lateral gain: 1 on the axis, the measured ratios beyond, clamped at the last sample depths/positions
    pos_mm = np.concatenate([[0.0], psf.lateral_gain_positions_mm])
    table = np.concatenate([np.ones((len(psf.lateral_gain_depths_mm), 1)), psf.lateral_gain], axis=1)
    per_depth = np.stack([np.interp(z, psf.lateral_gain_depths_mm, table[:, j]) for j in range(len(pos_mm))], 1)
    ax_abs = np.abs(grid.lateral_mm)
    gain_map = np.stack([np.interp(ax_abs, pos_mm, row) for row in per_depth]).astype(np.float32)

    coef = np.interp(z, d, psf.elevation_coef_per_mm2.real) + 1j * np.interp(z, d, psf.elevation_coef_per_mm2.imag)
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    return FrameKernels(
        grid=grid, assumed_sound_speed_m_per_s=psf.sound_speed_m_per_s,
        center_frequency_hz=psf.center_frequency_hz,
        axial_re=f32(k_ax.real), axial_im=f32(k_ax.imag), lateral_re=f32(k_lat.real), lateral_im=f32(k_lat.imag),
        gain_map=gain_map, elevation_coef_re=np.ascontiguousarray(coef.real),
        elevation_coef_im=np.ascontiguousarray(coef.imag),
        pad_rows=half_ax + 3, pad_cols=half_lat + 2,
    )


def fast_frame(
    kernels: FrameKernels,
    lateral_mm: np.ndarray,
    depth_mm: np.ndarray,
    elevation_mm: np.ndarray,
    amplitude: np.ndarray,
    tissue_sound_speed_m_per_s: float,
    snr_db: float | None = None,
    rng: np.random.Generator | None = None,
    attenuation_db_per_cm_mhz: float = 0.0,
    noise_reference_power: float | None = None,
) -> np.ndarray:
    """Envelope (H, W) float32, linear, of scatterers (S,): probe-frame lateral, true depth, elevation mm; amplitude.

    `snr_db` sets the electronic noise (None: none); the normals come from
    `rng` (required with snr_db). The noise power is 10^(-snr/10) times
    `noise_reference_power` (the compensated signal power, |IQ|^2; default:
    this frame's own mean), so frames of a window can share the whole
    image's level. Attenuation (dB/cm/MHz, two-way, at the centre
    frequency) is compensated by an ideal time-gain on apparent depth.
    """
    c_t = check_sound_speed(tissue_sound_speed_m_per_s, "tissue sound speed")
    if snr_db is not None and rng is None:
        raise ValueError("a noise level (snr_db) needs a random generator (rng)")
    if noise_reference_power is not None and not (math.isfinite(noise_reference_power) and noise_reference_power >= 0):
        raise ValueError(f"the noise's reference power must be finite and >= 0, got {noise_reference_power!r}")
    if not (math.isfinite(attenuation_db_per_cm_mhz) and attenuation_db_per_cm_mhz >= 0):
        raise ValueError(f"attenuation must be >= 0 dB/cm/MHz, got {attenuation_db_per_cm_mhz!r}")
    lat = np.ascontiguousarray(lateral_mm, dtype=np.float64)
    dep = np.ascontiguousarray(depth_mm, dtype=np.float64)
    ele = np.ascontiguousarray(elevation_mm, dtype=np.float64)
    amp = np.ascontiguousarray(amplitude, dtype=np.float32)
    if not (lat.shape == dep.shape == ele.shape == amp.shape and lat.ndim == 1):
        raise ValueError(f"scatterer arrays must be (S,) alike, got {lat.shape}, {dep.shape}, {ele.shape}, {amp.shape}")
    k = kernels
    g = k.grid
    H, W = g.shape
    c_a = k.assumed_sound_speed_m_per_s
    f_mhz = k.center_frequency_hz * 1e-6
    atten = 2.0 * attenuation_db_per_cm_mhz * f_mhz / 10.0 / _NEPER_DB  # two-way amplitude, 1/mm
    S = lat.size
    u = np.empty(S, np.float32)
    v = np.empty(S, np.float32)
    phase = np.empty(S, np.float32)
    log_mag = np.empty(S, np.float32)
    two_k = 2.0 * 2.0 * math.pi * k.center_frequency_hz / (c_t * 1e3)
    mapping = (c_a / c_t, 1.0 / g.dz_mm, k.pad_rows - g.depth_mm[0] / g.dz_mm, float(g.lateral_mm[0]), 1.0 / g.dx_mm,
               float(k.pad_cols), two_k, atten, float(k.pad_rows))
    bad = kn.scatterer_terms((lat, dep, ele, amp), mapping, (k.elevation_coef_re, k.elevation_coef_im),
                             (u, v, phase, log_mag))
    if bad:
        raise ValueError(f"{bad} scatterers have a non-finite position or amplitude")
    rows, cols = H + 2 * k.pad_rows, W + 2 * k.pad_cols
    grid = np.zeros(rows * 2 * cols, np.float32)
    kn.splat(u, v, amp, np.cos(phase), np.sin(phase), np.exp(log_mag), grid, rows, cols)
    g_re = np.empty((rows, cols), np.float32)
    g_im = np.empty((rows, cols), np.float32)
    kn.deinterleave(grid.reshape(rows, 2 * cols), g_re, g_im)
    out_re = np.zeros((H, W), np.float32)
    out_im = np.zeros((H, W), np.float32)
    a_re = np.empty((H, cols), np.float32)
    a_im = np.empty((H, cols), np.float32)
    half_ax = (k.axial_re.shape[2] - 1) // 2
    half_lat = (k.lateral_re.shape[2] - 1) // 2
    for r in range(k.rank):
        a_re.fill(0.0)
        a_im.fill(0.0)
        kn.convolve_axial(g_re, g_im, k.axial_re[r], k.axial_im[r], a_re, a_im, k.pad_rows - half_ax)
        kn.convolve_lateral(a_re, a_im, k.lateral_re[r], k.lateral_im[r], out_re, out_im, k.pad_cols - half_lat)
    tgc = np.exp(atten * g.depth_mm).astype(np.float32)
    envelope = np.empty((H, W), np.float32)
    noise = np.empty((0, 0, 0), np.float32)
    std = 0.0
    if rng is not None:
        noise = complex_normals(rng, (H, W))
        if snr_db is not None:
            power = (kn.signal_power(out_re, out_im, k.gain_map, tgc) if noise_reference_power is None
                     else float(noise_reference_power))
            std = math.sqrt(power * 10.0 ** (-snr_db / 10.0) / 2.0) if math.isfinite(snr_db) else 0.0
    kn.finish(out_re, out_im, k.gain_map, tgc, noise, np.float32(std), envelope)
    return envelope


def complex_normals(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """(2, *shape) float32 independent standard normals (real and imaginary planes) by the Box-Muller transform.

    Two float32 uniforms per complex sample: numpy's float32 uniforms and
    transcendental functions are vectorised, its normal sampler is not
    (a frame needs hundreds of thousands of normals).
    """
    u = rng.random((2, *shape), dtype=np.float32)
    r, t = u[0], u[1]
    np.subtract(np.float32(1.0), r, out=r)  # 1 - u in (0, 1]: its logarithm is finite
    np.log(r, out=r)
    r *= np.float32(-2.0)
    np.sqrt(r, out=r)
    t *= np.float32(2.0 * math.pi)
    out = np.empty_like(u)
    np.cos(t, out=out[0])
    np.sin(t, out=out[1])
    out *= r
    return out


def log_compress(envelope: np.ndarray, dynamic_range_db: float = 50.0, reference: float | None = None) -> np.ndarray:
    """B-mode in dB (H, W) float32: 20 log10(envelope / reference) clipped to [-dynamic_range_db, 0].

    reference defaults to the frame's maximum.
    """
    if not (math.isfinite(dynamic_range_db) and dynamic_range_db > 0):
        raise ValueError(f"dynamic range must be positive, got {dynamic_range_db!r} dB")
    e = np.asarray(envelope, dtype=np.float32)
    ref = float(e.max()) if reference is None else float(reference)
    if not ref > 0:
        return np.full(e.shape, -dynamic_range_db, np.float32)
    floor = ref * 10.0 ** (-dynamic_range_db / 20.0)
    return (20.0 * np.log10(np.maximum(e, floor) / ref)).astype(np.float32)
