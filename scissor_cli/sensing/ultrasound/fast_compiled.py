"""Compiled (numba) loops of the fast B-mode model: scatterer terms, splatting, convolution (docs/ultrasound.md §3).

`fast.fast_frame` calls them in this order:

1. `scatterer_terms`: each scatterer's grid position (u rows, v columns,
   apparent depth) and the phase and log-magnitude of its baseband
   coefficient. The trigonometry and the exponential stay in numpy, whose
   float32 versions are vectorised (numba calls the scalar libm ones).
2. `splat`: the coefficients onto the padded grid with cubic B-spline
   weights axially and linear ones laterally (8 complex updates per
   scatterer). The convolution kernels are least-squares fits in those
   spline bases, so the sum is the PSF at the scatterer's exact sub-pixel
   offset, up to the fit error, and speckle moves smoothly with the tissue.
3. `convolve_axial` / `convolve_lateral`: one kernel per output row (the
   PSF changes with depth), complex, on split real and imaginary planes
   so that the inner loops over a row vectorise.
4. `finish`: lateral gain, electronic noise, time-gain compensation, |IQ|.

Compiled on first use and cached on disk next to this file (numba's
`cache=True`); fastmath lets the row loops vectorise. Non-finite input is
caught by `scatterer_terms` (compiled without fastmath), so none reaches
the other loops.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(cache=True, nogil=True, fastmath=True, boundscheck=False)


# no fastmath here: this loop is where non-finite input is caught, and fastmath may assume there is none
@njit(cache=True, nogil=True, boundscheck=False)
def scatterer_terms(scatterers, mapping, elevation_coef, out):
    """Grid coordinates (S,) float32 and the coefficient's phase (rad, wrapped) and log-magnitude of each scatterer.

    scatterers: (lateral_mm, depth_mm, elevation_mm, amplitude) (S,) each;
    mapping: (depth_scale, inv_dz, u_offset, lateral0_mm, inv_dx, v_offset,
    two_k_per_mm, atten_per_mm, pad_rows), the grid's and the pulse's
    numbers; elevation_coef: (coef_re, coef_im) per padded row; out: (u, v,
    phase, log_mag) (S,) float32, written.

    u = apparent depth in padded rows, v = lateral in padded columns (both
    clamped to a range whose integer part is safe); the coefficient is
    exp(-atten z) exp(-coef(row) y^2) exp(-i 2 k z), z the true depth, y the
    elevation, coef looked up by the apparent row. Returns the number of
    scatterers with a non-finite position or amplitude (then the outputs
    are not to be used).
    """
    lateral_mm, depth_mm, elevation_mm, amplitude = scatterers
    depth_scale, inv_dz, u_offset, lateral0_mm, inv_dx, v_offset, two_k_per_mm, atten_per_mm, pad_rows = mapping
    coef_re, coef_im = elevation_coef
    u, v, phase, log_mag = out
    n_rows = coef_re.shape[0]
    two_pi = 2.0 * math.pi
    bad = 0
    for s in range(lateral_mm.shape[0]):
        z = depth_mm[s]
        x = lateral_mm[s]
        y = elevation_mm[s]
        if not (math.isfinite(z) and math.isfinite(x) and math.isfinite(y) and math.isfinite(amplitude[s])):
            bad += 1
            continue
        uu = min(max(z * depth_scale * inv_dz + u_offset, -8.0), 1.0e7)
        u[s] = uu
        v[s] = min(max((x - lateral0_mm) * inv_dx + v_offset, -8.0), 1.0e7)
        p = two_k_per_mm * z
        lm = -atten_per_mm * z
        if y != 0.0:
            row = min(max(int(uu - pad_rows + 0.5), 0), n_rows - 1)
            y2 = y * y
            lm -= coef_re[row] * y2
            p += coef_im[row] * y2
        phase[s] = p - two_pi * math.floor(p / two_pi)
        log_mag[s] = max(lm, -80.0)  # exp underflows to 0 well before; keeps the float32 exponential finite
    return bad


@njit(**_JIT)
def splat(u_px, v_px, amplitude, cos_p, sin_p, mag, grid, n_rows, n_cols):
    """Add every scatterer's coefficient amplitude*mag*exp(-i phase) to the flat interleaved grid (rows x 2 cols).

    Cubic B-spline weights on the 4 rows around u, linear on the 2 columns
    around v; scatterers whose stencil leaves the padded grid are skipped.
    """
    w2 = 2 * n_cols
    sixth = np.float32(1.0 / 6.0)
    two_thirds = np.float32(2.0 / 3.0)
    half = np.float32(0.5)
    one = np.float32(1.0)
    for s in range(u_px.shape[0]):
        u = u_px[s]
        w = v_px[s]
        if u < 1.0 or w < 0.0:
            continue
        iu = int(u)
        iv = int(w)
        if iu < 1 or iv < 0 or iu + 2 >= n_rows or iv + 1 >= n_cols:
            continue
        tu = u - np.float32(iu)
        tv = w - np.float32(iv)
        m = amplitude[s] * mag[s]
        cr = m * cos_p[s]
        ci = -m * sin_p[s]
        su = one - tu
        tu2 = tu * tu
        a0 = su * su * su * sixth
        a3 = tu2 * tu * sixth
        a1 = two_thirds - tu2 + half * tu2 * tu
        a2 = one - a0 - a1 - a3
        x0r = (one - tv) * cr
        x0i = (one - tv) * ci
        x1r = tv * cr
        x1i = tv * ci
        k = (iu - 1) * w2 + 2 * iv
        grid[k] += a0 * x0r
        grid[k + 1] += a0 * x0i
        grid[k + 2] += a0 * x1r
        grid[k + 3] += a0 * x1i
        k += w2
        grid[k] += a1 * x0r
        grid[k + 1] += a1 * x0i
        grid[k + 2] += a1 * x1r
        grid[k + 3] += a1 * x1i
        k += w2
        grid[k] += a2 * x0r
        grid[k + 1] += a2 * x0i
        grid[k + 2] += a2 * x1r
        grid[k + 3] += a2 * x1i
        k += w2
        grid[k] += a3 * x0r
        grid[k + 1] += a3 * x0i
        grid[k + 2] += a3 * x1r
        grid[k + 3] += a3 * x1i


@njit(**_JIT)
def deinterleave(grid, re, im):
    """Split an interleaved (rows, 2 cols) float32 grid into real and imaginary planes (rows, cols)."""
    rows, cols = re.shape
    for i in range(rows):
        g = grid[i]
        r = re[i]
        q = im[i]
        for j in range(cols):
            r[j] = g[2 * j]
            q[j] = g[2 * j + 1]


@njit(**_JIT)
def convolve_axial(in_re, in_im, k_re, k_im, out_re, out_im, offset):
    """out[i] += sum_t k[i, t] in[i + offset + K - 1 - t] over rows, complex; K taps per output row i."""
    rows = out_re.shape[0]
    cols = out_re.shape[1]
    taps = k_re.shape[1]
    for i in range(rows):
        o_r = out_re[i]
        o_i = out_im[i]
        for t in range(taps):
            a = k_re[i, t]
            b = k_im[i, t]
            r = i + offset + taps - 1 - t
            x_r = in_re[r]
            x_i = in_im[r]
            for j in range(cols):
                o_r[j] += a * x_r[j] - b * x_i[j]
                o_i[j] += a * x_i[j] + b * x_r[j]


@njit(**_JIT)
def convolve_lateral(in_re, in_im, k_re, k_im, out_re, out_im, offset):
    """out[i, j] += sum_t k[i, t] in[i, j + offset + K - 1 - t], complex; K taps per row i."""
    rows = out_re.shape[0]
    cols = out_re.shape[1]
    taps = k_re.shape[1]
    for i in range(rows):
        o_r = out_re[i]
        o_i = out_im[i]
        for t in range(taps):
            a = k_re[i, t]
            b = k_im[i, t]
            c0 = offset + taps - 1 - t
            x_r = in_re[i, c0:c0 + cols]
            x_i = in_im[i, c0:c0 + cols]
            for j in range(cols):
                o_r[j] += a * x_r[j] - b * x_i[j]
                o_i[j] += a * x_i[j] + b * x_r[j]


@njit(**_JIT)
def signal_power(re, im, gain_map, tgc):
    """Mean of |IQ x gain x tgc|^2 over the frame (the reference of the noise level)."""
    rows, cols = re.shape
    total = 0.0
    for i in range(rows):
        t2 = tgc[i] * tgc[i]
        acc = 0.0
        for j in range(cols):
            g = gain_map[i, j]
            acc += (re[i, j] * re[i, j] + im[i, j] * im[i, j]) * g * g
        total += acc * t2
    return total / (rows * cols)


@njit(**_JIT)
def finish(re, im, gain_map, tgc, noise, noise_std, envelope):
    """envelope = |IQ x gain + noise_std x (n_re + i n_im)| x tgc; noise (2, rows, cols) or empty for none."""
    rows, cols = re.shape
    with_noise = noise.shape[0] == 2
    for i in range(rows):
        t = tgc[i]
        e = envelope[i]
        for j in range(cols):
            g = gain_map[i, j]
            a = re[i, j] * g
            b = im[i, j] * g
            if with_noise:
                a += noise_std * noise[0, i, j]
                b += noise_std * noise[1, i, j]
            e[j] = math.sqrt(a * a + b * b) * t
