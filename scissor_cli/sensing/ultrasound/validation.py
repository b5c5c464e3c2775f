"""The fast model against SIMUS on the same scatterers: a small patch, two numbers (docs/ultrasound.md §4).

A patch of scatterers around a point is imaged by both models, before and
after a known motion (a shift, optionally an affine strain about the
point). Reported: the correlation coefficient of the two envelopes over
the patch's interior (the first frame), and the displacement each model's
frames give to the block matcher, with their difference. The run stores
these numbers; the patch is small because SIMUS's cost grows with the
scatterers (benchmark bench_ultrasound has the time).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scissor_cli.sensing.ultrasound.fast import FrameKernels, fast_frame
from scissor_cli.sensing.ultrasound.psf import PsfModel
from scissor_cli.sensing.ultrasound.simus_ref import simus_frame
from scissor_cli.sensing.ultrasound.speckle_tracking import TrackingParams, block_match
from scissor_cli.sensing.ultrasound.transducer import ImageGrid, ProbeParams


@dataclass(frozen=True)
class FastValidation:
    """Agreement of the fast model with SIMUS on one patch."""

    envelope_correlation: float  # Pearson correlation of the envelopes over the patch interior
    tracked_fast_mm: np.ndarray  # (2,) displacement (lateral, depth) tracked on the fast frames
    tracked_simus_mm: np.ndarray  # (2,) the same on the SIMUS frames
    true_mm: np.ndarray  # (2,) the motion of the centre
    scatterer_count: int

    @property
    def tracking_difference_mm(self) -> float:
        """|fast - SIMUS| of the tracked displacements, mm."""
        return float(np.hypot(*(self.tracked_fast_mm - self.tracked_simus_mm)))


def validate_fast(
    probe: ProbeParams,
    psf: PsfModel,
    kernels: FrameKernels,
    rng: np.random.Generator,
    center_mm: np.ndarray,
    shift_mm: np.ndarray,
    strain: np.ndarray | None = None,
    per_cell: float = 5.0,
    elevation_half_mm: float = 0.0,
    tissue_sound_speed_m_per_s: float | None = None,
) -> FastValidation:
    """Image a patch around center_mm (2,) (lateral, depth mm) with both models, before and after a motion.

    The motion maps x to x + shift_mm + strain (x - center_mm) (strain (2, 2),
    default none). The patch holds the tracking block, its search range and
    the motion. Scatterers: per_cell per resolution cell (fewer than a
    trial's, to keep SIMUS short: the comparison is of two linear models on
    the same scatterers, it needs no fully developed speckle), Gaussian
    amplitudes, elevations uniform in +-elevation_half_mm. Both models at one
    tissue sound speed (default: the scanner's).
    """
    c = np.asarray(center_mm, dtype=float).reshape(2)
    shift = np.asarray(shift_mm, dtype=float).reshape(2)
    A = np.zeros((2, 2)) if strain is None else np.asarray(strain, dtype=float).reshape(2, 2)
    g = kernels.grid
    c_a = kernels.assumed_sound_speed_m_per_s
    c_t = c_a if tissue_sound_speed_m_per_s is None else float(tissue_sound_speed_m_per_s)
    params = TrackingParams(search_mm=(0.5, 0.5))
    # image half-size: block + search + motion + a little; scatterers reach a PSF's half-width beyond
    half_img = np.array(params.block_half_mm) + np.array(params.search_mm) + np.abs(shift) + 0.2
    half_sc = half_img + np.array([1.0, 0.5])
    apparent = np.array([c[0], c[1] * c_a / c_t])
    g.require_inside(apparent - half_img, what="validation patch corner")
    g.require_inside(apparent + half_img + np.abs(shift), what="validation patch corner")
    n = rng.poisson(psf.density_per_mm2(per_cell, c[1]) * 4.0 * half_sc[0] * half_sc[1])
    pos = c + (2.0 * rng.random((n, 2)) - 1.0) * half_sc
    elevation = elevation_half_mm * (2.0 * rng.random(n) - 1.0)
    amp = rng.standard_normal(n)
    moved = pos + shift + (pos - c) @ A.T

    cols = np.abs(g.lateral_mm - apparent[0]) <= half_img[0]
    rows = np.abs(g.depth_mm - apparent[1]) <= half_img[1]
    sub = ImageGrid(g.lateral_mm[cols], g.depth_mm[rows])
    fast, ref = [], []
    for p in (pos, moved):
        fast.append(fast_frame(kernels, p[:, 0], p[:, 1], elevation, amp, c_t)[np.ix_(rows, cols)])
        ref.append(simus_frame(probe, sub, p[:, 0], p[:, 1], elevation, amp, c_t, c_a))
    X, Z = np.meshgrid(sub.lateral_mm - apparent[0], sub.depth_mm - apparent[1])
    inner = (np.abs(X) <= half_img[0] - 0.3) & (np.abs(Z) <= half_img[1] - 0.3)
    corr = float(np.corrcoef(fast[0][inner], ref[0][inner])[0, 1])
    predicted = apparent + shift * np.array([1.0, c_a / c_t])
    tracked = [block_match(f[0], f[1], sub, apparent, predicted, params)[0] for f in (fast, ref)]
    return FastValidation(envelope_correlation=corr, tracked_fast_mm=tracked[0], tracked_simus_mm=tracked[1],
                          true_mm=shift.copy(), scatterer_count=int(n))
