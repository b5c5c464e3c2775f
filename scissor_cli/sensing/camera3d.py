"""Cameras with a full pose over a 3-D body: projection, one camera's reading, triangulation (docs/model.md §19).

The pinhole model, the intrinsics Ω and T_cb are the 2-D camera's
(`sensing.camera`, §8); what is new is the pose and what a reading of a
3-D point is.

**Pose** (`posed_camera`). A camera at `position_mm` looks at `look_at_mm`;
absent, straight down −z (the paper's CCD), with exactly the 2-D camera's
axes x_c = +x, y_c = −y, z_c = −z (`sensing.camera.looking_down`). A
camera looking along any other unit axis a is the looking-down camera
*tilted* onto a: rotated by the smallest rotation that takes −z to a (about
the horizontal axis (−z) × a). So the image axes turn with the tilt and
the camera never rolls about its own axis: a camera beside the body looking
along −x has x_c = −z (u runs down the picture) and y_c = −y. The frame is
continuous in a everywhere except looking straight up (+z), where the
tilt's axis is undefined (by the hairy-ball theorem any convention has such
a point); there the frame is the looking-down one turned 180° about x:
x_c = +x, y_c = +y, z_c = +z.

**One camera's reading** (`plane_points`): project, add Gaussian pixel noise,
round to whole pixels, and take the pixel's ray. A camera does not see depth
along its view: the reading is the ray's point on the plane through a
reference point (the lesion's planned position, which the caller gives)
normal to the optical axis a, and what it observes is the plane's part,
`seen` = I − a aᵀ. The component along a is the reference's, not a
measurement. The coordinate axes within `SEEN_AXIS_DEG` of a are reported
as NaN (`unseen_axes`): a camera above gives z = NaN. An oblique camera
has no such axis: its reading is the full point on the plane, every
coordinate a mix of what it sees and the reference's depth, and only
`seen` says which part is measured. The reference's depth is assumed, so a
lesion off it by δ along a and seen at angle θ from the optical axis reads
off by δ·tan θ within the plane (parallax: 7.5 % of δ for a lesion 30 mm
off the axis of a camera 400 mm away).

**Two or more cameras** (`triangulate`): after each camera's noise and
rounding, the point closest to all rays in least squares,
Σ (I − dᵢdᵢᵀ) p = Σ (I − dᵢdᵢᵀ) oᵢ (dᵢ unit), and it sees all three axes.
The normal matrix is singular when the rays are parallel; `camera_problems`
refuses cameras whose sight lines differ by less than
`MIN_TRIANGULATION_DEG`, where the depth along them would be the pixel
noise magnified by 1/sin of the angle.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from scissor_cli.config.body_sections import BodyCameraConfig
from scissor_cli.sensing.camera import Camera, intrinsics, looking_down, rigid_transform

#: a coordinate axis within this angle (deg) of a single camera's view is not seen (its reading is NaN)
SEEN_AXIS_DEG = 1.0
#: cameras that triangulate must have two sight lines at least this far apart (deg)
MIN_TRIANGULATION_DEG = 5.0
#: the looking-down camera's axes as rows in the body frame: x_c = x, y_c = −y, z_c = −z
_DOWN = np.diag([1.0, -1.0, -1.0])


def view_rotation(axis) -> np.ndarray:
    """R_cb (3, 3), rows the camera axes in the body frame, of a camera looking along axis (3,) (any length).

    The looking-down rotation tilted by the smallest rotation Q taking −z to
    the unit axis a: R = diag(1, −1, −1) Qᵀ, Q = I + [k]× + [k]×²/(1 + c)
    with k = (−z) × a, c = −a_z (Rodrigues). Looking straight up, Q is the
    half turn about x.
    """
    a = np.asarray(axis, float)
    n = float(np.linalg.norm(a))
    if not n > 0.0:
        raise ValueError("a camera's view axis must not be the zero vector")
    a = a / n
    c = -a[2]
    if 1.0 + c <= 1e-15:  # looking straight up: the tilt's axis is undefined
        Q = np.diag([1.0, -1.0, -1.0])
    else:
        k = np.array([a[1], -a[0], 0.0])  # (0, 0, −1) × a
        Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        Q = np.eye(3) + Kx + Kx @ Kx / (1.0 + c)
    return _DOWN @ Q.T


def posed_camera(cfg: BodyCameraConfig) -> Camera:
    """The `Camera` of a 3-D scene's camera section: at position_mm, looking at look_at_mm (None: down −z).

    With look_at_mm None it is `Camera.from_config`'s camera exactly.
    """
    centre = np.asarray(cfg.position_mm, float)
    if cfg.look_at_mm is None:
        T = looking_down(centre)
    else:
        R = view_rotation(np.asarray(cfg.look_at_mm, float) - centre)
        T = rigid_transform(R, -R @ centre)
    return Camera(intrinsics(cfg.focal_mm, cfg.pixel_size_mm, cfg.principal_point_px), T, float(cfg.pixel_noise_px))


def optical_axis(camera: Camera) -> np.ndarray:
    """The unit optical axis z_c (3,) in the body frame."""
    return camera.rotation[2].copy()


def unseen_axes(axis) -> np.ndarray:
    """(3,) bool: the coordinate axes within SEEN_AXIS_DEG of the view axis, which one camera does not see."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.abs(a) >= np.cos(np.radians(SEEN_AXIS_DEG))


def seen_projector(axis) -> np.ndarray:
    """I − a aᵀ (3, 3): the orthogonal projector onto the plane a camera looking along axis observes."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.eye(3) - np.outer(a, a)


def depth_mm(camera: Camera, points) -> np.ndarray:
    """(K,) distance (mm) of points (K, 3) in front of the camera along its optical axis."""
    P = np.atleast_2d(np.asarray(points, float))
    return (P - camera.centre) @ optical_axis(camera)


def footprint_mm(camera: Camera, points) -> np.ndarray:
    """(K,) mm one pixel covers (the larger of u, v) on the plane normal to the axis at each point's depth."""
    return depth_mm(camera, points) * float(np.max(1.0 / np.diag(camera.intrinsics)[:2]))


def pixel_rays(camera: Camera, pixels) -> np.ndarray:
    """Directions (K, 3) in the body frame of the rays through pixels (K, 2), scaled to unit depth (d·a = 1)."""
    uv = np.atleast_2d(np.asarray(pixels, float))
    rays_c = np.linalg.solve(camera.intrinsics, np.column_stack([uv, np.ones(len(uv))]).T).T
    return rays_c @ camera.rotation  # R_cbᵀ d_c, row by row


def observed_pixels(cameras: Sequence[Camera], points, rng: Optional[np.random.Generator],
                    noise_px: Sequence[float]) -> np.ndarray:
    """(n, K, 2) pixels where n cameras see points (K, 3): projected, + N(0, σᵢ²) px per axis, rounded.

    Draws exactly 2nK normals from rng, camera by camera, even at σ = 0 (so
    a seeded stream does not depend on the noise); one camera draws what
    `Camera.measure` draws. rng None: the exact projection, unrounded, no
    draws (the nominal sensor).
    """
    P = np.atleast_2d(np.asarray(points, float))
    uv = np.stack([cam.project(P) for cam in cameras])
    if rng is None:
        return uv
    z = rng.standard_normal(uv.shape)
    return np.round(uv + np.asarray(noise_px, float)[:, None, None] * z)


def plane_points(camera: Camera, pixels, reference_mm) -> np.ndarray:
    """(K, 3) the points where the pixels' rays meet the plane through reference_mm ((3,) or (K, 3)) normal to
    the optical axis."""
    d = pixel_rays(camera, pixels)
    c = camera.centre
    lam = (np.asarray(reference_mm, float) - c) @ optical_axis(camera)  # d·a = 1: the reference's depth
    if np.any(np.asarray(lam) <= 0.0):
        raise ValueError("the reference point lies behind the camera")
    return c + np.atleast_1d(lam)[:, None] * d


def triangulate(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(K, 3) the least-squares points closest to n rays each: origins (n, 3) or (n, K, 3), directions (n, K, 3).

    Solves Σᵢ (I − dᵢdᵢᵀ) p = Σᵢ (I − dᵢdᵢᵀ) oᵢ per point, dᵢ normalised.
    Raises ValueError when the rays of a point are (nearly) parallel: two
    rays closer than MIN_TRIANGULATION_DEG / 2.
    """
    d = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    o = np.broadcast_to(np.asarray(origins, float)[:, None, :] if np.ndim(origins) == 2 else origins, d.shape)
    P = np.eye(3) - d[..., :, None] * d[..., None, :]  # (n, K, 3, 3)
    A = P.sum(axis=0)
    b = np.einsum("nkij,nkj->ki", P, o)
    # A's smallest eigenvalue is Σ sin² of the rays' angles to its eigenvector; two rays θ apart give
    # 2 sin²(θ/2). A safety net: below half the config check's angle (camera_problems refuses at the angle).
    if np.any(np.linalg.eigvalsh(A)[:, 0] < 2.0 * np.sin(np.radians(MIN_TRIANGULATION_DEG / 4.0)) ** 2):
        raise ValueError("the cameras' rays to a point are nearly parallel: its depth along them is not observed")
    return np.linalg.solve(A, b[..., None])[..., 0]


def sight_lines(cameras: Sequence[Camera], points) -> np.ndarray:
    """(n, K, 3) unit directions from each camera's centre to each point (K, 3)."""
    P = np.atleast_2d(np.asarray(points, float))
    d = P[None] - np.stack([cam.centre for cam in cameras])[:, None, :]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def reading_covariance(cameras: Sequence[Camera], point, noise_px: Sequence[float]) -> np.ndarray:
    """(3, 3) covariance (mm²) of a reading of point (3,): pixel noise σᵢ and the rounding's 1/12 px².

    Each camera's ray moves across its sight line by sᵢ = √(σᵢ² + 1/12) ×
    its footprint at the point (isotropically, for square pixels). One
    camera: sᵢ² (I − a aᵀ), its seen plane. Several: the least-squares
    solution's A⁻¹ (Σ sᵢ² Pᵢ) A⁻¹, A = Σ Pᵢ, Pᵢ = I − uᵢuᵢᵀ along the sight
    lines uᵢ. First order in the noise; the rounding's error is not random
    for a point that does not move, so this is its spread over points.
    """
    p = np.asarray(point, float)[None]
    s2 = np.array([(float(sig) ** 2 + 1.0 / 12.0) * footprint_mm(cam, p)[0] ** 2
                   for cam, sig in zip(cameras, noise_px)])
    if len(cameras) == 1:
        return s2[0] * seen_projector(optical_axis(cameras[0]))
    u = sight_lines(cameras, p)[:, 0]
    P = np.eye(3) - u[:, :, None] * u[:, None, :]
    Ainv = np.linalg.inv(P.sum(axis=0))
    return Ainv @ np.einsum("n,nij->ij", s2, P) @ Ainv


def _axis_of(cfg: BodyCameraConfig) -> Optional[np.ndarray]:
    if cfg.look_at_mm is None:
        return np.array([0.0, 0.0, -1.0])
    a = np.asarray(cfg.look_at_mm, float) - np.asarray(cfg.position_mm, float)
    n = float(np.linalg.norm(a))
    return a / n if n > 1e-6 else None


def camera_problems(cameras: Sequence[BodyCameraConfig], points_mm=None) -> list[str]:
    """What makes a 3-D scene's cameras unusable, one sentence each (empty: none).

    cameras: the `cameras:` list (or `[camera]`); points_mm (K, 3): the
    lesions' positions (rest and desired) when known. A camera whose
    look_at_mm is its position has no view; a point behind a camera is not
    seen. Two or more cameras triangulate: at every point, or without
    points along the optical axes, some two sight lines must differ by
    MIN_TRIANGULATION_DEG (as lines: opposite views are parallel too).
    Without points the check cannot see two cameras at one position looking
    different ways, whose rays to any point coincide: give the points.
    """
    problems = []
    axes = [_axis_of(c) for c in cameras]
    for i, a in enumerate(axes):
        if a is None:
            problems.append(f"cameras[{i}]: look_at_mm is the camera's own position, so it has no view direction")
    if problems:
        return problems
    cams = [posed_camera(c) for c in cameras]
    P = None if points_mm is None else np.atleast_2d(np.asarray(points_mm, float)).reshape(-1, 3)
    if P is not None:
        for i, cam in enumerate(cams):
            behind = np.flatnonzero(depth_mm(cam, P) <= 0.0)
            if len(behind):
                problems.append(f"cameras[{i}] does not see the point {P[behind[0]].tolist()} mm: it lies behind "
                                "the camera")
    if len(cams) < 2:
        return problems
    lines = np.stack(axes)[:, None, :] if P is None else sight_lines(cams, P)  # (n, K, 3)
    cos = np.abs(np.einsum("ikd,jkd->kij", lines, lines))
    widest = np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), 0.0, 1.0)))  # (K,) the widest pair per point
    bad = np.flatnonzero(widest < MIN_TRIANGULATION_DEG)
    if len(bad):
        k = bad[np.argmin(widest[bad])]
        where = "their optical axes" if P is None else f"their sight lines to {P[k].tolist()} mm"
        w = float(widest[k])
        gain = (f"{1.0 / np.sin(np.radians(w)):.3g}× the noise across them" if w > 1e-3 else "no bound")
        problems.append(f"the cameras cannot triangulate: {where} are at most {w:.2g}° apart, under "
                        f"{MIN_TRIANGULATION_DEG:g}° (the depth along them would have {gain}): "
                        "place the cameras further apart")
    return problems
