"""The reference image formation: PyMUST's SIMUS, IQ demodulation and delay-and-sum (docs/ultrasound.md §4).

One frame is one plane wave at 0 degrees (all transmit delays zero), every
element receiving, the RF demodulated to IQ (`pymust.rf2iq`) and
beamformed by delay-and-sum on the image grid (`pymust.dasmtx`, linear
interpolation, receive f-number from the element directivity, pymust's
rule). SIMUS propagates at the tissue's sound speed; the beamformer assumes
the scanner's, so a mismatch moves and blurs echoes as on a real scanner.

SIMUS runs in its 3-D mode (elevation focusing by the element height and
lens) for every call: pymust switches to a 2-D model when every scatterer
has elevation exactly 0, so in-plane scatterers are nudged by a few
nanometres. SIMUS scales its RF by the frequency step, which depends on the
farthest scatterer; `scale_anchor_mm` adds a silent scatterer (reflection
coefficient 0) so that separate calls share one scale.

`beamform` is the same delay-and-sum written directly over the points it is
asked for (the tests compare it with `pymust.dasmtx`): the point-spread
function's windows need many thousand scattered pixels, where building
dasmtx's sparse matrix dominates. SIMUS's cost grows with scatterers x
elements x frequency samples (benchmark bench_ultrasound), so reference
frames are small patches.
"""

from __future__ import annotations

import math

import numpy as np

from scissor_cli.sensing.ultrasound.transducer import ImageGrid, ProbeParams, check_sound_speed

# pymust runs SIMUS in 2-D when all |y| < 1e-9 m; in-plane scatterers get this elevation (m) instead.
_IN_PLANE_Y_M = 2e-9


def _options():
    import pymust  # noqa: PLC0415  (pymust imports matplotlib: only where it is used)

    opt = pymust.utils.Options()
    opt.WaitBar = False
    opt.ParPool = False  # one process, one thread: the caller decides the parallelism
    return opt


def simus_iq(
    probe: ProbeParams,
    lateral_mm: np.ndarray,
    depth_mm: np.ndarray,
    elevation_mm: np.ndarray,
    amplitude: np.ndarray,
    tissue_sound_speed_m_per_s: float,
    scale_anchor_mm: tuple[float, float] | None = None,
) -> np.ndarray:
    """Element IQ signals (T, N) complex of one 0-degree plane wave on scatterers (S,) given in the probe frame (mm).

    Rows are samples at 4 x the centre frequency from t = 0 (the transmit),
    columns the N elements. `scale_anchor_mm` = (lateral, depth) of a silent
    scatterer fixing SIMUS's amplitude scale (module docstring).
    """
    import pymust  # noqa: PLC0415

    c = check_sound_speed(tissue_sound_speed_m_per_s, "tissue sound speed")
    x = np.asarray(lateral_mm, dtype=float).ravel()
    z = np.asarray(depth_mm, dtype=float).ravel()
    y = np.asarray(elevation_mm, dtype=float).ravel()
    rc = np.asarray(amplitude, dtype=float).ravel()
    if not (x.shape == z.shape == y.shape == rc.shape) or x.size == 0:
        raise ValueError("scatterer arrays must be non-empty and of one length")
    if scale_anchor_mm is not None:
        x = np.append(x, scale_anchor_mm[0])
        z = np.append(z, scale_anchor_mm[1])
        y = np.append(y, 0.0)
        rc = np.append(rc, 0.0)
    y_m = np.where(np.abs(y) * 1e-3 < _IN_PLANE_Y_M, _IN_PLANE_Y_M, y * 1e-3)
    param = probe.pymust_param(c)
    delays = np.zeros((1, probe.n_elements))
    rf, _ = pymust.simus(x[None] * 1e-3, y_m[None], z[None] * 1e-3, rc[None], delays, param, _options())
    return pymust.rf2iq(rf, probe.pymust_param(c))


def receive_fnumber(probe: ProbeParams, sound_speed_m_per_s: float) -> float:
    """pymust.dasmtx's receive f-number from the element directivity.

    The acceptance angle is where cos(theta) x sinc(width / lambda_min x
    sin theta) falls to 0.71, lambda_min the wavelength at the top of the
    -6 dB band; f-number = 1 / (2 tan theta). Same search as dasmtx.
    """
    import scipy.optimize  # noqa: PLC0415

    c = check_sound_speed(sound_speed_m_per_s, "sound speed")
    lam_min = c * 1e3 / (probe.center_frequency_hz * (1.0 + probe.fractional_bandwidth / 2.0))
    w = probe.element_width_mm

    def f(th: float) -> float:
        return abs(math.cos(th) * np.sinc(w / lam_min * math.sin(th)) - 0.71)

    alpha = scipy.optimize.fminbound(f, 0.0, math.pi / 2, xtol=math.pi / 100)
    return 1.0 / 2.0 / math.tan(alpha)


def beamform(
    iq: np.ndarray,
    probe: ProbeParams,
    lateral_mm: np.ndarray,
    depth_mm: np.ndarray,
    assumed_sound_speed_m_per_s: float,
    fnumber: float | None = None,
) -> np.ndarray:
    """Delay-and-sum of element IQ (T, N) at points (any shape) mm -> beamformed IQ of that shape, complex.

    pymust.dasmtx's arithmetic for a 0-degree plane wave: transmit path to
    the nearest of dasmtx's 4N interpolated transmit positions, receive path
    to each element, linear interpolation in time, phase rotation by
    exp(i 2 pi fc tau), elements within depth / (2 f-number) laterally.
    """
    c = check_sound_speed(assumed_sound_speed_m_per_s, "assumed sound speed")
    fnum = receive_fnumber(probe, c) if fnumber is None else float(fnumber)
    x = np.asarray(lateral_mm, dtype=float)
    z = np.asarray(depth_mm, dtype=float)
    shape = np.broadcast(x, z).shape
    x, z = np.broadcast_to(x, shape).ravel(), np.broadcast_to(z, shape).ravel()
    N = probe.n_elements
    xe = (np.arange(N) - (N - 1) / 2.0) * probe.pitch_mm
    n_tx = 4 * N
    step = (xe[-1] - xe[0]) / (n_tx - 1)
    k = np.clip(np.rint((x - xe[0]) / step), 0, n_tx - 1)
    d_tx = np.hypot(xe[0] + k * step - x, z)
    fs = 4.0 * probe.center_frequency_hz
    wc = 2.0 * math.pi * probe.center_frequency_hz
    n_t = iq.shape[0]
    out = np.zeros(x.size, dtype=complex)
    chunk = max(1, 200_000 // N)  # bounds the (points, elements) temporaries
    for a in range(0, x.size, chunk):
        xs, zs = x[a:a + chunk, None], z[a:a + chunk, None]
        # only the elements some point of the chunk may use (the f-number's aperture)
        e0, e1 = 0, N
        if fnum > 0:
            reach = zs.max() / 2.0 / fnum
            e0 = int(np.clip(np.searchsorted(xe, xs.min() - reach), 0, N))
            e1 = int(np.clip(np.searchsorted(xe, xs.max() + reach, side="right"), e0, N))
        if e1 == e0:
            continue
        dx = xs - xe[None, e0:e1]
        tau = (d_tx[a:a + chunk, None] + np.hypot(dx, zs)) / (c * 1e3)  # s
        t = tau * fs
        valid = (t >= 0) & (t <= n_t - 2)
        if fnum > 0:
            valid &= np.abs(dx) <= zs / 2.0 / fnum
        t0 = np.floor(np.where(valid, t, 0.0)).astype(np.int64)
        frac = np.where(valid, t - t0, 0.0)
        cols = np.broadcast_to(np.arange(e0, e1), t0.shape)
        v = iq[t0, cols] * (1.0 - frac) + iq[t0 + 1, cols] * frac
        out[a:a + chunk] = np.sum(np.where(valid, v * np.exp(1j * wc * tau), 0.0), axis=1)
    return out.reshape(shape)


def simus_frame(
    probe: ProbeParams,
    grid: ImageGrid,
    lateral_mm: np.ndarray,
    depth_mm: np.ndarray,
    elevation_mm: np.ndarray,
    amplitude: np.ndarray,
    tissue_sound_speed_m_per_s: float,
    assumed_sound_speed_m_per_s: float,
    envelope: bool = True,
) -> np.ndarray:
    """The SIMUS reference frame on a grid: envelope (H, W) float (or the IQ, complex).

    Scatterers (S,) in the probe frame (mm): true depth; SIMUS propagates at
    the tissue's speed, pymust.dasmtx beamforms at the scanner's. Cost grows
    with S x N x the frequency samples: use small patches and small grids.
    """
    import pymust  # noqa: PLC0415

    c_a = check_sound_speed(assumed_sound_speed_m_per_s, "assumed sound speed")
    iq = simus_iq(probe, lateral_mm, depth_mm, elevation_mm, amplitude, tissue_sound_speed_m_per_s)
    X, Z = np.meshgrid(grid.lateral_mm * 1e-3, grid.depth_mm * 1e-3)
    param = probe.pymust_param(c_a)
    param.fnumber = None  # dasmtx: from the element directivity
    M = pymust.dasmtx(iq, X, Z, np.zeros((1, probe.n_elements)), param)
    bf = (M.tocsr() @ iq.flatten(order="F")).reshape(X.shape, order="F")
    return np.abs(bf) if envelope else bf
