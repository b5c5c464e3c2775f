"""Where the lesion is: first-frame localisation and speckle tracking (docs/ultrasound.md §5).

Localisation finds the lesion's disc near a planned position on the
first frame (a dark disc for a hypoechoic lesion, a bright one
otherwise): the log envelope is smoothed over about a speckle grain, then
correlated with a zero-mean disc-and-ring template of the lesion's radius
(inside -1, a ring out to 1.5 radii +1, equal weights); the strongest
response within the search radius, refined by a 3-point parabola per axis,
is the centre.

Tracking follows the lesion from frame to frame by normalised
cross-correlation (NCC) block matching on the envelope: a block around the
lesion in an anchor frame is searched for in the current frame around the
last estimate; a 3-point Gaussian fit per axis through the NCC peak gives
the sub-pixel offset (the peak of a speckle correlation is close to
Gaussian, and a parabola fitted to a peak only two pixels wide biases the
offset towards whole pixels). The anchor is the first frame as long as its
peak NCC stays above `reanchor_below`; when deformation decorrelates it, the
previous frame (at its estimate) becomes the anchor and the displacements
add up. Matching against a fixed anchor does not accumulate errors;
re-anchoring only when needed keeps the drift to a few re-anchorings.

The block is small (default +-2 mm laterally, +-1 mm axially: a few
speckle grains laterally, about ten axially). Under non-uniform
deformation a block moves with the average displacement of its bright
parts, not with its centre; around a hypoechoic lesion the bright parts
are its rim, so a large block reports the rim's motion. A smaller block
has less of that bias and more noise; the default balances the two on
the smooth-motion sequences of benchmark bench_ultrasound. The re-anchoring
threshold likewise trades the bias of matching through large strain
(low threshold) against the random walk of many re-anchorings (high).

Positions are probe-frame mm (lateral, apparent depth), on the grid of the
frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from scissor_cli.sensing.ultrasound.transducer import ImageGrid

_TINY = 1e-6


@dataclass(frozen=True)
class TrackingParams:
    """Speckle-tracking settings (mm, probe frame)."""

    block_half_mm: tuple[float, float] = (2.0, 1.0)  # (lateral, depth) half-size of the matched block
    search_mm: tuple[float, float] = (1.5, 1.5)  # (lateral, depth) search half-range around the last estimate
    reanchor_below: float = 0.7  # peak NCC under which the previous frame becomes the anchor

    def __post_init__(self) -> None:
        if not all(v > 0 and math.isfinite(v) for v in (*self.block_half_mm, *self.search_mm)):
            raise ValueError(f"block and search sizes must be positive, got {self.block_half_mm}, {self.search_mm}")
        if not 0.0 < self.reanchor_below < 1.0:
            raise ValueError(f"reanchor_below must be in (0, 1), got {self.reanchor_below}")


def _check_frame(frame: np.ndarray, grid: ImageGrid, what: str) -> np.ndarray:
    f = np.asarray(frame)
    if f.shape != grid.shape:
        raise ValueError(f"{what} has shape {f.shape}, the grid {grid.shape}")
    return f


def _peak_offset(c_minus: float, c0: float, c_plus: float, gaussian: bool) -> float:
    """Sub-pixel offset in [-0.5, 0.5] of the peak through three samples at -1, 0, +1 (c0 the largest)."""
    if gaussian:
        c_minus, c0, c_plus = (math.log(max(v, _TINY)) for v in (c_minus, c0, c_plus))
    den = c_minus - 2.0 * c0 + c_plus
    if den >= 0.0:
        return 0.0
    return float(min(0.5, max(-0.5, 0.5 * (c_minus - c_plus) / den)))


def subpixel_peak(score: np.ndarray, gaussian: bool = True) -> tuple[float, float, float]:
    """(row, column, value) of the maximum of a score map (h, w), refined per axis by a 3-point fit.

    Gaussian: through the logarithms (scores clipped to a small positive
    value); otherwise a parabola. A peak on the map's border is not refined
    along that axis.
    """
    i, j = np.unravel_index(int(np.argmax(score)), score.shape)
    c0 = float(score[i, j])
    di = _peak_offset(score[i - 1, j], c0, score[i + 1, j], gaussian) if 0 < i < score.shape[0] - 1 else 0.0
    dj = _peak_offset(score[i, j - 1], c0, score[i, j + 1], gaussian) if 0 < j < score.shape[1] - 1 else 0.0
    return i + di, j + dj, c0


def ncc_map(block: np.ndarray, region: np.ndarray) -> np.ndarray:
    """NCC (h', w') of a block (h, w) at every placement inside a larger region (h + h' - 1, w + w' - 1)."""
    from skimage.feature import match_template  # noqa: PLC0415  (skimage's import is slow: only where used)

    return match_template(np.asarray(region, dtype=np.float32), np.asarray(block, dtype=np.float32))


def _block_slices(center_px: np.ndarray, half_px: np.ndarray, shape: tuple[int, int], what: str):
    r0, c0 = int(round(center_px[0])) - half_px[0], int(round(center_px[1])) - half_px[1]
    r1, c1 = r0 + 2 * half_px[0] + 1, c0 + 2 * half_px[1] + 1
    if r0 < 0 or c0 < 0 or r1 > shape[0] or c1 > shape[1]:
        raise ValueError(f"{what} (rows {r0}..{r1 - 1}, columns {c0}..{c1 - 1}) leaves the image {shape}")
    return (slice(r0, r1), slice(c0, c1)), np.array([r0, c0])


def block_match(
    reference: np.ndarray,
    current: np.ndarray,
    grid: ImageGrid,
    center_mm: np.ndarray,
    predicted_mm: np.ndarray | None = None,
    params: TrackingParams = TrackingParams(),
) -> tuple[np.ndarray, float]:
    """Displacement (2,) mm (lateral, depth) of the block around center_mm from reference to current, and its peak NCC.

    Frames (H, W) on `grid`; the block is searched for within
    params.search_mm of predicted_mm (default: center_mm). ValueError if the
    block or the search region leaves the image.
    """
    ref = _check_frame(reference, grid, "reference frame")
    cur = _check_frame(current, grid, "current frame")
    center = np.asarray(center_mm, dtype=float)
    pred = center if predicted_mm is None else np.asarray(predicted_mm, dtype=float)
    grid.require_inside(center, what="block centre")
    grid.require_inside(pred, what="predicted position")
    px = np.array([grid.dz_mm, grid.dx_mm])
    half = np.maximum(1, np.rint(np.array(params.block_half_mm[::-1]) / px)).astype(int)
    search = np.maximum(1, np.rint(np.array(params.search_mm[::-1]) / px)).astype(int)
    (bs, origin) = _block_slices(grid.to_pixel(center), half, grid.shape, "block")
    block = ref[bs]
    pred_px = grid.to_pixel(pred) + (origin + half - grid.to_pixel(center))  # where the block's centre pixel should be
    rs, r_origin = _block_slices(pred_px, half + search, grid.shape, "search region")
    score = ncc_map(block, cur[rs])
    i, j, peak = subpixel_peak(score)
    moved_px = r_origin + np.array([i, j]) - origin  # block's top-left corner, current minus reference
    return np.array([moved_px[1] * grid.dx_mm, moved_px[0] * grid.dz_mm]), peak


@dataclass
class TrackState:
    """A tracker's result for one frame: position (2,) mm (lateral, depth), peak NCC, whether it re-anchored."""

    position_mm: np.ndarray
    correlation: float
    reanchored: bool


class SpeckleTracker:
    """Follows a point (the lesion) over frames by NCC block matching with re-anchoring (module docstring).

    One per trial; `update` per frame. Holds the anchor frame, the previous
    frame and their positions (probe frame, mm).
    """

    def __init__(self, first_frame: np.ndarray, grid: ImageGrid, position_mm: np.ndarray,
                 params: TrackingParams = TrackingParams()) -> None:
        self.grid = grid
        self.params = params
        p = np.asarray(position_mm, dtype=float).copy()
        grid.require_inside(p, what="tracked position")
        self._anchor = _check_frame(first_frame, grid, "first frame").copy()
        self._anchor_mm = p
        self._previous = self._anchor
        self._previous_mm = p
        self.reanchorings = 0

    @property
    def position_mm(self) -> np.ndarray:
        """The latest estimate (2,) mm."""
        return self._previous_mm.copy()

    def update(self, frame: np.ndarray) -> TrackState:
        """Track into the next frame (H, W); returns the new estimate."""
        cur = _check_frame(frame, self.grid, "frame")
        d, peak = block_match(self._anchor, cur, self.grid, self._anchor_mm, self._previous_mm, self.params)
        reanchored = False
        if peak < self.params.reanchor_below and self._previous is not self._anchor:
            self._anchor, self._anchor_mm = self._previous, self._previous_mm
            d, peak = block_match(self._anchor, cur, self.grid, self._anchor_mm, self._previous_mm, self.params)
            self.reanchorings += 1
            reanchored = True
        self._previous = cur.copy()
        self._previous_mm = self._anchor_mm + d
        return TrackState(self._previous_mm.copy(), float(peak), reanchored)


def localise_lesion(
    envelope: np.ndarray,
    grid: ImageGrid,
    planned_mm: np.ndarray,
    radius_mm: float,
    search_mm: float = 3.0,
    lesion_db: float = -10.0,
) -> np.ndarray:
    """Centre (2,) mm (lateral, depth) of the lesion's disc of radius_mm nearest planned_mm on a frame (H, W).

    Only the sign of lesion_db (the lesion's echogenicity) is used: a
    darker lesion is sought as a dark disc, a brighter one as a bright
    disc. ValueError for 0 dB (nothing to see) and if the planned position,
    with the template and the search radius around it, leaves the image.
    """
    from scipy.ndimage import gaussian_filter  # noqa: PLC0415
    from scipy.signal import fftconvolve  # noqa: PLC0415

    env = _check_frame(envelope, grid, "frame")
    if not (math.isfinite(radius_mm) and radius_mm > 0 and math.isfinite(search_mm) and search_mm > 0):
        raise ValueError(f"lesion radius and search radius must be positive, got {radius_mm}, {search_mm}")
    if not (math.isfinite(lesion_db) and lesion_db != 0.0) and lesion_db != -math.inf:
        raise ValueError(f"a lesion of {lesion_db} dB has no contrast to be localised")
    planned = np.asarray(planned_mm, dtype=float)
    grid.require_inside(planned, what="planned lesion position")
    dx, dz = grid.dx_mm, grid.dz_mm
    outer = 1.5 * radius_mm
    hx, hz = int(math.ceil((outer + search_mm) / dx)), int(math.ceil((outer + search_mm) / dz))
    c = grid.to_pixel(planned)
    (sl, origin) = _block_slices(c, np.array([hz, hx]), grid.shape, "lesion search region")
    patch = 20.0 * np.log10(np.maximum(env[sl].astype(float), _TINY * max(float(env[sl].max()), _TINY)))
    # smooth over about one speckle grain (the lateral grain is 3-4 pixels, the axial about 2)
    patch = gaussian_filter(patch, sigma=(1.0, 1.5))
    tz, tx = int(math.ceil(outer / dz)), int(math.ceil(outer / dx))
    Z, X = np.meshgrid(np.arange(-tz, tz + 1) * dz, np.arange(-tx, tx + 1) * dx, indexing="ij")
    r = np.hypot(X, Z)
    inside, ring = r <= radius_mm, (r > radius_mm) & (r <= outer)
    template = ring / ring.sum() - inside / inside.sum()  # high where a dark disc sits in a brighter ring
    if lesion_db > 0:
        template = -template
    response = fftconvolve(patch, template[::-1, ::-1], mode="valid")
    # only placements within search_mm of the plan
    rz, rx = response.shape
    Zr, Xr = np.meshgrid((np.arange(rz) - (rz - 1) / 2) * dz, (np.arange(rx) - (rx - 1) / 2) * dx, indexing="ij")
    response = np.where(np.hypot(Xr, Zr) <= search_mm, response, -np.inf)
    i, j, _ = subpixel_peak(np.where(np.isfinite(response), response, np.nanmin(response[np.isfinite(response)])),
                            gaussian=False)
    return grid.to_mm(origin + np.array([i + tz, j + tx]))
