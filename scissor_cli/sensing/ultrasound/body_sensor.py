"""Ultrasound on a 3-D body as the loop's sensor: the run's `BodyUltrasoundModel` and each trial's
`BodyUltrasoundSensor` (docs/ultrasound.md, "On the body (3-D)").

The layer's sensor (`imaging_sensor`) with a 3-D pose: the probe's image
plane cuts the body (`body_pose`), the scatterers fill a band about it and
ride the tetrahedra (`body_scatter`), each frame is the fast model's on
their (lateral, true depth, elevation) in the probe's true pose, weighted
by the elevation beam as in the slab. The first frame localises the lesion
near its planned position (`speckle_tracking.localise_lesion`), later
frames track it (`SpeckleTracker`), and the image position (lateral,
apparent depth) goes back to the body through the pose the scanner
believes, at the plan's elevation: one plane does not see where the lesion
lies across it. `measure` returns (3,) mm with NaN in the body coordinates
within `camera3d.SEEN_AXIS_DEG` of the elevation (a probe whose plane is
upright and along x reports y as NaN), as one camera reports its depth;
`seen` is the projector I - e eᵀ onto the plane, which the loop drives
(`control.allocation.stroke_step`).

Streams per trial, `np.random.default_rng(draws.key + (tag,))`, the layer's
tags: `POSE_STREAM` (7 normals, whatever the σ: the tissue's sound speed,
the believed pose's offset along lateral, axis and elevation, σ_p each, and
its rotation vector in the probe's frame, σ_θ per component),
`SPECKLE_STREAM` (the scatterers, drawn at the first frame),
`NOISE_STREAM` (the frames' electronic noise). A trial images a window of
the grid around the lesion's plan and goal, widened by the localisation's
and the tracking's reach and the errors' 3σ, as the layer's; the
scatterers are drawn in the probe-frame box that can move into it.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from scissor_cli.sensing.camera3d import seen_projector, unseen_axes
from scissor_cli.sensing.sensor import TrialDraws, TrueState
from scissor_cli.sensing.ultrasound.body_pose import BodyProbePose, imaging_pose
from scissor_cli.sensing.ultrasound.body_scatter import (
    CarriedBodyScatterers,
    Echo,
    band_density,
    carry_in_body,
    draw_body_scatterers,
    sphere_echo,
    tube_echo,
)
from scissor_cli.sensing.ultrasound.fast import FrameKernels, fast_frame
from scissor_cli.sensing.ultrasound.imaging_sensor import (
    DEFAULT_TRAVEL_MM,
    LOCALISE_SEARCH_MM,
    NOISE_STREAM,
    NOMINAL_TRIAL,
    SOUND_SPEED_RANGE,
    SPECKLE_STREAM,
    TRACKING_JITTER_MM,
    WINDOW_SLACK_MM,
    ImagingErrors,
    ImagingTables,
    Recording,
    drawn_sound_speed,
    obstacle_echogenicity,
    pose_draws,
    tracked,
)
from scissor_cli.sensing.ultrasound.psf import SCATTERERS_PER_CELL
from scissor_cli.sensing.ultrasound.scatter_scene import (
    ELEVATION_EDGE_NEPER,
    ELEVATION_MARGIN_MM,
    REGION_SLACK_MM,
    elevation_band_mm,
)
from scissor_cli.sensing.ultrasound.speckle_tracking import SpeckleTracker, TrackingParams, localise_lesion
from scissor_cli.sensing.ultrasound.transducer import ImageGrid


@dataclass(frozen=True, eq=False)
class BodyUltrasoundModel:
    """The run's ultrasound on a body (a `sensing.sensor.SensorModel`).

    pose: where the probe sits (on the skin; what the scanner believes up to
    the drawn calibration error); targets_rest_mm (K, 3) and
    lesion_radii_mm (K,): the lesions' echo spheres, in the order of the
    draws' target index; obstacles: their echo regions (`body_scatter.Echo`);
    full_frames: image the whole grid (else a window, module docstring).
    """

    tables: ImagingTables
    pose: BodyProbePose
    sound_speed_m_per_s: float
    targets_rest_mm: np.ndarray
    lesion_radii_mm: np.ndarray
    lesion_echogenicity_db: float = -10.0
    obstacles: tuple = ()
    snr_db: Optional[float] = 30.0
    errors: ImagingErrors = ImagingErrors()
    full_frames: bool = False
    tracking: TrackingParams = TrackingParams()

    @property
    def exact(self) -> bool:
        return False

    @property
    def assumed_sound_speed_m_per_s(self) -> float:
        return self.tables.psf.sound_speed_m_per_s

    @property
    def echoes(self) -> tuple[Echo, ...]:
        """The obstacles, then every lesion's sphere (later regions over earlier ones)."""
        rest = np.asarray(self.targets_rest_mm, float).reshape(-1, 3)
        lesions = tuple(sphere_echo(c, r, self.lesion_echogenicity_db) for c, r in zip(rest, self.lesion_radii_mm))
        return tuple(self.obstacles) + lesions

    def for_trial(self, draws: TrialDraws) -> "BodyUltrasoundSensor":
        """Trial k's sensor: its sound speed and calibration error, speckle and noise streams (module docstring)."""
        key, z = pose_draws(draws, 7)
        e = self.errors
        c_t = drawn_sound_speed(self.sound_speed_m_per_s, e.sound_speed_sd_m_per_s, z[0])
        believed = self.pose.moved(e.probe_position_sd_mm * z[1:4], math.radians(e.probe_angle_sd_deg) * z[4:7])
        return BodyUltrasoundSensor(self, key[1], c_t, believed, key + (SPECKLE_STREAM,),
                                    np.random.default_rng(key + (NOISE_STREAM,)), draws.goal_mm)

    def nominal(self, goal_mm=None, target_index: int = 0, seed: int = 0,
                record: bool = False) -> "BodyUltrasoundSensor":
        """The sensor of lesion target_index with no error drawn: the configured pose and sound speeds, the
        speckle of (seed, target, NOMINAL_TRIAL); record: keep every frame (`BodyUltrasoundSensor.recorded`)."""
        key = (int(seed), int(target_index), NOMINAL_TRIAL)
        return BodyUltrasoundSensor(self, target_index, self.sound_speed_m_per_s, self.pose, key + (SPECKLE_STREAM,),
                                    np.random.default_rng(key + (NOISE_STREAM,)), goal_mm, record)

    def error_reach_mm(self, depth_mm: float) -> float:
        """What the drawn errors can do, 3σ, to where the scanner sees a lesion at depth_mm (mm)."""
        e, c_a = self.errors, self.assumed_sound_speed_m_per_s
        speeds = np.clip(self.sound_speed_m_per_s + np.array([-3.0, 0.0, 3.0]) * e.sound_speed_sd_m_per_s,
                         *SOUND_SPEED_RANGE)
        time_of_flight = depth_mm * float(np.max(np.abs(c_a / speeds - 1.0)))
        return time_of_flight + 3.0 * (math.sqrt(3.0) * e.probe_position_sd_mm
                                       + math.sqrt(2.0) * depth_mm * math.radians(e.probe_angle_sd_deg))


def window_kernels(tables: ImagingTables, centres_mm: np.ndarray, half_mm: np.ndarray) -> FrameKernels:
    """The tables of the grid's window covering probe-frame points centres_mm (K, 2) (lateral, depth) mm ± half_mm
    (2,), at least 2 × 2 pixels, clipped to the image."""
    g = tables.grid
    c = np.atleast_2d(np.asarray(centres_mm, float))
    lo, hi = c.min(axis=0) - half_mm, c.max(axis=0) + half_mm
    c0, c1 = (int(v) for v in np.searchsorted(g.lateral_mm, [lo[0], hi[0]]))
    r0, r1 = (int(v) for v in np.searchsorted(g.depth_mm, [lo[1], hi[1]]))
    W, H = len(g.lateral_mm), len(g.depth_mm)
    c0, r0 = min(max(0, c0 - 1), W - 2), min(max(0, r0 - 1), H - 2)
    c1, r1 = max(min(W, c1 + 1), c0 + 2), max(min(H, r1 + 1), r0 + 2)
    return tables.kernels.window(slice(r0, r1), slice(c0, c1))


class BodyUltrasoundSensor:
    """One trial's ultrasound on the body (a `sensing.sensor.Sensor`): scatterers, poses, sound speed, tracker.

    Positions inside are probe-frame mm (lateral, apparent depth); `measure`
    returns body mm through the pose the scanner believes (module docstring).
    """

    def __init__(self, model: BodyUltrasoundModel, target_index: int, tissue_sound_speed_m_per_s: float,
                 believed_pose: BodyProbePose, speckle_key: tuple, rng: np.random.Generator, goal_mm=None,
                 record: bool = False):
        self.model, self.target_index = model, int(target_index)
        self.tissue_sound_speed_m_per_s = float(tissue_sound_speed_m_per_s)
        self.true_pose, self.believed_pose = model.pose, believed_pose
        self.rng, self.speckle_key = rng, tuple(speckle_key)
        self.rest_mm = np.asarray(model.targets_rest_mm, float).reshape(-1, 3)[self.target_index]
        self.radius_mm = float(np.asarray(model.lesion_radii_mm, float)[self.target_index])
        planned = believed_pose.to_probe(self.rest_mm)
        self.planned_mm, self.reference_elevation_mm = planned[:2].copy(), float(planned[2])
        reach = model.error_reach_mm(float(self.planned_mm[1]))
        self.search_mm = LOCALISE_SEARCH_MM + reach
        goal = None if goal_mm is None else believed_pose.to_probe(np.asarray(goal_mm, float).reshape(3))[:2]
        self.travel_mm = DEFAULT_TRAVEL_MM if goal is None else float(np.hypot(*(goal - self.planned_mm)))
        if model.full_frames:
            self.kernels = model.tables.kernels
        else:
            tp = model.tracking
            track = np.array(tp.block_half_mm) + np.array(tp.search_mm) + reach
            half = np.maximum(self.search_mm + 1.5 * self.radius_mm, track) + WINDOW_SLACK_MM
            ends = [self.planned_mm] + ([goal] if goal is not None else
                                        [self.planned_mm - DEFAULT_TRAVEL_MM, self.planned_mm + DEFAULT_TRAVEL_MM])
            self.kernels = window_kernels(model.tables, np.array(ends), half)
        self._draw: Optional[object] = None
        self._carried: list[tuple[object, CarriedBodyScatterers]] = []
        self._tracker: Optional[SpeckleTracker] = None
        self._last_mm: Optional[np.ndarray] = None
        self._counts = {"frames": 0, "lost": 0}  # shared with reseeded copies
        self.correlation = float("nan")
        #: every frame with the reported lesion (3,) and the true one (3,) body mm, when asked (the nominal run's
        #: B-mode figure and /imaging); its nodes are not kept
        self.recorded: Optional[Recording] = Recording() if record else None
        self._env: Optional[np.ndarray] = None  # the last frame, kept while recording

    @property
    def noise_mm(self) -> float:
        """σ (mm) of one reading's random part: the tracking's frame-to-frame jitter (TRACKING_JITTER_MM)."""
        return TRACKING_JITTER_MM

    @property
    def seen(self) -> np.ndarray:
        """(3, 3) the projector onto the image plane, I − e eᵀ (e the believed elevation)."""
        return seen_projector(self.believed_pose.elevation)

    @property
    def unseen(self) -> np.ndarray:
        """(3,) bool: the body coordinates `measure` reports as NaN (within 1° of the elevation)."""
        return unseen_axes(self.believed_pose.elevation)

    @property
    def frames(self) -> int:
        return self._counts["frames"]

    @property
    def lost_frames(self) -> int:
        """Frames (of this sensor and its reseeded copies) on which the lesion could not be found or tracked."""
        return self._counts["lost"]

    @property
    def grid(self) -> ImageGrid:
        return self.kernels.grid

    def region_mm(self) -> np.ndarray:
        """The probe-frame box [[lateral0, depth0], [lateral1, depth1]] mm (true depth, from the face on) the
        scatterers are drawn in: the window at the tissue's speed, grown by the travel and REGION_SLACK_MM."""
        g = self.grid
        depth = np.array([g.depth_mm[0], g.depth_mm[-1]]) * self.tissue_sound_speed_m_per_s \
            / self.model.assumed_sound_speed_m_per_s
        grow = self.travel_mm + REGION_SLACK_MM
        return np.array([[g.lateral_mm[0] - grow, max(0.0, depth[0] - grow)],
                         [g.lateral_mm[-1] + grow, depth[1] + grow]])

    def band_mm(self) -> float:
        """Half-width (mm) of the elevation band (`scatter_scene.elevation_band_mm`, no slab to bound it)."""
        return elevation_band_mm(self.kernels)

    def band_profile(self) -> tuple[np.ndarray, np.ndarray]:
        """(true depths (R,), half-widths (R,)) mm: the band at each row of the window, where the row's two-way
        elevation amplitude falls to -20 dB, plus the slab's margin (`scatter_scene`); near the face the beam
        is wide, about its focus narrow, so a band of one width would hold several times the scatterers."""
        k = self.kernels
        depth = k.grid.depth_mm * self.tissue_sound_speed_m_per_s / self.model.assumed_sound_speed_m_per_s
        half = np.sqrt(ELEVATION_EDGE_NEPER / np.maximum(k.elevation_coef_re, 1e-9)) + ELEVATION_MARGIN_MM
        return depth, np.minimum(half, self.band_mm())

    def _scatterers(self, mesh):
        if self._draw is None:  # on the first mesh seen: the scatterers are then its material points
            psf = self.model.tables.psf
            band = self.band_mm()
            depth = float(np.clip(self.planned_mm[1], psf.depths_mm[0], psf.depths_mm[-1]))
            density = band_density(psf.density_per_mm2(SCATTERERS_PER_CELL), band, float(psf.elevation_fwhm_mm(depth)))
            self._draw = draw_body_scatterers(np.random.default_rng(self.speckle_key), mesh, self.true_pose,
                                              self.region_mm(), density, self.band_profile(), self.model.echoes)
        return self._draw

    def _carriage(self, mesh) -> CarriedBodyScatterers:
        for known, carried in self._carried:
            if known is mesh:
                return carried
        carried = carry_in_body(mesh, self._scatterers(mesh))
        self._carried = self._carried[-1:] + [(mesh, carried)]  # the last two meshes seen
        return carried

    def frame(self, state: TrueState) -> np.ndarray:
        """The envelope (H, W) float32 of the true state on this sensor's grid (no localisation, no tracking)."""
        if state.nodes_mm is None or state.mesh is None:
            raise ValueError("the ultrasound sensor needs the true body's nodes and mesh (TrueState.nodes_mm, .mesh)")
        carried = self._carriage(state.mesh)
        lat, dep, ele = carried.to_probe(state.nodes_mm, self.true_pose)
        m = self.model
        scale = m.errors.electronic_noise_scale
        snr = None if m.snr_db is None or scale <= 0 else float(m.snr_db) - 20.0 * math.log10(scale)
        return fast_frame(self.kernels, lat, dep, ele, carried.amplitude, self.tissue_sound_speed_m_per_s,
                          snr_db=snr, rng=self.rng, noise_reference_power=m.tables.reference_power)

    def image_position(self, state: TrueState) -> np.ndarray:
        """One frame; the lesion's (lateral, apparent depth) mm in it, localised (first frame) or tracked."""
        env = self.frame(state)
        self._env = env if self.recorded is not None else None
        self._counts["frames"] += 1
        if self._last_mm is None:
            self._last_mm = self._first_position(env)
        else:
            self._tracker, self._last_mm, lost, correlation = tracked(self._tracker, env, self._last_mm)
            self._counts["lost"] += lost
            self.correlation = self.correlation if correlation is None else correlation
        return self._last_mm.copy()

    def point(self, image_mm: np.ndarray) -> np.ndarray:
        """(3,) body mm of an image position (lateral, apparent depth) through the believed pose, at the plan's
        elevation."""
        q = np.array([image_mm[0], image_mm[1], self.reference_elevation_mm])
        return self.believed_pose.to_body(q)

    def measure(self, state: TrueState) -> np.ndarray:
        """(3,) body mm, NaN in the coordinates along the elevation (module docstring)."""
        t0 = time.perf_counter()
        reported = self.point(self.image_position(state))
        if self.recorded is not None:
            r = self.recorded
            r.frames.append(self._env)
            r.tracked.append(reported)
            r.true.append(np.array(state.target_mm, float).reshape(3))
            r.frame_time_s.append(time.perf_counter() - t0)
        return np.where(self.unseen, np.nan, reported)

    def _first_position(self, env: np.ndarray) -> np.ndarray:
        g = self.grid
        try:
            p = localise_lesion(env, g, self.planned_mm, self.radius_mm, self.search_mm,
                                self.model.lesion_echogenicity_db)
        except ValueError:  # the search region leaves the image: start from the plan
            self._counts["lost"] += 1
            p = np.clip(self.planned_mm, [g.lateral_mm[0], g.depth_mm[0]], [g.lateral_mm[-1], g.depth_mm[-1]])
        try:
            self._tracker = SpeckleTracker(env, g, p, self.model.tracking)
        except ValueError:  # the block would leave the window: the lesion is held where it was found
            self._tracker = None
        return np.asarray(p, float)

    def reseeded(self, rng: np.random.Generator) -> "BodyUltrasoundSensor":
        """The same sensor (scatterers, poses, sound speed, the tracker as it stands), its frame noise from rng."""
        other = copy.copy(self)
        other.rng = rng
        other._tracker = copy.copy(self._tracker)
        other.recorded = None
        return other


def body_ultrasound_model(im, mesh, targets, obstacles, tables: ImagingTables, needle_direction=None,
                          errors: Optional[ImagingErrors] = None, full_frames: bool = False) -> BodyUltrasoundModel:
    """The run's model from a 3-D scene's `imaging` section (`config.body_imaging.BodyImagingConfig`).

    mesh: the body's (its skin holds the probe); targets, obstacles: the
    config's lesions and obstacles (rest positions and radii); tables: the
    probe's (`imaging_tables` at the section's probe, speed and depth);
    errors: the σ of a trial's imaging errors (None: none).
    """
    names = [o.name for o in obstacles]
    db = obstacle_echogenicity(names, im.obstacle_echogenicity_db)
    echoes = tuple(sphere_echo(o.sphere.center_mm, o.sphere.radius_mm, d) if o.sphere is not None
                   else tube_echo(o.tube.points_mm, o.tube.radius_mm, d) for o, d in zip(obstacles, db))
    return BodyUltrasoundModel(
        tables=tables, pose=imaging_pose(mesh, im, needle_direction), sound_speed_m_per_s=im.sound_speed_m_per_s,
        targets_rest_mm=np.array([t.position_mm for t in targets], float).reshape(-1, 3),
        lesion_radii_mm=np.array([im.lesion_radius_for(t.radius_mm) for t in targets], float),
        lesion_echogenicity_db=im.lesion_echogenicity_db, obstacles=echoes, snr_db=im.snr_db,
        errors=ImagingErrors() if errors is None else errors,
        full_frames=full_frames)


__all__ = ["BodyUltrasoundModel", "BodyUltrasoundSensor", "body_ultrasound_model", "window_kernels"]
