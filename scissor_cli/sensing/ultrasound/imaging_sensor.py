"""Ultrasound as the loop's sensor: the run's `UltrasoundModel` and each trial's `UltrasoundSensor`
(docs/ultrasound.md §6).

The closed loop, the insertion and the trials read it through the
`sensing.sensor` interface, as they read the camera: a `TrueState` in,
the measured target (2,) mm in the layer's plane out.

**Per run** (`ImagingTables`, `UltrasoundModel`): the probe, its PSF
(measured once on SIMUS, or handed in from a cache), the image grid, the
fast model's tables and the noise's reference power; the configured pose,
sound speeds, lesion and echogenicities; the σ of the trial's imaging
errors.

**Per trial** (`UltrasoundModel.for_trial`), drawn from streams of the
sensor's own, `np.random.default_rng(draws.key + (tag,))`, so that a
scene without imaging draws exactly what it drew before:

* `POSE_STREAM` (4 normals, whatever the σ): the tissue's sound speed,
  c_t = c + σ_c z0 (clipped to `SOUND_SPEED_RANGE`), and the probe's
  calibration error. The probe sits where the config puts it (the true
  pose); the scanner maps its image to the layer through the pose it
  believes, that pose moved by σ_p (z1, z2) along its lateral and axis and
  turned by σ_θ z3;
* `SPECKLE_STREAM`: the scatterers (fully developed speckle,
  `scatterers.draw_scatterers`) in the rest frame, with the lesion (a
  disc, in the slab a sphere, of the lesion's radius around the target's
  rest position) and the obstacles' echogenicity; drawn at the first frame,
  once the sensor knows whether the truth is the layer or the slab;
* `NOISE_STREAM`: every frame's electronic noise (its normals are drawn
  whatever the noise level; `reseeded` replaces this stream).

**Per frame** (`UltrasoundSensor.measure`): the scatterers follow the true
state's nodes (`scatterer_motion`), are imaged in the probe's true pose at
the tissue's sound speed (so the scanner's apparent depth is the true one
x c_assumed / c_tissue), the first frame localises the lesion near its
planned position as the scanner sees it (rest position through the
believed pose), later frames track it (`SpeckleTracker`); the image
position goes back to the layer through the believed pose. A frame on
which tracking fails (the block or its search leaves the image, or its
peak correlation is below `LOST_CORRELATION`) holds the last position,
leaves the tracker as it was, and is counted (`lost_frames`).

**Windows.** A trial's frames cover only a window of the image: the
lesion's planned position and its goal (`TrialDraws.goal_mm`), with the
localisation's and the tracking's reach around them and the errors the
profile can draw; the scatterers are drawn in the rest region that can
move into it. `full_frames=True` images the whole grid (the nominal
record). A window's pixels equal the whole frame's there (`FrameKernels.window`);
its noise has the whole image's level (`ImagingTables.reference_power`).
Costs: benchmark bench_ultrasound_loop.

`model: simus` forms the frames with the SIMUS reference instead, with
`SIMUS_PER_CELL` scatterers per resolution cell and the noise relative to
each frame's own power, and only on the pixels the next step reads (the
first frame's localisation search, then the tracking's block and search;
0 on the rest of the window): a reference for checks, seconds to minutes
per frame (benchmark bench_ultrasound has SIMUS's cost per scatterer).
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from scissor_cli.sensing.sensor import TrialDraws, TrueState
from scissor_cli.sensing.ultrasound.fast import FrameKernels, complex_normals, fast_frame, frame_kernels
from scissor_cli.sensing.ultrasound.psf import SCATTERERS_PER_CELL, PsfModel
from scissor_cli.sensing.ultrasound.scatter_scene import ScatterScene
from scissor_cli.sensing.ultrasound.scatterers import draw_scatterers
from scissor_cli.sensing.ultrasound.speckle_tracking import SpeckleTracker, TrackingParams, localise_lesion
from scissor_cli.sensing.ultrasound.transducer import ImageGrid, ProbeParams, ProbePose, image_grid

#: tags of a trial's own streams, np.random.default_rng(draws.key + (tag,)) (module docstring)
SPECKLE_STREAM = 21
POSE_STREAM = 22
NOISE_STREAM = 23
#: the trial index in the nominal manipulation's key (seed, target, NOMINAL_TRIAL): no trial has it
NOMINAL_TRIAL = 1_000_000
#: a drawn tissue sound speed is clipped to the config's range (m/s)
SOUND_SPEED_RANGE = (1000.0, 2000.0)
#: the first frame's search radius (mm) around the planned position with no error drawn (localise_lesion's);
#: the errors the profile can draw (3 σ) are added to it
LOCALISE_SEARCH_MM = 3.0
#: what a window adds beyond the localisation's and the tracking's reach (mm): the loop's overshoot
WINDOW_SLACK_MM = 2.0
#: the target's travel assumed when the trial's goal is not known (mm)
DEFAULT_TRAVEL_MM = 10.0
#: scatterers per resolution cell of the SIMUS reference frames (as its validation: two linear models on the
#: same scatterers need no fully developed speckle; SIMUS's cost grows with them)
SIMUS_PER_CELL = 5.0
#: a frame whose tracking peak NCC (after any re-anchoring) falls below this found no match: the lesion is lost
#: there (decorrelated beyond recognition, or gone from the window); its last position is held
LOST_CORRELATION = 0.3
#: σ (mm) of one reading's random part: the tracked position's frame-to-frame jitter over a manipulation
#: (benchmark bench_ultrasound_loop)
TRACKING_JITTER_MM = 0.01


@dataclass(frozen=True)
class ImagingTables:
    """What is fixed per probe, assumed sound speed and depth: the probe, its PSF, the fast model's tables.

    reference_power: the mean compensated power |IQ|^2 of a whole frame of
    background speckle (no lesion, no noise) at the PSF's density: the
    electronic noise's level is 10^(-snr/10) times it, on every frame and
    window alike.
    """

    probe: ProbeParams
    psf: PsfModel
    kernels: FrameKernels
    reference_power: float

    @property
    def grid(self) -> ImageGrid:
        return self.kernels.grid


def imaging_tables(probe: ProbeParams, psf: PsfModel, depth_mm: float) -> ImagingTables:
    """The tables of a probe and its PSF for an image depth_mm deep (the grid at the PSF's assumed speed)."""
    grid = image_grid(probe, depth_mm, psf.sound_speed_m_per_s)
    kernels = frame_kernels(psf, grid)
    # the reference speckle: a fixed draw (the level must not depend on a trial) over the image and a margin
    region = np.array([[grid.lateral_mm[0] - 1.5, -1.0], [grid.lateral_mm[-1] + 1.5, grid.depth_mm[-1] + 1.0]])
    sc = draw_scatterers(np.random.default_rng(0), region, psf.density_per_mm2())
    env = fast_frame(kernels, sc.positions_mm[:, 0], sc.positions_mm[:, 1], sc.elevation_mm, sc.amplitude,
                     psf.sound_speed_m_per_s)
    return ImagingTables(probe, psf, kernels, float(np.mean(env.astype(np.float64) ** 2)))


@dataclass(frozen=True)
class ImagingErrors:
    """σ of a trial's imaging errors (experiments/profiles.py has the values and their sources)."""

    sound_speed_sd_m_per_s: float = 0.0
    probe_position_sd_mm: float = 0.0
    probe_angle_sd_deg: float = 0.0
    #: the electronic noise's amplitude relative to the configured SNR's (0: none)
    electronic_noise_scale: float = 1.0


@dataclass(frozen=True)
class UltrasoundModel:
    """The run's ultrasound sensor (a `sensing.sensor.SensorModel`).

    pose: where the probe sits (the config's; what the scanner believes up
    to the drawn calibration error); sound_speed_m_per_s: the tissue's
    (nominal), the scanner's is the tables' PSF's; targets_rest_mm (K, 2):
    the targets' rest positions, in the order of the draws' target index;
    obstacles: (outline (Q, 2) mm, echogenicity dB) of each; snr_db: the
    configured electronic noise (None: none); image_model "fast" or
    "simus"; full_frames: image the whole grid (else a window, module
    docstring); tracking: the speckle tracker's settings.
    """

    tables: ImagingTables
    pose: ProbePose
    sound_speed_m_per_s: float
    lesion_radius_mm: float
    lesion_echogenicity_db: float
    targets_rest_mm: np.ndarray
    obstacles: tuple = ()
    snr_db: Optional[float] = 30.0
    image_model: str = "fast"
    errors: ImagingErrors = ImagingErrors()
    full_frames: bool = False
    tracking: TrackingParams = TrackingParams()

    def __post_init__(self) -> None:
        if self.image_model not in ("fast", "simus"):
            raise ValueError(f"image model must be 'fast' or 'simus', got {self.image_model!r}")

    @property
    def exact(self) -> bool:
        return False

    @property
    def assumed_sound_speed_m_per_s(self) -> float:
        return self.tables.psf.sound_speed_m_per_s

    def for_trial(self, draws: TrialDraws) -> "UltrasoundSensor":
        """Trial k's sensor: its sound speed and calibration error, speckle and noise streams (module docstring)."""
        key, z = pose_draws(draws, 4)
        e = self.errors
        c_t = drawn_sound_speed(self.sound_speed_m_per_s, e.sound_speed_sd_m_per_s, z[0])
        offset = e.probe_position_sd_mm * (z[1] * self.pose.lateral + z[2] * self.pose.axis)
        turn = math.radians(e.probe_angle_sd_deg) * z[3]
        ca, sa = math.cos(turn), math.sin(turn)
        a = self.pose.axis
        believed = ProbePose(self.pose.position_mm + offset, np.array([ca * a[0] - sa * a[1], sa * a[0] + ca * a[1]]))
        return UltrasoundSensor(self, key[1], c_t, believed, key + (SPECKLE_STREAM,),
                                np.random.default_rng(key + (NOISE_STREAM,)), draws.goal_mm)

    def nominal(self, seed: int, target_index: int, goal_mm=None, record: bool = False) -> "UltrasoundSensor":
        """The sensor with no error drawn: the configured pose and sound speeds, the speckle of (seed, target,
        NOMINAL_TRIAL); record: keep every frame (`UltrasoundSensor.recorded`)."""
        key = (int(seed), int(target_index), NOMINAL_TRIAL)
        return UltrasoundSensor(self, target_index, self.sound_speed_m_per_s, self.pose, key + (SPECKLE_STREAM,),
                                np.random.default_rng(key + (NOISE_STREAM,)), goal_mm, record=record)

    # what the errors the profile draws can do, 3 σ, to where the scanner sees the lesion (mm)
    def _error_reach_mm(self, depth_mm: float) -> float:
        e, c_a = self.errors, self.assumed_sound_speed_m_per_s
        speeds = np.clip(self.sound_speed_m_per_s + np.array([-3.0, 0.0, 3.0]) * e.sound_speed_sd_m_per_s,
                         *SOUND_SPEED_RANGE)
        time_of_flight = depth_mm * float(np.max(np.abs(c_a / speeds - 1.0)))
        calibration = 3.0 * (math.sqrt(2.0) * e.probe_position_sd_mm + depth_mm * math.radians(e.probe_angle_sd_deg))
        return time_of_flight + calibration


@dataclass
class _Counts:
    """Frames of one trial's sensor and its reseeded copies (shared between them)."""

    frames: int = 0
    lost: int = 0


@dataclass
class Recording:
    """What a recording sensor keeps per frame: envelope (H, W) float32, tracked (2,) and true (2,) mm in the
    layer, the true nodes (N, d) mm, the frame's wall time (s)."""

    frames: list = field(default_factory=list)
    tracked: list = field(default_factory=list)
    true: list = field(default_factory=list)
    nodes: list = field(default_factory=list)
    frame_time_s: list = field(default_factory=list)


class UltrasoundSensor:
    """One trial's ultrasound (a `sensing.sensor.Sensor`): its scatterers, poses, sound speed and tracker.

    Positions inside are probe-frame mm (lateral, apparent depth); `measure`
    returns layer mm through the pose the scanner believes.
    """

    def __init__(self, model: UltrasoundModel, target_index: int, tissue_sound_speed_m_per_s: float,
                 believed_pose: ProbePose, speckle_key: tuple, rng: np.random.Generator,
                 goal_mm: Optional[np.ndarray] = None, record: bool = False):
        self.model = model
        self.target_index = int(target_index)
        self.tissue_sound_speed_m_per_s = float(tissue_sound_speed_m_per_s)
        self.true_pose, self.believed_pose = model.pose, believed_pose
        self.rng = rng
        rest = np.asarray(model.targets_rest_mm, float).reshape(-1, 2)[self.target_index]
        self.planned_mm = believed_pose.to_probe(rest)  # where the scanner expects the lesion in its image
        reach = model._error_reach_mm(float(self.planned_mm[1]))
        self.search_mm = LOCALISE_SEARCH_MM + reach
        goal = None if goal_mm is None else believed_pose.to_probe(np.asarray(goal_mm, float)[:2])
        self.travel_mm = DEFAULT_TRAVEL_MM if goal is None else float(np.hypot(*(goal - self.planned_mm)))
        self.kernels = model.tables.kernels if model.full_frames else self._window(goal, reach)
        per_cell = SIMUS_PER_CELL if model.image_model == "simus" else SCATTERERS_PER_CELL
        self._scene = ScatterScene(model, rest, speckle_key, self.kernels, self.true_pose,
                                   self.tissue_sound_speed_m_per_s, self.travel_mm, per_cell)
        self._tracker: Optional[SpeckleTracker] = None
        self._last_mm: Optional[np.ndarray] = None
        self._counts = _Counts()
        self.recorded: Optional[Recording] = Recording() if record else None
        self.correlation = float("nan")  # the last tracking step's peak NCC

    @property
    def noise_mm(self) -> float:
        """σ (mm) of one reading's random part: the tracking's frame-to-frame jitter (TRACKING_JITTER_MM)."""
        return TRACKING_JITTER_MM

    @property
    def lost_frames(self) -> int:
        """Frames (of this trial's sensor and its reseeded copies) on which the lesion could not be tracked."""
        return self._counts.lost

    @property
    def frames(self) -> int:
        """Frames formed by this trial's sensor and its reseeded copies."""
        return self._counts.frames

    @property
    def grid(self) -> ImageGrid:
        """The grid of this sensor's frames (the window, or the whole image)."""
        return self.kernels.grid

    def _window(self, goal: Optional[np.ndarray], reach: float) -> FrameKernels:
        m = self.model
        tp = m.tracking
        r = m.lesion_radius_mm
        lo = self.planned_mm.copy()
        hi = self.planned_mm.copy()
        if goal is not None:
            lo, hi = np.minimum(lo, goal), np.maximum(hi, goal)
        else:
            lo, hi = lo - DEFAULT_TRAVEL_MM, hi + DEFAULT_TRAVEL_MM
        track = np.array(tp.block_half_mm) + np.array(tp.search_mm) + reach
        half = np.maximum(self.search_mm + 1.5 * r, track) + WINDOW_SLACK_MM
        lo, hi = lo - half, hi + half
        g = m.tables.grid
        c0, c1 = np.searchsorted(g.lateral_mm, [lo[0], hi[0]])
        r0, r1 = np.searchsorted(g.depth_mm, [lo[1], hi[1]])
        c0, r0 = max(0, int(c0) - 1), max(0, int(r0) - 1)
        c1, r1 = min(len(g.lateral_mm), max(int(c1) + 1, c0 + 2)), min(len(g.depth_mm), max(int(r1) + 1, r0 + 2))
        if c1 - c0 < 2 or r1 - r0 < 2:  # the plan lies off the image: a window at its nearest edge
            c0, c1 = max(0, min(c0, len(g.lateral_mm) - 2)), max(2, min(c1, len(g.lateral_mm)))
            r0, r1 = max(0, min(r0, len(g.depth_mm) - 2)), max(2, min(r1, len(g.depth_mm)))
        return m.tables.kernels.window(slice(r0, r1), slice(c0, c1))

    def frame(self, state: TrueState) -> np.ndarray:
        """The envelope (H, W) float32 of the true state on this sensor's grid (no localisation, no tracking)."""
        lat, dep, ele, amp = self._scene.in_probe_frame(state)
        m = self.model
        c_t = self.tissue_sound_speed_m_per_s
        if m.image_model == "fast":
            return fast_frame(self.kernels, lat, dep, ele, amp, c_t, snr_db=self._snr_db(), rng=self.rng,
                              noise_reference_power=m.tables.reference_power)
        return self._simus_frame(lat, dep, ele, amp)

    def _snr_db(self) -> Optional[float]:
        m, scale = self.model, self.model.errors.electronic_noise_scale
        if m.snr_db is None or scale <= 0:
            return None
        return float(m.snr_db) - 20.0 * math.log10(scale)

    def _simus_frame(self, lat, dep, ele, amp) -> np.ndarray:
        """The SIMUS reference on the pixels the next step reads (`_simus_pixels`), 0 on the rest of the window."""
        from scissor_cli.sensing.ultrasound.simus_ref import simus_frame  # noqa: PLC0415  (pymust: only here)

        m, g = self.model, self.kernels.grid
        c_t, c_a = self.tissue_sound_speed_m_per_s, m.assumed_sound_speed_m_per_s
        noise = complex_normals(self.rng, g.shape)  # drawn whatever the level
        rows, cols = self._simus_pixels()
        sub = ImageGrid(g.lateral_mm[cols].copy(), g.depth_mm[rows].copy())
        reach = np.array([m.tables.psf.window_lateral_mm[-1], m.tables.psf.window_axial_mm[-1]]) + 0.5
        apparent = dep * c_a / c_t
        near = ((lat >= sub.lateral_mm[0] - reach[0]) & (lat <= sub.lateral_mm[-1] + reach[0])
                & (apparent >= sub.depth_mm[0] - reach[1]) & (apparent <= sub.depth_mm[-1] + reach[1]))
        out = np.zeros(g.shape, np.float32)
        if not near.any():
            return out
        iq = simus_frame(m.tables.probe, sub, lat[near], dep[near], ele[near], amp[near], c_t, c_a, envelope=False)
        snr = self._snr_db()
        std = 0.0 if snr is None else math.sqrt(float(np.mean(np.abs(iq) ** 2)) * 10.0 ** (-snr / 10.0) / 2.0)
        out[rows, cols] = np.abs(iq + std * (noise[0][rows, cols] + 1j * noise[1][rows, cols]))
        return out

    def _simus_pixels(self) -> tuple[slice, slice]:
        """The window's rows and columns a SIMUS frame must fill: the first frame's localisation search (plus
        the lesion's ring), later the tracking's block and search around the last position (they hold the block
        of any frame that becomes the anchor)."""
        m, g = self.model, self.kernels.grid
        if self._last_mm is None:
            centre, half = self.planned_mm, np.full(2, self.search_mm + 1.5 * m.lesion_radius_mm)
        else:
            centre, half = self._last_mm, np.array(m.tracking.block_half_mm) + np.array(m.tracking.search_mm)
        half = half + 2.0 * np.array([g.dx_mm, g.dz_mm])
        c0, c1 = np.searchsorted(g.lateral_mm, [centre[0] - half[0], centre[0] + half[0]])
        r0, r1 = np.searchsorted(g.depth_mm, [centre[1] - half[1], centre[1] + half[1]])
        c0, r0 = min(int(c0), len(g.lateral_mm) - 2), min(int(r0), len(g.depth_mm) - 2)
        return slice(r0, max(int(r1), r0 + 2)), slice(c0, max(int(c1), c0 + 2))

    def measure(self, state: TrueState) -> np.ndarray:
        """The measured target (2,) mm in the layer: one frame, the lesion localised (first) or tracked."""
        t0 = time.perf_counter()
        env = self.frame(state)
        elapsed = time.perf_counter() - t0
        self._counts.frames += 1
        if self._last_mm is None:
            self._last_mm = self._first_position(env)
        else:
            self._tracker, self._last_mm, lost, correlation = tracked(self._tracker, env, self._last_mm)
            self._counts.lost += lost
            self.correlation = self.correlation if correlation is None else correlation
        y = self.believed_pose.to_layer(self._last_mm)
        if self.recorded is not None:
            r = self.recorded
            r.frames.append(env)
            r.tracked.append(y.copy())
            r.true.append(np.array(state.target_mm, float)[:2])
            r.nodes.append(None if state.nodes_mm is None else np.array(state.nodes_mm, float))
            r.frame_time_s.append(elapsed)
        return y

    def _first_position(self, env: np.ndarray) -> np.ndarray:
        g = self.kernels.grid
        m = self.model
        try:
            p = localise_lesion(env, g, self.planned_mm, m.lesion_radius_mm, self.search_mm,
                                m.lesion_echogenicity_db)
        except ValueError:  # the search region leaves the image: start from the plan
            self._counts.lost += 1
            p = np.clip(self.planned_mm, [g.lateral_mm[0], g.depth_mm[0]], [g.lateral_mm[-1], g.depth_mm[-1]])
        try:
            self._tracker = SpeckleTracker(env, g, p, m.tracking)
        except ValueError:  # pragma: no cover - p is inside the grid by construction
            self._tracker = None
        return np.asarray(p, float)

    def reseeded(self, rng: np.random.Generator) -> "UltrasoundSensor":
        """The same sensor (scatterers, poses, sound speed, the tracker as it stands) with its frame noise from rng.

        The copy tracks on from here on its own (its tracker is a copy);
        its lost frames count with this one's; it records nothing.
        """
        other = copy.copy(self)
        other.rng = rng
        other._tracker = copy.copy(self._tracker)
        other.recorded = None
        return other


def pose_draws(draws: TrialDraws, n: int) -> tuple[tuple[int, ...], np.ndarray]:
    """A trial's key (seed, target, trial) and its n normals on POSE_STREAM: the sound speed's, then the probe
    pose's calibration error (drawn whatever their σ, so one σ does not shift the others)."""
    key = tuple(int(k) for k in draws.key)
    if len(key) < 2:
        raise ValueError(f"an ultrasound trial needs its key (seed, target, trial), got {draws.key!r}")
    return key, np.random.default_rng(key + (POSE_STREAM,)).standard_normal(n)


def drawn_sound_speed(nominal_m_per_s: float, sd_m_per_s: float, z: float) -> float:
    """The trial's tissue sound speed (m/s) from its normal z, within SOUND_SPEED_RANGE."""
    return float(np.clip(nominal_m_per_s + sd_m_per_s * z, *SOUND_SPEED_RANGE))


def tracked(tracker, env: np.ndarray, last_mm: np.ndarray) -> tuple[object, np.ndarray, bool, Optional[float]]:
    """A later frame's lesion: (the tracker, its (lateral, depth) mm, lost, the match's correlation or None).

    A `SpeckleTracker` follows it; when the block or its search leaves the
    image, or nothing matches (correlation below LOST_CORRELATION), the last
    position is held, the tracker kept as it was, and the frame is lost.
    Without a tracker every frame holds the last position, lost.
    """
    if tracker is None:
        return None, last_mm, True, None
    before = copy.copy(tracker)
    try:
        st = tracker.update(env)
    except ValueError:
        return before, last_mm, True, None
    if st.correlation < LOST_CORRELATION:
        return before, last_mm, True, st.correlation
    return tracker, st.position_mm, False, st.correlation


def obstacle_echogenicity(names: Sequence[str], overrides: Optional[dict] = None) -> list[float]:
    """The echogenicity (dB) of obstacles by name: an override, else the kind its name says, else 0.

    Kinds (`scatterers.ECHOGENICITY_DB`): a name containing 'vessel',
    'artery' or 'vein' is a vessel's lumen, 'nerve' a nerve, 'cyst' a
    cyst, 'fat' fat, 'gland' fibroglandular tissue; any other obstacle
    echoes like the background (0 dB: stiffer, not brighter).
    """
    from scissor_cli.sensing.ultrasound.scatterers import ECHOGENICITY_DB  # noqa: PLC0415

    kinds = (("vessel", "vessel_lumen"), ("arter", "vessel_lumen"), ("vein", "vessel_lumen"), ("nerve", "nerve"),
             ("cyst", "cyst"), ("fat", "fat"), ("gland", "fibroglandular"))
    out = []
    for name in names:
        if overrides and name in overrides:
            out.append(float(overrides[name]))
            continue
        low = name.lower()
        out.append(next((ECHOGENICITY_DB[k] for key, k in kinds if key in low), ECHOGENICITY_DB["background"]))
    return out


__all__ = ["ImagingErrors", "ImagingTables", "Recording", "UltrasoundModel", "UltrasoundSensor", "imaging_tables",
           "obstacle_echogenicity"]
