"""Tissue as random point scatterers, drawn once per trial in the layer's rest frame (docs/ultrasound.md §2).

A homogeneous Poisson process of the given in-plane density fills the
region; each scatterer also gets an elevation coordinate, uniform in
+-elevation_half_mm (the slab of tissue the elevation beam sees; 0 puts
every scatterer in the imaging plane), and an amplitude: a standard normal
times the echogenicity of where it lies, 10^(dB/20).

Echogenicity is relative to the background tissue (0 dB). Later rules
override earlier ones: background, then the obstacles in their order, then
the lesion (a sphere of the given radius around its centre and elevation;
a disc when every elevation is 0). Defaults, `ECHOGENICITY_DB`:

* lesion -10 dB: most breast carcinomas are hypoechoic, and the BI-RADS
  ultrasound lexicon grades echogenicity against fat, which is itself
  darker than fibroglandular tissue; -10 dB is a moderate, clearly
  visible contrast;
* vessel lumen -40 dB: blood backscatters some 30-40 dB below soft tissue
  at clinical frequencies (red cells are far smaller than a wavelength),
  so a lumen looks anechoic on a 40-60 dB display;
* cyst -40 dB: a simple cyst is anechoic;
* nerve +3 dB: peripheral nerves show hypoechoic fascicles inside
  hyperechoic epineurium ("honeycomb"); averaged over a resolution cell
  they are slightly brighter than the surrounding fat;
* fat -6 dB, fibroglandular +3 dB: fat lobules are the darker, the
  glandular tissue the brighter component of breast parenchyma.

Fully developed speckle needs many scatterers per resolution cell; with
Gaussian amplitudes the envelope's statistics approach the Rayleigh law
more slowly than with equal ones, so the default of `psf.PsfModel.
density_per_mm2` is 20 per cell, twice the classic 10 (the envelope's
mean/std against the density: benchmark bench_ultrasound).

The scatterers are drawn tile by tile (1 mm squares in raster order) so
that neighbours in the arrays are neighbours in space: the fast model's
splatting then stays in cache. The draw is deterministic for a given
generator state and uses the same number of draws whatever the lesion
and obstacles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from scissor_cli.geometry import points_in_polygon

ECHOGENICITY_DB: dict[str, float] = {
    "background": 0.0,
    "lesion": -10.0,
    "vessel_lumen": -40.0,
    "cyst": -40.0,
    "nerve": 3.0,
    "fat": -6.0,
    "fibroglandular": 3.0,
}

_TILE_MM = 1.0
_CHUNK = 65536  # points per point-in-polygon call: bounds its (points x edges) temporaries


@dataclass(frozen=True)
class Scatterers:
    """Point scatterers: positions_mm (S, 2) in the layer's rest plane, elevation_mm (S,), amplitude (S,) float32."""

    positions_mm: np.ndarray
    elevation_mm: np.ndarray
    amplitude: np.ndarray

    def __len__(self) -> int:
        return len(self.amplitude)


def _region_polygon(region_mm: np.ndarray) -> np.ndarray:
    r = np.asarray(region_mm, dtype=float)
    if r.ndim != 2 or r.shape[1] != 2 or not np.all(np.isfinite(r)):
        raise ValueError(f"region must be a polygon (P, 2) or a box [[x0, y0], [x1, y1]] in mm, got shape {r.shape}")
    if r.shape[0] == 2:  # a box
        (x0, y0), (x1, y1) = np.minimum(r[0], r[1]), np.maximum(r[0], r[1])
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"region box must have positive width and height, got {r.tolist()}")
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    if r.shape[0] < 3:
        raise ValueError("region polygon needs at least 3 vertices")
    return r


def _inside(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(K,) bool: points (K, 2) inside the polygon, tested only where its bounding box allows, in chunks."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    out = np.zeros(len(points), dtype=bool)
    cand = np.flatnonzero(np.all((points >= lo) & (points <= hi), axis=1))
    for a in range(0, len(cand), _CHUNK):
        idx = cand[a:a + _CHUNK]
        out[idx] = points_in_polygon(points[idx], poly)
    return out


def _gain(db: float) -> float:
    """Amplitude factor of an echogenicity in dB (-inf: 0, an anechoic region)."""
    if math.isnan(db) or db == math.inf:
        raise ValueError(f"echogenicity must be a finite dB value or -inf, got {db!r}")
    return 0.0 if db == -math.inf else 10.0 ** (db / 20.0)


def draw_scatterers(
    rng: np.random.Generator,
    region_mm: np.ndarray,
    density_per_mm2: float,
    elevation_half_mm: float = 0.0,
    lesion_center_mm: np.ndarray | None = None,
    lesion_radius_mm: float = 0.0,
    lesion_db: float = ECHOGENICITY_DB["lesion"],
    obstacles: Sequence[tuple[np.ndarray, float]] = (),
    lesion_elevation_mm: float = 0.0,
) -> Scatterers:
    """Scatterers filling region_mm (polygon (P, 2) or box (2, 2), mm) at density_per_mm2 in the plane.

    lesion_center_mm (2,) and lesion_radius_mm give the lesion (a sphere at
    lesion_elevation_mm); obstacles are (polygon (Q, 2) mm, dB) pairs,
    prisms across the elevation band. Module docstring for the rules.
    """
    poly = _region_polygon(region_mm)
    if not (math.isfinite(density_per_mm2) and density_per_mm2 > 0):
        raise ValueError(f"scatterer density must be positive, got {density_per_mm2!r} per mm^2")
    if not (math.isfinite(elevation_half_mm) and elevation_half_mm >= 0):
        raise ValueError(f"elevation half-width must be >= 0 mm, got {elevation_half_mm!r}")
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    nx, ny = (int(math.ceil((hi[i] - lo[i]) / _TILE_MM - 1e-9)) for i in (0, 1))
    counts = rng.poisson(density_per_mm2 * _TILE_MM * _TILE_MM, size=nx * ny)
    tiles = np.repeat(np.arange(nx * ny), counts)  # raster order: row (y) by row, x within a row
    S = len(tiles)
    corner = lo + _TILE_MM * np.stack([tiles % nx, tiles // nx], axis=1)
    pos = corner + _TILE_MM * rng.random((S, 2))
    elevation = elevation_half_mm * (2.0 * rng.random(S) - 1.0)
    amp = rng.standard_normal(S)
    keep = np.all(pos <= hi, axis=1) & _inside(pos, poly)
    pos, elevation, amp = pos[keep], elevation[keep], amp[keep]

    gain = np.ones(len(amp))
    for obstacle, db in obstacles:
        o = np.asarray(obstacle, dtype=float)
        if o.ndim != 2 or o.shape[0] < 3 or o.shape[1] != 2:
            raise ValueError(f"an obstacle must be a polygon (Q, 2) in mm, got shape {o.shape}")
        gain[_inside(pos, o)] = _gain(float(db))
    if lesion_center_mm is not None and lesion_radius_mm > 0:
        c = np.asarray(lesion_center_mm, dtype=float).reshape(2)
        d2 = np.sum((pos - c) ** 2, axis=1) + (elevation - lesion_elevation_mm) ** 2
        gain[d2 <= lesion_radius_mm ** 2] = _gain(float(lesion_db))
    return Scatterers(positions_mm=pos, elevation_mm=elevation, amplitude=(amp * gain).astype(np.float32))
