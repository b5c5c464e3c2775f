"""3-D cameras as the loop's sensor: a trial's reading with its noise and bias, and the run's model (§19).

A `BodyCameraSensor` reads the lesion's centre (`TrueState.target_mm`, (3,)
in the body frame) with one camera, which does not see depth along its
view, or with two or more that triangulate (`sensing.camera3d`). Its
`measure` is the `Sensor` interface's: (3,) mm with NaN in the coordinates
it does not see; `reading` adds what it does see (`Reading.seen`, the
projector the controller drives the error through) and the full point.

The errors mirror the 2-D camera's (`sensing.camera.CameraModel`): pixel
noise σ (the trial profile's, else each camera's `pixel_noise_px`) and
rounding per frame, drawn from the trial's stream; a localisation bias per
camera fixed for the trial, a 3-vector in the body frame of σ =
`localisation_error_mm` per axis. It shifts that camera's rays, so only its
part across the view matters. Its standard normals are the trial's
`localisation_z` (the first camera's x and y, so a camera above has the 2-D
camera's bias) and, for the rest, the stream (key + (BIAS_STREAM,)).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional, Sequence, Union

import numpy as np

from scissor_cli.config.body_sections import BodyCameraConfig
from scissor_cli.sensing.camera import Camera
from scissor_cli.sensing.camera3d import (
    observed_pixels,
    optical_axis,
    pixel_rays,
    plane_points,
    posed_camera,
    reading_covariance,
    seen_projector,
    triangulate,
    unseen_axes,
)
from scissor_cli.sensing.sensor import TrialDraws, TrueState

#: the tag of the stream of the localisation normals beyond the trial's localisation_z
BIAS_STREAM = 31


@dataclass(frozen=True, eq=False)
class Reading:
    """One reading of the lesion's centre.

    position (3,) mm: NaN in the coordinates the sensor does not see (one
    camera within `camera3d.SEEN_AXIS_DEG` of an axis); point (3,) mm: the
    whole point, the reference's depth along a single camera's view (equal
    to position where that is not NaN; an oblique camera reports it all);
    seen (3, 3): the orthogonal projector onto what is observed (I − a aᵀ
    for one camera looking along a, I for a triangulation).
    """

    position: np.ndarray
    point: np.ndarray
    seen: np.ndarray

    def observed_error(self, goal_mm) -> np.ndarray:
        """(3,) the part of point − goal the sensor observes, seen (point − goal): no NaN."""
        return self.seen @ (self.point - np.asarray(goal_mm, float))


def _as_cameras(cameras) -> tuple[Camera, ...]:
    cams = (cameras,) if isinstance(cameras, (Camera, BodyCameraConfig)) else tuple(cameras)
    if not cams:
        raise ValueError("a 3-D camera sensor needs at least one camera")
    return tuple(c if isinstance(c, Camera) else posed_camera(c) for c in cams)


@dataclass(frozen=True, eq=False)
class BodyCameraSensor:
    """One trial's camera or cameras over the body.

    reference_mm (3,): the point whose plane normal to a single camera's
    view its readings lie on (the lesion's planned position; required for
    one camera; for several, where `noise_mm` is evaluated, default the
    point closest to their optical axes); biases_mm (n, 3): each camera's
    localisation bias (zero by default); noise_px (n,): pixel noise σ per
    camera (None: each camera's own); rng: the per-frame noise's stream
    (None: a fresh default_rng(0) per reading, as the 2-D `CameraSensor`);
    exact: no noise, no rounding, no draws (the nominal sensor; the view's
    geometry stays: one camera still does not see its depth).
    """

    cameras: tuple[Camera, ...]
    reference_mm: Optional[np.ndarray] = None
    biases_mm: Optional[np.ndarray] = None
    noise_px: Optional[tuple[float, ...]] = None
    rng: Optional[np.random.Generator] = None
    exact: bool = False

    def __post_init__(self):
        cams = _as_cameras(self.cameras)
        object.__setattr__(self, "cameras", cams)
        n = len(cams)
        if self.reference_mm is not None:
            object.__setattr__(self, "reference_mm", np.asarray(self.reference_mm, float).reshape(3))
        elif n == 1:
            raise ValueError("one camera needs a reference point (the lesion's planned position) for its readings")
        biases = np.zeros((n, 3)) if self.biases_mm is None else np.asarray(self.biases_mm, float).reshape(n, 3)
        object.__setattr__(self, "biases_mm", biases)
        noise = tuple(c.pixel_noise_px for c in cams) if self.noise_px is None else tuple(map(float, self.noise_px))
        if len(noise) != n:
            raise ValueError(f"noise_px has {len(noise)} values for {n} cameras")
        object.__setattr__(self, "noise_px", noise)

    @property
    def triangulates(self) -> bool:
        return len(self.cameras) > 1

    @property
    def seen(self) -> np.ndarray:
        """(3, 3) the projector onto what the sensor observes: I − a aᵀ for one camera, I for several."""
        return np.eye(3) if self.triangulates else seen_projector(optical_axis(self.cameras[0]))

    @property
    def unseen(self) -> np.ndarray:
        """(3,) bool: the coordinates `measure` reports as NaN."""
        return np.zeros(3, bool) if self.triangulates else unseen_axes(optical_axis(self.cameras[0]))

    @property
    def noise_point_mm(self) -> np.ndarray:
        """(3,) where `noise_mm` is evaluated: the reference, else the point closest to the optical axes."""
        if self.reference_mm is not None:
            return self.reference_mm
        centres = np.stack([c.centre for c in self.cameras])
        axes = np.stack([optical_axis(c) for c in self.cameras])[:, None, :]
        return triangulate(centres, axes)[0]

    @property
    def noise_mm(self) -> float:
        """σ (mm) of one reading's random part, pixel noise and rounding (σ² + 1/12 px²), at the noise point
        along its worst seen direction: one camera, √(σ² + 1/12) × its footprint there (the 2-D
        camera's σ); several, the triangulation's (`camera3d.reading_covariance`). 0 when exact."""
        if self.exact:
            return 0.0
        cov = reading_covariance(self.cameras, self.noise_point_mm, self.noise_px)
        return float(np.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0)))

    def read_points(self, points) -> np.ndarray:
        """(K, 3) whole readings (the `Reading.point`s) of true points (K, 3) mm, in one vectorised pass.

        Per frame: each camera projects, adds its pixel noise, rounds
        (`camera3d.observed_pixels`, 2 normals per point and camera); then one
        camera's ray meets the reference's plane and its bias's part across
        the view is added, or the cameras' rays, each moved by its bias, are
        triangulated.
        """
        P = np.atleast_2d(np.asarray(points, float))
        rng = None if self.exact else (self.rng if self.rng is not None else np.random.default_rng(0))
        uv = observed_pixels(self.cameras, P, rng, self.noise_px)
        if not self.triangulates:
            cam = self.cameras[0]
            return plane_points(cam, uv[0], self.reference_mm) + self.seen @ self.biases_mm[0]
        origins = np.stack([c.centre for c in self.cameras]) + self.biases_mm
        directions = np.stack([pixel_rays(c, uv[i]) for i, c in enumerate(self.cameras)])
        return triangulate(origins, directions)

    def reading(self, state: TrueState) -> Reading:
        """The reading of the true lesion centre state.target_mm (3,)."""
        point = self.read_points(np.asarray(state.target_mm, float).reshape(1, 3))[0]
        return Reading(np.where(self.unseen, np.nan, point), point, self.seen)

    def measure(self, state: TrueState) -> np.ndarray:
        """(3,) mm, NaN in the coordinates not seen (the history's measured_x/_y/_z)."""
        return self.reading(state).position

    def reseeded(self, rng: np.random.Generator) -> "BodyCameraSensor":
        """The same cameras, reference and biases, the frame noise from rng."""
        return replace(self, rng=rng)


@dataclass(frozen=True, eq=False)
class BodyCameraModel:
    """The run's 3-D camera or cameras and the σ of their errors.

    pixel_noise_px: the trial profile's σ for every camera (None: each
    camera's own); localisation_error_mm: σ per axis of each camera's
    bias; reference_mm (3,): the reading plane's point when a trial's draws
    give no goal; ideal: every trial's sensor is the nominal one.
    """

    cameras: tuple[Camera, ...]
    pixel_noise_px: Optional[float] = None
    localisation_error_mm: float = 0.0
    reference_mm: Optional[np.ndarray] = None
    ideal: bool = False

    def __post_init__(self):
        object.__setattr__(self, "cameras", _as_cameras(self.cameras))

    @classmethod
    def from_config(cls, cameras: Union[BodyCameraConfig, Sequence[BodyCameraConfig]],
                    pixel_noise_px: Optional[float] = None, localisation_error_mm: float = 0.0,
                    reference_mm=None, ideal: bool = False) -> "BodyCameraModel":
        """From the scene's `camera` (one) or `cameras` (a list)."""
        return cls(_as_cameras(cameras), pixel_noise_px, float(localisation_error_mm), reference_mm, ideal)

    @property
    def exact(self) -> bool:
        """Every trial's sensor is exact: no bias, noise or rounding (in what it sees: one camera's depth is not)."""
        return self.ideal

    def _noise(self) -> Optional[tuple[float, ...]]:
        return None if self.pixel_noise_px is None else (float(self.pixel_noise_px),) * len(self.cameras)

    def _reference(self, goal_mm) -> Optional[np.ndarray]:
        ref = goal_mm if goal_mm is not None else self.reference_mm
        return None if ref is None else np.asarray(ref, float).reshape(3)

    def biases(self, draws: TrialDraws) -> np.ndarray:
        """(n, 3) mm: each camera's localisation bias, σ × standard normals (the trial's localisation_z first,
        then its BIAS_STREAM)."""
        n = 3 * len(self.cameras)
        z = np.asarray(draws.localisation_z, float).ravel()[:n]
        if len(z) < n:
            extra = np.random.default_rng(tuple(draws.key) + (BIAS_STREAM,)).standard_normal(n - len(z))
            z = np.concatenate([z, extra])
        return self.localisation_error_mm * z.reshape(-1, 3)

    def for_trial(self, draws: TrialDraws) -> BodyCameraSensor:
        """The trial's sensor: biases from its draws, frame noise from its stream, reading plane through its goal."""
        if self.ideal:
            return self.nominal(draws.goal_mm)
        return BodyCameraSensor(self.cameras, self._reference(draws.goal_mm), self.biases(draws), self._noise(),
                                draws.rng)

    def nominal(self, goal_mm=None, target_index: int = 0, seed: int = 0) -> BodyCameraSensor:
        """The sensor with no error drawn: exact projection, no noise, rounding or bias (a camera draws nothing per
        lesion or seed: target_index and seed are the ultrasound's, `sensing.ultrasound.body_sensor`)."""
        return BodyCameraSensor(self.cameras, self._reference(goal_mm), None, self._noise(), None, exact=True)
