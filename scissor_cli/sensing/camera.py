"""The camera sensor: a pinhole camera over the tissue layer and a localisation bias (docs/model.md §8).

    z_c [u, v, 1]ᵀ = Ω T_cb [X, Y, Z, 1]ᵀ,    Ω = [[f/dx, 0, u0], [0, f/dy, v0], [0, 0, 1]]

(paper §4.2, eq. 32–38; no distortion). Points are in the layer frame (mm);
the layer is the plane Z = 0. T_cb (4×4) maps layer coordinates to camera
coordinates, whose z axis is the optical axis (z_c > 0 in front of the lens).

Conventions of `Camera.from_config` (a camera at `position_mm` looking
straight down −z at the layer): the image u axis runs along the layer's +x,
the v axis along the layer's −y (the usual image convention: v grows
"downwards" in the picture when +y is "up" on the layer). So the camera axes
in the layer frame are x_c = +x, y_c = −y, z_c = −z (right-handed), a point
on the layer has depth z_c = position_z, and one pixel covers
dx·position_z/f by dy·position_z/f mm of the layer (0.24 mm for the
example scene).

A simulated measurement projects the true point, adds Gaussian pixel noise,
rounds to whole pixels (the detector's quantisation) and back-projects the
pixel's ray onto Z = 0. The sensor's extent is not modelled: a point is
measured wherever it projects.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from scissor_cli.config import CameraConfig
from scissor_cli.sensing.sensor import TrialDraws, TrueState


def intrinsics(focal_mm: float, pixel_size_mm, principal_point_px) -> np.ndarray:
    """Ω (3, 3): focal length f (mm), pixel size [dx, dy] (mm/px), principal point [u0, v0] (px)."""
    dx, dy = pixel_size_mm
    u0, v0 = principal_point_px
    return np.array([[focal_mm / dx, 0.0, u0], [0.0, focal_mm / dy, v0], [0.0, 0.0, 1.0]])


def rigid_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The homogeneous 4×4 [[R, t], [0, 1]]."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def looking_down(position_mm) -> np.ndarray:
    """T_cb (4, 4) of a camera centred at position_mm (3,) looking down −z: x_c = x, y_c = −y, z_c = −z."""
    R = np.diag([1.0, -1.0, -1.0])  # rows: camera axes in layer coordinates
    return rigid_transform(R, -R @ np.asarray(position_mm, float))


@dataclass(frozen=True)
class Camera:
    """Pinhole camera: Ω (3, 3) in px, T_cb (4, 4) layer → camera (mm), noise σ in px."""

    intrinsics: np.ndarray
    T_cb: np.ndarray
    pixel_noise_px: float = 0.0

    @classmethod
    def from_config(cls, cfg: CameraConfig) -> "Camera":
        return cls(
            intrinsics=intrinsics(cfg.focal_mm, cfg.pixel_size_mm, cfg.principal_point_px),
            T_cb=looking_down(cfg.position_mm),
            pixel_noise_px=float(cfg.pixel_noise_px),
        )

    @property
    def rotation(self) -> np.ndarray:
        """R_cb (3, 3): layer → camera."""
        return self.T_cb[:3, :3]

    @property
    def centre(self) -> np.ndarray:
        """Optical centre (3,) in the layer frame, mm."""
        return -self.rotation.T @ self.T_cb[:3, 3]

    @property
    def depth_mm(self) -> float:
        """Distance (mm) along the optical axis from the centre to the layer plane Z = 0."""
        axis = self.rotation[2]  # the optical axis z_c in layer coordinates
        if abs(axis[2]) < 1e-12:
            raise ValueError("the optical axis is parallel to the layer plane")
        depth = -self.centre[2] / axis[2]
        if depth <= 0:
            raise ValueError("the layer plane is behind the camera")
        return float(depth)

    @property
    def mm_per_pixel(self) -> np.ndarray:
        """Pixel footprint [along u, along v] (2,) in mm at the layer, depth / (f/d).

        Exact everywhere for a camera looking straight down (the layer is
        fronto-parallel); for a tilted camera it is the footprint at the
        principal point of a fronto-parallel plane at the same depth, a guide
        only (the true footprint then varies across the image).
        """
        return self.depth_mm / np.diag(self.intrinsics)[:2]

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (K, 2), unrounded, of points (K, 2) on Z = 0 or (K, 3), mm.

        Raises ValueError if a point is not in front of the camera.
        """
        P = np.atleast_2d(np.asarray(points, float))
        if P.shape[1] == 2:
            P = np.column_stack([P, np.zeros(len(P))])
        Pc = P @ self.rotation.T + self.T_cb[:3, 3]
        if np.any(Pc[:, 2] <= 0):
            raise ValueError("a point lies behind the camera (z_c <= 0)")
        uvw = Pc @ self.intrinsics.T
        return uvw[:, :2] / uvw[:, 2:]

    def back_project(self, pixels: np.ndarray) -> np.ndarray:
        """Points (K, 2) mm on the layer plane Z = 0 seen at pixels (K, 2) px.

        Intersects each pixel's ray, centre + λ·d with d = R_cbᵀ Ω⁻¹ [u, v, 1]ᵀ,
        with Z = 0, so it holds for any T_cb. Raises ValueError if a ray is
        parallel to the layer or meets it behind the camera.
        """
        uv = np.atleast_2d(np.asarray(pixels, float))
        rays_c = np.linalg.solve(self.intrinsics, np.column_stack([uv, np.ones(len(uv))]).T).T
        rays = rays_c @ self.rotation  # R_cbᵀ d_c, row by row
        c = self.centre
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = -c[2] / rays[:, 2]
        if not np.all(np.isfinite(lam) & (lam > 0)):
            raise ValueError("a pixel's ray does not meet the layer plane in front of the camera")
        return c[:2] + lam[:, None] * rays[:, :2]

    def measure(self, points: np.ndarray, rng: np.random.Generator, noise_px: float | None = None) -> np.ndarray:
        """A simulated camera reading (K, 2) mm of true layer points (K, 2) mm.

        project → + N(0, σ²) px per axis (σ = noise_px, default the camera's
        pixel_noise_px) → round to whole pixels → back-project onto Z = 0.
        Draws exactly 2K normals from rng (even when σ = 0), so the stream of
        a seeded run does not depend on the noise level.
        """
        sigma = self.pixel_noise_px if noise_px is None else float(noise_px)
        uv = self.project(points)
        uv = uv + sigma * rng.standard_normal(uv.shape)
        return self.back_project(np.round(uv))


@dataclass(frozen=True)
class CameraSensor:
    """One trial's camera: pixel noise + rounding, and a fixed localisation bias.

    camera None reads the true position exactly (no rounding, no draws);
    bias_mm (2,) is the trial's offset of the image-based localisation;
    noise_px overrides the camera's pixel noise σ; rng is the stream of the
    per-frame pixel noise (the trial's).
    """

    camera: Optional[Camera] = None
    bias_mm: tuple[float, float] = (0.0, 0.0)
    noise_px: Optional[float] = None
    rng: Optional[np.random.Generator] = None

    @property
    def noise_mm(self) -> float:
        """σ (mm) of one reading's random part at the layer: pixel noise and rounding (σ² + 1/12 px²); 0 without a
        camera."""
        if self.camera is None:
            return 0.0
        px = self.camera.pixel_noise_px if self.noise_px is None else self.noise_px
        return float(np.sqrt(px * px + 1.0 / 12.0) * np.max(self.camera.mm_per_pixel))

    def measure(self, state: TrueState) -> np.ndarray:
        """The measured target (2,) mm of the true target's in-plane part."""
        p = np.array(state.target_mm, float)[:2]
        if self.camera is not None:
            rng = self.rng if self.rng is not None else np.random.default_rng(0)
            p = self.camera.measure(p[None], rng, self.noise_px)[0]
        return p + np.asarray(self.bias_mm, float)

    def reseeded(self, rng: np.random.Generator) -> "CameraSensor":
        return replace(self, rng=rng)


@dataclass(frozen=True)
class CameraModel:
    """The run's camera and the σ of its errors: pixel noise (px) and the per-trial localisation bias (mm)."""

    camera: Camera
    pixel_noise_px: float
    localisation_error_mm: float
    ideal: bool = False

    @property
    def exact(self) -> bool:
        return self.ideal

    def for_trial(self, draws: TrialDraws) -> CameraSensor:
        """The trial's camera: its bias is the trial's localisation normals times σ; its noise, the trial's stream."""
        if self.ideal:
            return CameraSensor()
        bias = np.asarray(draws.localisation_z, float) * self.localisation_error_mm
        return CameraSensor(self.camera, tuple(bias), noise_px=self.pixel_noise_px, rng=draws.rng)
