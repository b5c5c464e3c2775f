"""Cross-field checks of the `imaging` section: the probe on the skin, facing in, the targets in its image.

The image's extent is the probe's (`sensing.ultrasound.image_grid`): two
columns per element of pitch p, so laterally ±(2 N − 1) p / 4 about the
array's centre, N the element count; in depth 0 … depth_mm of apparent
depth, the true depth × c_assumed / c_tissue. config does not import
sensing (it comes later in the layers), so the arrays' sizes are a small
literal table here, `PROBE_ARRAYS`, that tests/test_ultrasound_loop.py
holds equal to pymust's.
"""

from __future__ import annotations

import numpy as np

from scissor_cli import geometry
from scissor_cli.config.sections import LINEAR_PROBE_NAMES, Config

#: element count and pitch (mm) of each linear probe (pymust.getparam)
PROBE_ARRAYS: dict[str, tuple[int, float]] = {"L11-5v": (128, 0.3), "L12-3v": (192, 0.2), "P4-2v": (64, 0.3)}
assert set(PROBE_ARRAYS) == set(LINEAR_PROBE_NAMES)
#: how far (mm) the centre of the array's face may lie from the tissue's outline: the flat face on a skin that
#: the mesh follows with straight edges
ON_SKIN_TOLERANCE_MM = 0.5
#: the beam must enter the tissue: the point this far (mm) along the axis from the face lies inside
FACING_DEPTH_MM = 1.0


def image_half_width_mm(probe: str) -> float:
    """Half the image's width (mm): its outermost column centres, ±(2 N − 1) p / 4."""
    n, pitch = PROBE_ARRAYS[probe]
    return (2 * n - 1) * pitch / 4.0


def imaging_problems(cfg: Config, outline: np.ndarray, inside) -> list:
    """[(location, message)] of the imaging section; `inside(points (K, 2), outline)` → (K,) strictly inside."""
    im = cfg.imaging
    if im is None:
        return []
    problems = []
    pos = np.asarray(im.position_mm, float)
    axis = np.asarray(im.axis, float)
    d = float(geometry.distance_to_boundary(pos[None], outline)[0])
    if d > ON_SKIN_TOLERANCE_MM:
        problems.append((("imaging", "position_mm"), (
            f"the probe's face must lie on the skin (the tissue's outline, within {ON_SKIN_TOLERANCE_MM:g} mm); "
            f"{im.position_mm} is {d:.3g} mm from it")))
    elif not inside(pos + FACING_DEPTH_MM * axis, outline)[0]:
        problems.append((("imaging", "axis"), (
            f"the beam must point into the tissue: {FACING_DEPTH_MM:g} mm along axis "
            f"{[round(float(v), 4) for v in axis]} from the probe at {im.position_mm} is outside it")))
    half = image_half_width_mm(im.probe)
    lateral_unit = np.array([-axis[1], axis[0]])
    scale = im.assumed_sound_speed_m_per_s / im.sound_speed_m_per_s  # apparent / true depth
    for target in cfg.targets:
        q = np.asarray(target.position_mm, float) - pos
        lateral, depth = float(q @ lateral_unit), float(q @ axis)
        if abs(lateral) > half:
            problems.append((("imaging", "position_mm"), (
                f"target {target.name!r} at {target.position_mm} is {lateral:+.3g} mm lateral of the probe's centre, "
                f"outside the {im.probe} image (±{half:.4g} mm): move the probe (imaging.position_mm, axis)")))
        elif not 0.0 < depth * scale < im.depth_mm:
            problems.append((("imaging", "depth_mm"), (
                f"target {target.name!r} at {target.position_mm} shows at {depth * scale:.3g} mm depth, outside the "
                f"image (0 to depth_mm {im.depth_mm:g} mm): deepen the image or move the probe")))
    size = min(2.0 * half, im.depth_mm)
    if 2.0 * im.lesion_radius_mm >= size:
        problems.append((("imaging", "lesion_radius_mm"), (
            f"the lesion ({2 * im.lesion_radius_mm:g} mm across) must be smaller than the image "
            f"({2 * half:.4g} × {im.depth_mm:g} mm)")))
    return problems + echo_problems(im, cfg.obstacles)


def echo_problems(im, obstacles) -> list:
    """The echoes an `imaging` section (the layer's or a body's) gives: a lesion with no contrast, an obstacle's
    echogenicity naming no obstacle of obstacles (each with a `name`); (path, message) pairs."""
    problems = []
    if im.lesion_echogenicity_db == 0.0:
        problems.append((("imaging", "lesion_echogenicity_db"),
                         "0 dB: a lesion that echoes like the background cannot be seen; give it a contrast"))
    names = {o.name for o in obstacles}
    for name in sorted(im.obstacle_echogenicity_db or {}):
        if name not in names:
            problems.append((("imaging", "obstacle_echogenicity_db", name),
                             f"unknown obstacle {name!r}; obstacles are {sorted(names)}"))
    return problems
