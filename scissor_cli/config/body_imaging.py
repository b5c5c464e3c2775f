"""Ultrasound on a 3-D body: the `imaging` section of a 3-D scene and its checks (docs/ultrasound.md, "On the body
(3-D)"; docs/model.md §20).

The section is the layer's (`sections.ImagingConfig`) with a 3-D pose: the
array's centre `position_mm` (3,), moved to the nearest skin point; the beam
`axis` (3,) into the body; the `lateral_axis` (3,) along the array. The
image plane holds axis and lateral_axis; elevation, across it, is
lateral_axis × axis.

Defaults of the pose (`probe_axes`):

* axis absent: the skin's inward normal at the probe's skin point;
* lateral_axis absent: in-plane guidance, the clinical default — the
  needle's direction (`needle.direction`) with its part along the axis
  removed, so the needle lies in the image plane; when the needle runs
  within `IN_PLANE_MIN_DEG` of the beam, the body's x axis (then y) with
  its part along the axis removed.

Checks (`body_imaging_problems`, on the body's exact surface the other
body checks use; each a (location, message) pair): the position within
`ON_SKIN_MM` of the skin ("off the skin"), the axis within `MAX_TILT_DEG` of
the inward normal there ("pointing out"), lateral_axis perpendicular to the
axis within `PERPENDICULAR_TOL`, every lesion in the image: within the
array's lateral extent, at an apparent depth in (0, depth_mm), and across
the plane within the elevation reach (`elevation_reach_mm`).

config does not import sensing (it comes later in the layers): the
probes' elevation apertures are a literal table, `PROBE_ELEVATION`, that
tests/test_ultrasound_body.py holds equal to pymust's, as
`imaging_checks.PROBE_ARRAYS` is held.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal, Optional

import numpy as np
from annotated_types import Len
from pydantic import field_validator

from scissor_cli.config.imaging_checks import PROBE_ARRAYS, echo_problems, image_half_width_mm
from scissor_cli.config.sections import LINEAR_PROBE_NAMES, Num, Vec3, _Section

#: element height (mm) and elevation focus (mm) of each linear probe (pymust.getparam)
PROBE_ELEVATION: dict[str, tuple[float, float]] = {"L11-5v": (5.0, 18.0), "L12-3v": (5.0, 20.0),
                                                    "P4-2v": (14.0, 60.0)}
#: centre frequency (Hz) of each linear probe (pymust.getparam): the wavelength of the Gaussian beam
PROBE_FREQUENCY_HZ: dict[str, float] = {"L11-5v": 7.6e6, "L12-3v": 7.54e6, "P4-2v": 2.72e6}
assert set(PROBE_ELEVATION) == set(PROBE_FREQUENCY_HZ) == set(PROBE_ARRAYS) == set(LINEAR_PROBE_NAMES)
#: the configured position may lie this far (mm) from the skin, inside or outside: it says where on the skin the
#: array sits (it is moved to the nearest skin point); farther, it is a mistake (a probe held in the air or a
#: point inside the body), not a placement
ON_SKIN_MM = 2.0
#: the beam may lean this far (deg) from the skin's inward normal: beyond it most of a flat array's face is off the
#: skin (no coupling), and at 90° and more the beam runs along the skin or out of the body
MAX_TILT_DEG = 60.0
#: |axis · lateral_axis| at most this (cos 89.4°): the two span the image plane and must be perpendicular
PERPENDICULAR_TOL = 0.01
#: unit vectors are given to this length tolerance (then normalised), as the layer's axis
UNIT_TOL = 0.01
#: below this angle (deg) between the needle and the beam, the needle cannot give the in-plane lateral axis
IN_PLANE_MIN_DEG = 10.0
#: the Gaussian aperture's 1/e half-width over the element height (sensing.ultrasound.psf's)
GAUSSIAN_APERTURE = 0.44


def _unit(v: list[float] | None) -> list[float] | None:
    if v is None:
        return None
    n = float(np.linalg.norm(v))
    if abs(n - 1.0) > UNIT_TOL:
        raise ValueError(f"must be a unit vector (length 1 ± {UNIT_TOL:g}); got length {n:.4g}")
    return [float(c) / n for c in v]


class BodyImagingConfig(_Section):
    """Ultrasound in a 3-D scene's loop (docs/ultrasound.md, "On the body (3-D)"): a linear probe anywhere on the
    skin images a plane through the body; the lesion is localised on its frames. Fields as the layer's
    `ImagingConfig` but the pose (module docstring for the defaults and the checks)."""

    probe: Literal[LINEAR_PROBE_NAMES] = "L11-5v"
    #: the array's centre (mm), moved to the nearest skin point (refused farther than ON_SKIN_MM from the skin)
    position_mm: Vec3
    #: the beam's direction into the body, a unit vector (length 1 ± 0.01, normalised); absent: the skin's inward
    #: normal at the probe
    axis: Optional[Vec3] = None
    #: along the array, a unit vector perpendicular to axis; absent: in-plane guidance (the needle in the image)
    lateral_axis: Optional[Vec3] = None
    depth_mm: Num(5.0, 250.0) = 70.0
    assumed_sound_speed_m_per_s: Num(1000.0, 2000.0) = 1540.0
    sound_speed_m_per_s: Num(1000.0, 2000.0) = 1540.0
    #: the lesion's echo sphere about each target's rest centre; absent: that target's own radius_mm
    lesion_radius_mm: Optional[Num(gt=0.0, hi=100.0)] = None
    #: not 0: a lesion like the background cannot be seen (checks)
    lesion_echogenicity_db: Num(-100.0, 40.0) = -10.0
    #: electronic noise: signal-to-noise ratio (dB) of a frame of background speckle; null: none
    snr_db: Optional[Num(-20.0, 120.0)] = 30.0
    #: fast: the fast model, validated against SIMUS (on a body the only one: the checks refuse simus)
    model: Literal["fast", "simus"] = "fast"
    #: per obstacle name: its echogenicity (dB), overriding the kind its name says (docs/ultrasound.md §6)
    obstacle_echogenicity_db: Optional[Annotated[dict[str, Num(-100.0, 40.0)], Len(0, 64)]] = None

    @field_validator("axis", "lateral_axis")
    @classmethod
    def _unit_vectors(cls, v: list[float] | None) -> list[float] | None:
        return _unit(v)

    def lesion_radius_for(self, target_radius_mm: float) -> float:
        """The lesion's echo radius (mm): lesion_radius_mm, else the target's own radius."""
        return float(self.lesion_radius_mm if self.lesion_radius_mm is not None else target_radius_mm)


def elevation_reach_mm(probe: str, depth_mm: float, sound_speed_m_per_s: float, lesion_radius_mm: float) -> float:
    """How far (mm) across the image plane a lesion's centre may lie at depth_mm and still be in the image.

    The larger of half the lesion's radius (the plane then cuts its sphere
    in a disc of at least 0.87 of its radius, which the localisation's
    template of the full radius still matches) and the elevation beam's
    two-way -6 dB half-thickness there, W sqrt(ln 2 / 2) with the Gaussian
    beam's W(z)² = W0² [(1 - z/F)² + (z/z_R)²], W0 = 0.44 h, z_R = π W0² / λ
    (sensing.ultrasound.psf.elevation_width_mm).
    """
    height, focus = PROBE_ELEVATION[probe]
    lam = sound_speed_m_per_s * 1e3 / PROBE_FREQUENCY_HZ[probe]
    w0 = GAUSSIAN_APERTURE * height
    z_r = math.pi * w0 * w0 / lam
    w = w0 * math.sqrt((1.0 - depth_mm / focus) ** 2 + (depth_mm / z_r) ** 2)
    return max(0.5 * lesion_radius_mm, w * math.sqrt(math.log(2.0) / 2.0))


def probe_axes(inward_normal, axis=None, lateral=None, needle_direction=None) -> tuple[np.ndarray, np.ndarray]:
    """The probe's unit axis (3,) and lateral (3,), exactly perpendicular (module docstring for the defaults).

    inward_normal (3,): the skin's at the probe; axis, lateral (3,) or None
    (the config's); needle_direction (3,) or None. A given lateral keeps
    its direction up to the part along the axis (removed: the checks bound
    it by PERPENDICULAR_TOL).
    """
    a = np.asarray(inward_normal if axis is None else axis, float)
    a = a / np.linalg.norm(a)
    if lateral is not None:
        candidates = [np.asarray(lateral, float)]
    else:
        candidates = [] if needle_direction is None else [np.asarray(needle_direction, float)]
        candidates += [np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])]
    floor = math.sin(math.radians(IN_PLANE_MIN_DEG))
    for c in candidates:
        c = c / np.linalg.norm(c)
        r = c - (c @ a) * a
        n = float(np.linalg.norm(r))
        if n >= floor or lateral is not None:
            return a, r / n
    raise AssertionError("x and y cannot both lie within IN_PLANE_MIN_DEG of one axis")  # pragma: no cover


def body_imaging_problems(cfg, surface, skin_normals) -> list:
    """[(location, message)] of a 3-D scene's imaging section on its body surface (`body_checks.body_surface`);
    skin_normals(surface, points (K, 3)) → outward unit normals (K, 3) (`body_checks.skin_normals`, handed in:
    body_checks imports this module)."""
    im = cfg.imaging
    if im is None:
        return []
    out: list = []
    pos = np.asarray(im.position_mm, float)
    on_skin, dist = surface.nearest_skin(pos[None])
    if float(dist[0]) > ON_SKIN_MM:
        side = "inside the body" if float(surface.depth(pos[None])[0]) > 0 else "outside the body"
        return [(("imaging", "position_mm"), (
            f"the probe is off the skin: {im.position_mm} is {float(dist[0]):.3g} mm {side}, the nearest skin point "
            f"{np.round(on_skin[0], 2).tolist()}; allowed: within {ON_SKIN_MM:g} mm of the skin (the position is "
            f"moved to the nearest skin point)"))]
    inward = -skin_normals(surface, on_skin)[0]
    if im.axis is not None:
        tilt = math.degrees(math.acos(float(np.clip(np.dot(im.axis, inward), -1.0, 1.0))))
        if tilt > MAX_TILT_DEG:
            what = "pointing out of the body" if tilt >= 90.0 else f"{tilt:.3g}° from the skin's inward normal"
            return [(("imaging", "axis"), (
                f"the beam is {what}: axis {[round(float(v), 4) for v in im.axis]} at the skin point "
                f"{np.round(on_skin[0], 2).tolist()} whose inward normal is {np.round(inward, 3).tolist()}; allowed: "
                f"within {MAX_TILT_DEG:g}° of the inward normal (or leave axis out: the inward normal)"))]
    axis, lateral = probe_axes(inward, im.axis, im.lateral_axis, cfg.needle.direction)
    if im.lateral_axis is not None and abs(float(np.dot(im.lateral_axis, axis))) > PERPENDICULAR_TOL:
        return [(("imaging", "lateral_axis"), (
            f"must be perpendicular to the beam axis {np.round(axis, 4).tolist()} (|axis · lateral_axis| ≤ "
            f"{PERPENDICULAR_TOL:g}); got {abs(float(np.dot(im.lateral_axis, axis))):.3g} "
            f"(or leave lateral_axis out: the needle in the image plane)"))]
    out += _lesion_image_problems(cfg, on_skin[0], axis, lateral)
    if im.model != "fast":
        out.append((("imaging", "model"), (
            f"{im.model!r}: on a body the frames are the fast model's (the SIMUS reference runs on the layer and the "
            f"slab, where it is checked against it); allowed: fast")))
    return out + echo_problems(im, cfg.obstacles)


def _lesion_image_problems(cfg, origin: np.ndarray, axis: np.ndarray, lateral: np.ndarray) -> list:
    im = cfg.imaging
    half = image_half_width_mm(im.probe)
    elevation = np.cross(lateral, axis)
    scale = im.assumed_sound_speed_m_per_s / im.sound_speed_m_per_s  # apparent / true depth
    out = []
    for t in cfg.targets:
        q = np.asarray(t.position_mm, float) - origin
        lat, depth, ele = float(q @ lateral), float(q @ axis), float(q @ elevation)
        radius = im.lesion_radius_for(t.radius_mm)
        where = f"the lesion outside the image: target {t.name!r} at {t.position_mm} is"
        if 2.0 * radius >= min(2.0 * half, im.depth_mm):
            out.append((("imaging", "lesion_radius_mm"), (
                f"the lesion of {t.name!r} ({2 * radius:g} mm across) must be smaller than the image "
                f"({2 * half:.4g} × {im.depth_mm:g} mm)")))
        elif abs(lat) > half:
            out.append((("imaging", "position_mm"), (
                f"{where} {lat:+.3g} mm lateral of the probe's centre; allowed: within the {im.probe} image's "
                f"±{half:.4g} mm (move the probe: imaging.position_mm, lateral_axis)")))
        elif not 0.0 < depth * scale < im.depth_mm:
            out.append((("imaging", "depth_mm"), (
                f"{where} at {depth * scale:.3g} mm apparent depth; allowed: 0 to depth_mm {im.depth_mm:g} mm "
                f"(deepen the image or move the probe)")))
        else:
            reach = elevation_reach_mm(im.probe, depth, im.assumed_sound_speed_m_per_s, radius)
            if abs(ele) > reach:
                out.append((("imaging", "position_mm"), (
                    f"{where} {ele:+.3g} mm across the image plane (elevation); allowed: within ±{reach:.3g} mm at "
                    f"its depth {depth:.3g} mm (the elevation beam, or half the lesion's radius): put the plane "
                    f"through the lesion (imaging.position_mm, axis, lateral_axis)")))
    return out


__all__ = ["BodyImagingConfig", "ON_SKIN_MM", "MAX_TILT_DEG", "PERPENDICULAR_TOL", "PROBE_ELEVATION",
           "body_imaging_problems", "elevation_reach_mm", "probe_axes"]
