"""The fast model's point-spread function, measured once per probe on SIMUS (docs/ultrasound.md §3).

Single point scatterers are simulated with SIMUS (0-degree plane wave) and
beamformed on small windows around them, exactly as a reference frame is
(`simus_ref`). From these, per sample depth (every `DEPTH_STEP_MM`):

* the baseband (IQ) window around the point, demodulated by the scanner's
  carrier exp(-i 2 k_a dz), normalised to 1 at its centre (D, nz, nx);
* the centre's gain and phase (D,): the elevation lens makes both vary
  with depth (focal gain, Gouy phase);
* the elevation response: the echo of a point at elevation y relative to
  y = 0, fitted as a complex Gaussian w(y) = exp(-coef y^2) (D,) from
  points at three elevations inside the beam;
* the lateral gain (D2, L): the peak at lateral offsets relative to the
  centre, which falls near the ends of the array (plane-wave edge and a
  truncated receive aperture).

The elevations probed come from a Gaussian-beam reading of the lens
(`elevation_width_mm`): a Gaussian aperture of 1/e half-width 0.44 x the
element height (which gives the rect aperture's focal main-lobe width)
focused at the elevation focus. SIMUS's own beam is what is stored; the
formula only places the probe points inside it.

Everything is plain arrays (`to_arrays`, `from_arrays`) so a run can cache
it; the build is deterministic (no random draw).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from scissor_cli.sensing.ultrasound.simus_ref import beamform, receive_fnumber, simus_iq
from scissor_cli.sensing.ultrasound.transducer import ProbeParams, check_sound_speed, probe_params

# the PSF's shape changes fastest around the elevation focus; linear interpolation needs this step there
DEPTH_STEP_MM = 2.5
_AXIAL_HALF_WAVELENGTHS = 3.5  # window half-height in wavelengths: the pulse-echo envelope and its ringing
_LATERAL_HALF_FWHM = 3.0  # window half-width in receive-limited lateral FWHMs (1.2 lambda F#): main lobe + 2 sidelobes
_ELEVATION_PROBES = (0.25, 0.5, 0.75)  # elevations probed, in units of the Gaussian-beam 1/e two-way half-width
# (beyond the focus SIMUS's beam is narrower than the formula's and its phase grows as y^2: small probes keep
# the unwrapping unambiguous)
_LATERAL_PROBES = (0.3, 0.6, 0.85, 1.0)  # lateral gain probes, in units of the half aperture
# Scatterers per resolution cell by default: with Gaussian amplitudes the envelope approaches the Rayleigh law
# more slowly than with equal ones; 20 per cell keeps its mean/std near Rayleigh's (benchmark bench_ultrasound)
SCATTERERS_PER_CELL = 20.0
_GAUSSIAN_APERTURE = 0.44  # 1/e half-width of the equivalent Gaussian aperture / element height (module docstring)


@dataclass(frozen=True)
class PsfModel:
    """The fast model's PSF of one probe at one assumed sound speed, as plain arrays (module docstring)."""

    probe_name: str
    center_frequency_hz: float
    sound_speed_m_per_s: float  # the scanner's assumed speed, at which the PSF was simulated and beamformed
    fnumber: float  # receive f-number of the beamformer
    depths_mm: np.ndarray  # (D,) sample depths
    window_lateral_mm: np.ndarray  # (nx,) offsets of the window columns
    window_axial_mm: np.ndarray  # (nz,) offsets of the window rows
    windows: np.ndarray  # (D, nz, nx) complex64 baseband PSF, 1 at the centre
    gain: np.ndarray  # (D,) centre magnitude, relative to its largest value
    phase_rad: np.ndarray  # (D,) centre phase, unwrapped over depth
    elevation_coef_per_mm2: np.ndarray  # (D,) complex: w(y) = exp(-coef y^2), y mm
    lateral_gain_depths_mm: np.ndarray  # (D2,)
    lateral_gain_positions_mm: np.ndarray  # (L,) |lateral| of the probes (the response is symmetric)
    lateral_gain: np.ndarray  # (D2, L) peak at that lateral offset / peak on the axis

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Every field as a numpy array for a cache file (.npz or HDF5): floats as 0-d arrays, the name as bytes."""
        out = {f.name: np.asarray(getattr(self, f.name)) for f in fields(self)}
        out["probe_name"] = np.bytes_(self.probe_name.encode("ascii"))
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "PsfModel":
        """The model back from `to_arrays`' dictionary."""
        kw = {}
        for f in fields(cls):
            a = np.asarray(arrays[f.name])
            if f.name == "probe_name":
                v = a.item()
                kw[f.name] = v.decode("ascii") if isinstance(v, bytes) else str(v)
            else:
                kw[f.name] = float(a) if a.ndim == 0 else a.copy()
        return cls(**kw)

    def resolution_cell_mm(self, depth_mm: float | None = None) -> tuple[float, float]:
        """(lateral, axial) -6 dB widths, mm, of the PSF at a depth (default: the median sample depth)."""
        d = float(np.median(self.depths_mm)) if depth_mm is None else float(depth_mm)
        i = int(np.argmin(np.abs(self.depths_mm - d)))
        w = np.abs(self.windows[i])
        return _fwhm(self.window_lateral_mm, w[len(self.window_axial_mm) // 2]), _fwhm(
            self.window_axial_mm, w[:, len(self.window_lateral_mm) // 2])


    def density_per_mm2(self, per_cell: float = SCATTERERS_PER_CELL, depth_mm: float | None = None) -> float:
        """In-plane scatterer density (1/mm^2) giving per_cell scatterers per lateral x axial -6 dB cell."""
        lat, ax = self.resolution_cell_mm(depth_mm)
        return float(per_cell) / (lat * ax)

    def elevation_fwhm_mm(self, depth_mm) -> np.ndarray:
        """Two-way -6 dB thickness (mm) of the elevation beam at depth(s) mm, from the fitted exp(-coef y^2)."""
        re = np.interp(np.asarray(depth_mm, dtype=float), self.depths_mm, self.elevation_coef_per_mm2.real)
        return 2.0 * np.sqrt(math.log(2.0) / re)


def _fwhm(u: np.ndarray, profile: np.ndarray) -> float:
    """Width (units of u) where a peaked profile (n,) stays above half its maximum, by linear interpolation."""
    p = profile / profile.max()
    i = int(np.argmax(p))
    lo = i
    while lo > 0 and p[lo - 1] >= 0.5:
        lo -= 1
    hi = i
    while hi < len(p) - 1 and p[hi + 1] >= 0.5:
        hi += 1
    left = u[lo] if lo == 0 else u[lo - 1] + (0.5 - p[lo - 1]) / (p[lo] - p[lo - 1]) * (u[lo] - u[lo - 1])
    right = u[hi] if hi == len(p) - 1 else u[hi] + (p[hi] - 0.5) / (p[hi] - p[hi + 1]) * (u[hi + 1] - u[hi])
    return float(right - left)


def elevation_width_mm(probe: ProbeParams, sound_speed_m_per_s: float, depth_mm) -> np.ndarray:
    """Gaussian-beam one-way 1/e amplitude half-width W(z), mm, of the elevation beam at depth(s) z mm.

    W(z)^2 = W0^2 [(1 - z/F)^2 + (z/z_R)^2], W0 = 0.44 h, z_R = pi W0^2 / lambda,
    h the element height, F the elevation focus. The two-way amplitude of
    a point at elevation y is then about exp(-2 y^2 / W^2).
    """
    lam = probe.wavelength_mm(sound_speed_m_per_s)
    w0 = _GAUSSIAN_APERTURE * probe.element_height_mm
    z_r = math.pi * w0 * w0 / lam
    z = np.asarray(depth_mm, dtype=float)
    return w0 * np.sqrt((1.0 - z / probe.elevation_focus_mm) ** 2 + (z / z_r) ** 2)


def build_psf(probe: ProbeParams | str, assumed_sound_speed_m_per_s: float, depth_mm: float) -> PsfModel:
    """Simulate and measure the PSF of a probe down to depth_mm (module docstring). A few SIMUS calls."""
    if isinstance(probe, str):
        probe = probe_params(probe)
    c = check_sound_speed(assumed_sound_speed_m_per_s, "assumed sound speed")
    if not (math.isfinite(depth_mm) and depth_mm > 0):
        raise ValueError(f"imaging depth must be positive, got {depth_mm!r} mm")
    lam = probe.wavelength_mm(c)
    fnum = receive_fnumber(probe, c)
    # sample depths reach one step past the image so every row interpolates
    depths = DEPTH_STEP_MM * np.arange(1, int(math.ceil(depth_mm / DEPTH_STEP_MM)) + 2)
    D = len(depths)
    half_ap = probe.aperture_mm / 2.0
    anchor = (half_ap, float(depths[-1]) + 1.0)  # one SIMUS scale for every call
    # window: lambda/4 laterally, lambda/8 axially (the baseband is band-limited well inside these)
    nxh = int(math.ceil(_LATERAL_HALF_FWHM * 1.2 * lam * fnum / (lam / 4)))
    nzh = int(math.ceil(_AXIAL_HALF_WAVELENGTHS * lam / (lam / 8)))
    wx = np.arange(-nxh, nxh + 1) * (lam / 4)
    wz = np.arange(-nzh, nzh + 1) * (lam / 8)

    # in-plane points: the axis at every depth, lateral probes at every other depth
    lat_depths = depths[1::2]
    lat_pos = np.asarray(_LATERAL_PROBES) * half_ap
    xs = np.concatenate([np.zeros(D), np.repeat(lat_pos, len(lat_depths))])
    zs = np.concatenate([depths, np.tile(lat_depths, len(lat_pos))])
    iq = simus_iq(probe, xs, zs, np.zeros_like(xs), np.ones_like(xs), c, scale_anchor_mm=anchor)
    win = beamform(iq, probe, np.broadcast_to(wx, (D, len(wz), len(wx))),
                   depths[:, None, None] + wz[None, :, None], c, fnum)
    side = beamform(iq, probe, np.broadcast_to(lat_pos, (len(lat_depths), len(lat_pos))),
                    np.broadcast_to(lat_depths[:, None], (len(lat_depths), len(lat_pos))), c, fnum)
    k_a = 2 * math.pi / lam
    win = win * np.exp(-2j * k_a * wz)[None, :, None]  # baseband: remove the scanner's carrier
    peak = win[:, nzh, nxh].copy()
    windows = (win / peak[:, None, None]).astype(np.complex64)
    lateral_gain = np.abs(side) / np.abs(peak[1::2, None])

    # elevation: the axis points again, at three elevations inside the beam
    y_scale = elevation_width_mm(probe, c, depths) / math.sqrt(2.0)
    rel = []
    for kappa in _ELEVATION_PROBES:
        y = kappa * y_scale
        iq_y = simus_iq(probe, np.zeros(D), depths, y, np.ones(D), c, scale_anchor_mm=anchor)
        rel.append(beamform(iq_y, probe, np.zeros(D), depths, c, fnum) / peak)
    coef = _fit_elevation(np.asarray(_ELEVATION_PROBES)[:, None] * y_scale[None], np.array(rel))
    # in the near field (well before the focus) the response is flat-topped, not Gaussian, and the fit can
    # lose its decay: keep at least the decay of a beam twice the formula's width there
    coef = np.maximum(coef.real, 0.5 / elevation_width_mm(probe, c, depths) ** 2) + 1j * coef.imag

    return PsfModel(
        probe_name=probe.name, center_frequency_hz=probe.center_frequency_hz, sound_speed_m_per_s=c,
        fnumber=float(fnum), depths_mm=depths,
        window_lateral_mm=wx, window_axial_mm=wz, windows=windows,
        gain=np.abs(peak) / np.abs(peak).max(), phase_rad=np.unwrap(np.angle(peak)),
        elevation_coef_per_mm2=coef, lateral_gain_depths_mm=lat_depths,
        lateral_gain_positions_mm=lat_pos, lateral_gain=lateral_gain,
    )


def _fit_elevation(y_mm: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """coef (D,) complex of rel ~ exp(-coef y^2), from samples y_mm (J, D) and rel (J, D), J increasing in |y|.

    Weighted least squares on the complex logarithm, weights |rel|^2 (the
    far samples are the faintest); each phase is unwrapped onto the branch
    the nearer samples predict.
    """
    y2 = y_mm ** 2
    logs = np.log(np.maximum(np.abs(rel), 1e-12)) + 1j * np.angle(rel)
    coef = -logs[0] / y2[0]
    for j in range(1, len(y2)):
        predicted = -(coef * y2[j]).imag
        turns = np.round((predicted - logs[j].imag) / (2 * math.pi))
        logs[j] = logs[j].real + 1j * (logs[j].imag + 2 * math.pi * turns)
        w = np.abs(rel[: j + 1]) ** 2
        coef = -np.sum(w * y2[: j + 1] * logs[: j + 1], axis=0) / np.sum(w * y2[: j + 1] ** 2, axis=0)
    return coef
