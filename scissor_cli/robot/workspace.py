"""Workspace of the puncture module (paper §2.3, Fig. 8; docs/model.md §11).

Monte-Carlo (or grid) samples of the joint space are mapped to needle tips;
the breast box is voxelised and two coverages are measured:

* `coverage` — the contract's number: the fraction of box voxels that hold at
  least one sampled tip. It is a sampling estimate and converges from below:
  the box is ~6 % of the paper robot's reachable volume, so 2·10⁵ uniform
  joint samples leave most 5 mm voxels empty even where they are reachable.
* `coverage_reachable` — sample-free: the fraction of voxel centres that IK
  reaches with the joints inside their limits, sweeping θ4 over its range.
  It says what the robot can do; `coverage` says what the samples showed.

Each comes with a multi-direction variant (beyond the paper): the fraction
of voxels reached from at least `min_directions` distinct insertion
directions, directions binned by the azimuth (and elevation) of the needle
axis. All lengths mm, angles rad unless a name says deg.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from scissor_cli.robot.chain import RobotModel
from scissor_cli.robot.ik import linear_interval

#: paper §2.1: the puncture workspace must hold a 150 × 330 × 100 mm box;
#: this placement is the shipped example scene's.
DEFAULT_BOX_MIN = np.array([60.0, 50.0, 200.0])
DEFAULT_BOX_MAX = np.array([210.0, 380.0, 300.0])

# A revolute joint is weighted like a prismatic one of this length when a
# grid spreads its points over the joints (≈ the paper's mid needle reach).
_REVOLUTE_LEVER_MM = 120.0

_FACES = ("x-", "x+", "y-", "y+", "z-", "z+")


# --------------------------------------------------------------------------- #
# Sampling
# --------------------------------------------------------------------------- #


def _grid_counts(widths: np.ndarray, n: int) -> np.ndarray:
    """Points per joint for a tensor grid of about n points with equal
    spacing (in mm-equivalents) along every joint of non-zero width."""
    moving = widths > 0
    if n <= 1 or not moving.any():
        return np.ones(widths.size, dtype=int)

    def counts(h: float) -> np.ndarray:
        return np.where(moving, np.maximum(2, np.floor(widths / h).astype(int) + 1), 1)

    lo, hi = 1e-9, float(widths.max()) * 2
    for _ in range(200):  # bisection on the spacing
        mid = np.sqrt(lo * hi)
        if np.prod(counts(mid).astype(float)) > n:
            lo = mid
        else:
            hi = mid
    return counts(hi)


def sample_joints(robot: RobotModel, n: int, seed: int = 0, method: str = "uniform") -> np.ndarray:
    """Joint samples inside the limits, (n, n_joints), mm / rad.

    uniform: n independent uniform samples from a seeded Generator.
    grid: a tensor grid (limits included) with about n points — the count
        is the closest product of per-joint counts not above n (at least 2
        per moving joint); deterministic, seed unused.
    """
    lo, hi = robot.lower, robot.upper
    if method == "uniform":
        rng = np.random.default_rng(seed)
        return rng.uniform(lo, hi, size=(int(n), lo.size))
    if method == "grid":
        widths = (hi - lo) * np.where(robot.revolute_mask, _REVOLUTE_LEVER_MM, 1.0)
        axes = [np.linspace(a, b, k) for a, b, k in zip(lo, hi, _grid_counts(widths, int(n)))]
        mesh = np.meshgrid(*axes, indexing="ij")
        return np.stack([m.ravel() for m in mesh], axis=1)
    raise ValueError(f"sampling method must be 'uniform' or 'grid', got {method!r}")


# --------------------------------------------------------------------------- #
# Voxels and coverage
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class VoxelGrid:
    """The box split into shape = (nx, ny, nz) voxels of size (3,) ≤ voxel_mm."""

    box_min: np.ndarray
    box_max: np.ndarray
    shape: tuple[int, int, int]
    size: np.ndarray

    @classmethod
    def of_box(cls, box_min, box_max, voxel_mm: float) -> "VoxelGrid":
        box_min = np.asarray(box_min, dtype=float).reshape(3)
        box_max = np.asarray(box_max, dtype=float).reshape(3)
        if not np.all(box_max > box_min):
            raise ValueError(f"box_max must exceed box_min on every axis, got {box_min} .. {box_max}")
        if not voxel_mm > 0:
            raise ValueError(f"voxel_mm must be positive, got {voxel_mm}")
        ext = box_max - box_min
        shape = np.maximum(1, np.ceil(ext / voxel_mm - 1e-9)).astype(int)
        return cls(box_min, box_max, tuple(int(s) for s in shape), ext / shape)

    @property
    def n(self) -> int:
        return int(np.prod(self.shape))

    def centres(self) -> np.ndarray:
        """(n, 3) voxel centres in C order of `shape`."""
        axes = [self.box_min[k] + (np.arange(self.shape[k]) + 0.5) * self.size[k] for k in range(3)]
        mesh = np.meshgrid(*axes, indexing="ij")
        return np.stack([m.ravel() for m in mesh], axis=1)

    def index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Linear voxel index of the points inside the box (closed box) and
        the (S,) mask of which points those are."""
        inside = np.all((points >= self.box_min) & (points <= self.box_max), axis=1)
        ijk = ((points[inside] - self.box_min) / self.size).astype(np.int64)
        ijk = np.minimum(ijk, np.array(self.shape) - 1)  # the max faces belong to the last voxel
        lin = (ijk[:, 0] * self.shape[1] + ijk[:, 1]) * self.shape[2] + ijk[:, 2]
        return lin, inside


@dataclass
class CoverageResult:
    """How much of the box is reached.

    coverage: fraction of voxels reached (≥ 1 tip / reachable centre).
    coverage_multi_direction: fraction reached from ≥ min_directions
        distinct direction bins.
    hits: (nx,ny,nz) int — tips per voxel (sampled) or feasible swept angles
        per voxel centre (reachable).
    directions: (nx,ny,nz) int — distinct direction bins per voxel.
    missed_bbox_min/max: (3,) mm bounds of the missed voxels, None if none.
    missed_by_face: face ("x-", …, "z+") → fraction of that face's voxel
        layer missed.
    summary: the missed part in words.
    """

    coverage: float
    coverage_multi_direction: float
    method: str
    grid: VoxelGrid
    min_directions: int
    direction_bin_deg: float
    hits: np.ndarray
    directions: np.ndarray
    points_in_box: int
    missed_bbox_min: Optional[np.ndarray]
    missed_bbox_max: Optional[np.ndarray]
    missed_by_face: dict[str, float]
    summary: str


def direction_bins(axes: np.ndarray, bin_deg: float) -> tuple[np.ndarray, int]:
    """Direction key per axis (S,) and the number of keys.

    Azimuth atan2(y, x) and polar angle from +z, each in bin_deg bins; the
    paper's needle is horizontal, so only the azimuth varies there.
    """
    b = np.deg2rad(bin_deg)
    n_az = int(np.ceil(2 * np.pi / b - 1e-9))
    n_el = int(np.ceil(np.pi / b - 1e-9))
    az = np.arctan2(axes[:, 1], axes[:, 0])
    el = np.arccos(np.clip(axes[:, 2] / np.maximum(np.linalg.norm(axes, axis=1), 1e-300), -1.0, 1.0))
    ia = np.minimum(np.floor((az + np.pi) / b).astype(np.int64), n_az - 1)
    ie = np.minimum(np.floor(el / b).astype(np.int64), n_el - 1)
    return ia * n_el + ie, n_az * n_el


def _distinct_per_voxel(vox: np.ndarray, keys: np.ndarray, n_keys: int, n_vox: int) -> np.ndarray:
    """(n_vox,) number of distinct keys among the (voxel, key) pairs."""
    pairs = np.unique(vox * n_keys + keys)
    return np.bincount(pairs // n_keys, minlength=n_vox)


def _describe_missed(grid: VoxelGrid, missed: np.ndarray, hits: np.ndarray, method: str):
    """Bounding box, per-face fractions and a sentence about missed voxels."""
    frac = float(missed.mean())
    faces = {
        "x-": missed[0].mean(), "x+": missed[-1].mean(),
        "y-": missed[:, 0].mean(), "y+": missed[:, -1].mean(),
        "z-": missed[:, :, 0].mean(), "z+": missed[:, :, -1].mean(),
    }
    faces = {k: float(v) for k, v in faces.items()}
    vox = f"{grid.n} voxels of {' x '.join(f'{s:.2f}' for s in grid.size)} mm"
    if not missed.any():
        return None, None, faces, f"the whole box is reached ({vox})"
    ijk = np.argwhere(missed)
    bmin = grid.box_min + ijk.min(axis=0) * grid.size
    bmax = grid.box_min + (ijk.max(axis=0) + 1) * grid.size
    span = ", ".join(f"{a} {lo:.0f}..{hi:.0f}" for a, lo, hi in zip("xyz", bmin, bmax))
    # where along each axis the misses concentrate (thirds of the box)
    lean = []
    for k, a in enumerate("xyz"):
        third = np.minimum(ijk[:, k] * 3 // grid.shape[k], 2)
        share = np.bincount(third, minlength=3) / len(ijk)
        if share.max() >= 0.6:
            lean.append(f"{share.max():.0%} in the {('low', 'middle', 'high')[int(share.argmax())]} third of {a}")
    worst = sorted(faces.items(), key=lambda kv: -kv[1])
    face_txt = ", ".join(f"{k} {v:.0%}" for k, v in worst if v > 0) or "none"
    text = (f"missed {int(missed.sum())} of {vox} ({frac:.1%}); missed voxels span {span} mm; "
            f"face layers missed: {face_txt}")
    if lean:
        text += "; " + "; ".join(lean)
    if method == "sampled":
        mean_hits = float(hits.sum() / grid.n)
        if mean_hits < 5 or not lean:
            text += (f"; only {mean_hits:.1f} tips per voxel on average — scattered misses are "
                     "under-sampling, compare coverage_reachable or raise the sample count")
    return bmin, bmax, faces, text


def _result(grid, method, hits, directions, min_directions, bin_deg, n_in) -> CoverageResult:
    hits = hits.reshape(grid.shape)
    directions = directions.reshape(grid.shape)
    reached = hits > 0
    bmin, bmax, faces, text = _describe_missed(grid, ~reached, hits, method)
    return CoverageResult(
        coverage=float(reached.mean()),
        coverage_multi_direction=float((directions >= min_directions).mean()),
        method=method, grid=grid, min_directions=int(min_directions), direction_bin_deg=float(bin_deg),
        hits=hits, directions=directions, points_in_box=int(n_in),
        missed_bbox_min=bmin, missed_bbox_max=bmax, missed_by_face=faces, summary=text,
    )


def coverage(tips, axes, box_min, box_max, voxel_mm: float = 5.0, min_directions: int = 3,
             direction_bin_deg: float = 10.0) -> CoverageResult:
    """Sampled coverage of the box by tips (S,3) mm with needle axes (S,3).

    The box is split into voxels no larger than voxel_mm; a voxel counts
    once a tip lies in it, and for the multi-direction figure once tips
    with ≥ min_directions distinct direction bins lie in it.
    """
    tips = np.asarray(tips, dtype=float).reshape(-1, 3)
    axes = np.asarray(axes, dtype=float).reshape(-1, 3)
    if len(tips) != len(axes):
        raise ValueError(f"tips and axes differ in length: {len(tips)} vs {len(axes)}")
    grid = VoxelGrid.of_box(box_min, box_max, voxel_mm)
    lin, inside = grid.index(tips)
    hits = np.bincount(lin, minlength=grid.n)
    keys, n_keys = direction_bins(axes[inside], direction_bin_deg)
    directions = _distinct_per_voxel(lin, keys, n_keys, grid.n)
    return _result(grid, "sampled", hits, directions, min_directions, direction_bin_deg, lin.size)


def reachable_coverage(robot: RobotModel, box_min, box_max, voxel_mm: float = 5.0, min_directions: int = 3,
                       direction_bin_deg: float = 10.0, angle_step_deg: float = 1.0) -> CoverageResult:
    """Sample-free coverage: voxel centres that IK reaches inside the limits.

    θ4 is swept over its range in angle_step_deg steps (a loop over angles,
    vectorised over voxels); at each angle a centre is reachable when d1 is
    in range and the d5 interval that keeps d2, d3, d5 in range is non-empty
    (the same test as `robot.ik.ik_batch`). Paper-structure robots only.
    """
    cf = robot.require_closed_form()
    grid = VoxelGrid.of_box(box_min, box_max, voxel_mm)
    P = grid.centres()
    lo, hi, off = robot.lower, robot.upper, cf.offsets
    d1 = P[:, 2] - cf.a5 - off[0]
    d1_ok = (d1 >= lo[0]) & (d1 <= hi[0])
    n_ang = max(2, int(np.ceil(np.rad2deg(hi[3] - lo[3]) / angle_step_deg)) + 1)
    thetas = np.linspace(lo[3], hi[3], n_ang)
    approach = np.stack([-np.cos(thetas + off[3]), -np.sin(thetas + off[3]), np.zeros(n_ang)], axis=1)
    keys, _ = direction_bins(approach, direction_bin_deg)
    _, keys = np.unique(keys, return_inverse=True)  # only the bins the sweep visits
    n_keys = int(keys.max()) + 1

    hits = np.zeros(grid.n, dtype=np.int64)
    bins_hit = np.zeros((grid.n, n_keys), dtype=bool)
    lo5, hi5 = np.full(grid.n, lo[4]), np.full(grid.n, hi[4])
    for th, key in zip(thetas, keys):
        c, s = np.cos(th + off[3]), np.sin(th + off[3])
        b3 = P[:, 0] - cf.a1 - off[2] + (cf.d6 + off[4]) * c
        b2 = P[:, 1] - cf.a3 - off[1] + (cf.d6 + off[4]) * s
        i3 = linear_interval(b3, np.full_like(b3, c), lo[2], hi[2])
        i2 = linear_interval(b2, np.full_like(b2, s), lo[1], hi[1])
        ok = d1_ok & (np.maximum.reduce([lo5, i3[0], i2[0]]) <= np.minimum.reduce([hi5, i3[1], i2[1]]))
        hits += ok
        bins_hit[:, key] |= ok
    return _result(grid, "reachable", hits, bins_hit.sum(axis=1), min_directions, direction_bin_deg,
                   int((hits > 0).sum()))


# --------------------------------------------------------------------------- #
# The workspace run
# --------------------------------------------------------------------------- #


@dataclass
class WorkspaceResult:
    """joints (S,5) mm/rad, tip (S,3) mm, axis (S,3); `coverage` sampled,
    `reachable` the IK-based one (None for a robot without closed form);
    timings in seconds."""

    joints: np.ndarray
    tip: np.ndarray
    axis: np.ndarray
    coverage: CoverageResult
    reachable: Optional[CoverageResult]
    box_min: np.ndarray
    box_max: np.ndarray
    voxel_mm: float
    seed: int
    method: str
    joint_names: tuple[str, ...]
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def samples(self) -> int:
        return int(self.joints.shape[0])


def run_workspace(robot: RobotModel, box_min=None, box_max=None, samples: int = 200_000, seed: int = 0,
                  method: str = "uniform", voxel_mm: float = 5.0, min_directions: int = 3,
                  direction_bin_deg: float = 10.0) -> WorkspaceResult:
    """Sample the joints, map them to tips, measure both coverages.

    box_min / box_max default to the paper's 150 × 330 × 100 mm box at the
    example scene's placement.
    """
    box_min = DEFAULT_BOX_MIN.copy() if box_min is None else np.asarray(box_min, dtype=float)
    box_max = DEFAULT_BOX_MAX.copy() if box_max is None else np.asarray(box_max, dtype=float)
    t = {}
    t0 = time.perf_counter()
    q = sample_joints(robot, samples, seed, method)
    t1 = time.perf_counter()
    tip, axis = robot.tip_and_axis(q)
    t2 = time.perf_counter()
    cov = coverage(tip, axis, box_min, box_max, voxel_mm, min_directions, direction_bin_deg)
    t3 = time.perf_counter()
    reach = (reachable_coverage(robot, box_min, box_max, voxel_mm, min_directions, direction_bin_deg)
             if robot.has_closed_form else None)
    t4 = time.perf_counter()
    t.update(sample_s=t1 - t0, fk_s=t2 - t1, coverage_s=t3 - t2, reachable_s=t4 - t3, total_s=t4 - t0)
    return WorkspaceResult(q, tip, axis, cov, reach, box_min, box_max, float(voxel_mm), int(seed), method,
                           robot.joint_names, t)

