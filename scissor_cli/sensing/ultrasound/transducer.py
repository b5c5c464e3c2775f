"""The linear probe: its transducer parameters, its pose on the layer and its image grid (docs/ultrasound.md §1).

Frames. The layer frame is the scene's (x right, y up, mm). The probe frame
has its origin at the centre of the array face (`ProbePose.position_mm`, on
the skin), depth along the unit beam direction `axis` (into the tissue) and
lateral along `axis` turned +90 degrees, i.e. lateral unit = (-axis_y,
axis_x). Elevation, across the imaging plane, is the slab's z minus the
layer's height; the layer itself has none. Points in the probe frame are
written (lateral, depth), in that column order.

The image grid samples the scanner's apparent depth (echo time x the
scanner's assumed sound speed / 2), not the true depth: the two differ when
the tissue's sound speed is not the assumed one (`fast.py`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# The names pymust.getparam (0.1.9) knows whose array is flat (radius inf) and
# that carry an element height and an elevation focus, which the elevation
# profile needs. getparam also knows C5-2v (convex) and six legacy entries
# (PA4-2/20, L9-4/38, LA530, L14-5/38, L14-5W/60, P6-3) without elevation data;
# P4-2v is a flat phased array, imaged here the same way as the linear ones.
LINEAR_PROBES: tuple[str, ...] = ("L11-5v", "L12-3v", "P4-2v")


@dataclass(frozen=True)
class ProbeParams:
    """A linear array as plain numbers (from `pymust.getparam`)."""

    name: str
    center_frequency_hz: float
    pitch_mm: float
    n_elements: int
    element_width_mm: float
    kerf_mm: float
    fractional_bandwidth: float  # pulse-echo -6 dB bandwidth / centre frequency (0.77 = 77 %)
    element_height_mm: float  # elevation aperture
    elevation_focus_mm: float

    @property
    def aperture_mm(self) -> float:
        """Width of the array (element pitch x element count), mm."""
        return self.pitch_mm * self.n_elements

    def wavelength_mm(self, sound_speed_m_per_s: float) -> float:
        """Wavelength at the centre frequency, mm."""
        check_sound_speed(sound_speed_m_per_s, "sound speed")
        return sound_speed_m_per_s * 1e3 / self.center_frequency_hz

    def pymust_param(self, sound_speed_m_per_s: float):
        """A fresh pymust parameter structure of this probe (SI units) in a medium of this sound speed.

        The sampling frequency is pymust's default, 4 x the centre frequency.
        """
        import pymust  # noqa: PLC0415  (pymust imports matplotlib: only where it is used)

        check_sound_speed(sound_speed_m_per_s, "sound speed")
        p = pymust.utils.Param()
        p.fc = self.center_frequency_hz
        p.pitch = self.pitch_mm * 1e-3
        p.width = self.element_width_mm * 1e-3
        p.kerf = self.kerf_mm * 1e-3
        p.Nelements = self.n_elements
        p.bandwidth = self.fractional_bandwidth * 100.0
        p.radius = math.inf
        p.height = self.element_height_mm * 1e-3
        p.focus = self.elevation_focus_mm * 1e-3
        p.c = float(sound_speed_m_per_s)
        p.fs = 4.0 * self.center_frequency_hz
        return p


def probe_params(name: str) -> ProbeParams:
    """The parameters of a linear probe pymust knows; ValueError for any other name."""
    canonical = {n.upper(): n for n in LINEAR_PROBES}
    key = str(name).strip().upper()
    if key not in canonical:
        raise ValueError(
            f"probe {name!r} is not a linear array pymust knows with elevation data; "
            f"allowed: {', '.join(LINEAR_PROBES)}"
        )
    import pymust  # noqa: PLC0415

    p = pymust.getparam(canonical[key])
    if not math.isinf(p.radius):  # pragma: no cover - guards a future pymust table
        raise ValueError(f"probe {name!r} is not linear (radius {p.radius} m); allowed: {', '.join(LINEAR_PROBES)}")
    return ProbeParams(
        name=canonical[key],
        center_frequency_hz=float(p.fc),
        pitch_mm=float(p.pitch) * 1e3,
        n_elements=int(p.Nelements),
        element_width_mm=float(p.width) * 1e3,
        kerf_mm=float(p.kerf) * 1e3,
        fractional_bandwidth=float(p.bandwidth) / 100.0,
        element_height_mm=float(p.height) * 1e3,
        elevation_focus_mm=float(p.focus) * 1e3,
    )


def check_sound_speed(value: float, what: str) -> float:
    """value if it is a finite positive speed (m/s), else ValueError naming `what`."""
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{what} must be a positive finite speed in m/s, got {value!r}")
    return v


@dataclass(frozen=True)
class ProbePose:
    """Where the probe sits on the layer: array-face centre (2,) mm and unit beam direction (2,)."""

    position_mm: np.ndarray
    axis: np.ndarray

    def __post_init__(self) -> None:
        p = np.asarray(self.position_mm, dtype=float).reshape(-1)
        a = np.asarray(self.axis, dtype=float).reshape(-1)
        if p.shape != (2,) or a.shape != (2,) or not (np.all(np.isfinite(p)) and np.all(np.isfinite(a))):
            raise ValueError(
                f"probe position and axis must be finite 2-vectors, got {self.position_mm!r}, {self.axis!r}")
        n = float(np.hypot(a[0], a[1]))
        if n < 1e-9:
            raise ValueError("probe axis must not be zero")
        object.__setattr__(self, "position_mm", p)
        object.__setattr__(self, "axis", a / n)

    @property
    def lateral(self) -> np.ndarray:
        """Lateral unit vector (2,): the axis turned +90 degrees."""
        return np.array([-self.axis[1], self.axis[0]])

    def to_probe(self, points_mm: np.ndarray) -> np.ndarray:
        """Layer points (K, 2) mm -> probe frame (K, 2) mm as (lateral, depth)."""
        d = np.asarray(points_mm, dtype=float) - self.position_mm
        lat, ax = self.lateral, self.axis
        return np.stack([d[..., 0] * lat[0] + d[..., 1] * lat[1], d[..., 0] * ax[0] + d[..., 1] * ax[1]], axis=-1)

    def to_layer(self, probe_mm: np.ndarray) -> np.ndarray:
        """Probe-frame points (K, 2) mm as (lateral, depth) -> layer points (K, 2) mm."""
        q = np.asarray(probe_mm, dtype=float)
        lat, ax = self.lateral, self.axis
        return self.position_mm + q[..., :1] * lat + q[..., 1:2] * ax


@dataclass(frozen=True)
class ImageGrid:
    """Pixel centres of a B-mode frame: lateral_mm (W,) and apparent depth_mm (H,), both uniform and increasing."""

    lateral_mm: np.ndarray
    depth_mm: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W): rows are depths, columns lateral positions."""
        return (len(self.depth_mm), len(self.lateral_mm))

    @property
    def dx_mm(self) -> float:
        """Lateral pixel size, mm."""
        return float(self.lateral_mm[1] - self.lateral_mm[0])

    @property
    def dz_mm(self) -> float:
        """Axial pixel size, mm."""
        return float(self.depth_mm[1] - self.depth_mm[0])

    def to_pixel(self, probe_mm: np.ndarray) -> np.ndarray:
        """Probe-frame points (K, 2) mm (lateral, depth) -> fractional pixel indices (K, 2) as (row, column)."""
        q = np.asarray(probe_mm, dtype=float)
        row = (q[..., 1] - self.depth_mm[0]) / self.dz_mm
        return np.stack([row, (q[..., 0] - self.lateral_mm[0]) / self.dx_mm], -1)

    def to_mm(self, pixel: np.ndarray) -> np.ndarray:
        """Fractional pixel indices (K, 2) as (row, column) -> probe-frame points (K, 2) mm (lateral, depth)."""
        p = np.asarray(pixel, dtype=float)
        return np.stack([self.lateral_mm[0] + p[..., 1] * self.dx_mm, self.depth_mm[0] + p[..., 0] * self.dz_mm], -1)

    def require_inside(self, probe_mm: np.ndarray, margin_mm: float = 0.0, what: str = "point") -> None:
        """ValueError if any probe-frame point (K, 2) mm lies outside the image shrunk by margin_mm."""
        q = np.atleast_2d(np.asarray(probe_mm, dtype=float))
        lo = np.array([self.lateral_mm[0], self.depth_mm[0]]) + margin_mm
        hi = np.array([self.lateral_mm[-1], self.depth_mm[-1]]) - margin_mm
        bad = ~np.all(np.isfinite(q) & (q >= lo) & (q <= hi), axis=-1)
        if np.any(bad):
            p = q[np.argmax(bad)]
            raise ValueError(
                f"{what} (lateral {p[0]:.3g} mm, depth {p[1]:.3g} mm) is outside the image "
                f"(lateral {lo[0]:.3g}..{hi[0]:.3g} mm, depth {lo[1]:.3g}..{hi[1]:.3g} mm)"
            )


def image_grid(probe: ProbeParams, depth_mm: float, assumed_sound_speed_m_per_s: float) -> ImageGrid:
    """The B-mode grid of a probe: the array's width laterally, 0..depth_mm in apparent depth.

    Pixel sizes: lateral = pitch / 2 and axial = wavelength / 2 at the centre
    frequency and the scanner's sound speed. The image is formed in the
    baseband (IQ) domain, which is band-limited: the axial band is the
    pulse-echo band (about +-fractional bandwidth x fc / 2 around fc, i.e.
    spatial frequencies up to about 0.4 x 2 / wavelength), the lateral band
    is set by the receive f-number. Half a wavelength axially samples that
    band at its Nyquist rate, half a pitch samples the lateral band several
    times over; so a speckle grain spans a couple of pixels axially and
    several laterally, enough for a sub-pixel fit of a correlation peak,
    while a whole image keeps two columns per element.
    """
    check_sound_speed(assumed_sound_speed_m_per_s, "assumed sound speed")
    if not (math.isfinite(depth_mm) and depth_mm > 0):
        raise ValueError(f"imaging depth must be positive, got {depth_mm!r} mm")
    dz = probe.wavelength_mm(assumed_sound_speed_m_per_s) / 2.0
    dx = probe.pitch_mm / 2.0
    W = 2 * probe.n_elements
    H = int(math.floor(depth_mm / dz + 1e-9)) + 1
    return ImageGrid(lateral_mm=(np.arange(W) - (W - 1) / 2.0) * dx, depth_mm=np.arange(H) * dz)
