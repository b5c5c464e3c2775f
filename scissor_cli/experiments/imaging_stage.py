"""The nominal manipulation seen by ultrasound, every frame kept; the fast model's check against SIMUS
(docs/model.md §17).

With `imaging`, the nominal manipulation of each target (`simulate.
_manipulation_stage`) reads the target through an ultrasound sensor with
the ideal profile's draws: the probe where the config puts it and believed
there, the configured sound speeds, no electronic noise, the speckle of
the key (seed, target index, `imaging_sensor.NOMINAL_TRIAL`). The closed
loop's sensor images the whole grid and keeps every frame, with the
tracked and true positions and the tissue's nodes; the open-loop baseline
reads a window, unkept. What is kept goes to the sink as an
`ImagingRecord` (`RunSink.imaging`, when the sink has it). With `model:
simus` the closed loop too reads a window (a whole SIMUS frame would cost
its scatterers' count times SIMUS's cost per scatterer: benchmark
bench_ultrasound): its frames are stored on the whole grid, 0 outside.

The record's attrs are the run's, the same for every target and across a
resume: the settings, the validation, and `frame_time_s` (the median wall
time of a whole fast frame of background speckle, or of one SIMUS frame of
the tracking's block and search; `frame_time_s()`), measured with the
validation and cached with it.

The fast model's validation against SIMUS (`sensing.ultrasound.
validate_fast`: envelope correlation and the tracked displacements on one
patch) is made once per probe, sound speeds and depth and kept in the
cache beside the runs, as the PSF is (`sensor_models.imaging_data`).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config import Config, ImagingConfig, TrialsConfig
from scissor_cli.experiments import run_cache
from scissor_cli.experiments.profiles import error_model
from scissor_cli.experiments.sensor_models import imaging_data, imaging_tables_for, sensor_model
from scissor_cli.experiments.sink import ImagingRecord

#: the validation patch: its centre (lateral 0, this fraction of the image's depth) and the known shift (mm)
VALIDATION_DEPTH_FRACTION = 0.6
VALIDATION_SHIFT_MM = (0.25, 0.15)
VALIDATION_SEED = 0
#: frames timed for `frame_time_s` (fast model; SIMUS: one)
FRAME_TIMINGS = 5


def fast_validation(im: ImagingConfig, tables, cache_dir: Optional[Path] = None) -> dict:
    """The fast model against SIMUS on one patch (module docstring) and the frame time, as plain numbers, from the
    cache or made."""
    from scissor_cli.sensing.ultrasound import validate_fast  # noqa: PLC0415

    parts = {"what": "ultrasound-validation", "probe": im.probe, "depth_mm": im.depth_mm,
             "assumed_sound_speed_m_per_s": im.assumed_sound_speed_m_per_s,
             "sound_speed_m_per_s": im.sound_speed_m_per_s, "model": im.model}
    path = None if cache_dir is None else Path(cache_dir) / f"ultrasound-validation-{run_cache.key(parts)}.json"
    if path is not None and path.exists():
        try:
            stored = json.loads(path.read_text())
            if "frame_time_s" in stored and "envelope_correlation" in stored:
                return stored
        except (OSError, ValueError):
            pass  # unreadable: made again
    t0 = time.perf_counter()
    v = validate_fast(tables.probe, tables.psf, tables.kernels, np.random.default_rng(VALIDATION_SEED),
                      np.array([0.0, VALIDATION_DEPTH_FRACTION * im.depth_mm]), np.array(VALIDATION_SHIFT_MM),
                      tissue_sound_speed_m_per_s=im.sound_speed_m_per_s)
    out = {"envelope_correlation": v.envelope_correlation, "tracked_fast_mm": v.tracked_fast_mm.tolist(),
           "tracked_simus_mm": v.tracked_simus_mm.tolist(), "true_mm": v.true_mm.tolist(),
           "tracking_difference_mm": v.tracking_difference_mm, "scatterer_count": v.scatterer_count,
           "time_s": time.perf_counter() - t0}
    progress.info(f"imaging: the fast model against SIMUS: envelope correlation {out['envelope_correlation']:.3f}, "
                  f"tracked displacements {1e3 * out['tracking_difference_mm']:.1f} µm apart "
                  f"({out['time_s']:.1f} s)")
    out = {**out, "frame_time_s": frame_time_s(im, tables)}
    if path is not None:
        run_cache.write_whole(path, lambda partial: partial.write_text(json.dumps(out)))
    return out


def frame_time_s(im: ImagingConfig, tables) -> float:
    """The median wall time (s) of a frame: fast, FRAME_TIMINGS whole frames of background speckle over the image
    at the default density; simus, one frame of the tracking's block and search at its density, at the
    validation patch's centre."""
    from scissor_cli.sensing.ultrasound import ImageGrid, TrackingParams, draw_scatterers, fast_frame  # noqa: PLC0415
    from scissor_cli.sensing.ultrasound.imaging_sensor import SIMUS_PER_CELL  # noqa: PLC0415
    from scissor_cli.sensing.ultrasound.simus_ref import simus_frame  # noqa: PLC0415

    g, psf, c_t = tables.grid, tables.psf, im.sound_speed_m_per_s
    rng = np.random.default_rng(VALIDATION_SEED)
    if im.model == "fast":
        region = np.array([[g.lateral_mm[0] - 1.5, -1.0], [g.lateral_mm[-1] + 1.5, g.depth_mm[-1] + 1.0]])
        sc = draw_scatterers(rng, region, psf.density_per_mm2())
        p = sc.positions_mm
        times = []
        for _ in range(FRAME_TIMINGS):
            t0 = time.perf_counter()
            fast_frame(tables.kernels, p[:, 0], p[:, 1], sc.elevation_mm, sc.amplitude, c_t, snr_db=im.snr_db,
                       rng=rng, noise_reference_power=tables.reference_power)
            times.append(time.perf_counter() - t0)
        return float(np.median(times))
    centre = np.array([0.0, VALIDATION_DEPTH_FRACTION * im.depth_mm])
    half = np.array(TrackingParams().block_half_mm) + np.array(TrackingParams().search_mm)
    cols = np.abs(g.lateral_mm - centre[0]) <= half[0]
    rows = np.abs(g.depth_mm - centre[1]) <= half[1]
    reach = half + np.array([psf.window_lateral_mm[-1], psf.window_axial_mm[-1]]) + 0.5
    sc = draw_scatterers(rng, np.array([centre - reach, centre + reach]), psf.density_per_mm2(SIMUS_PER_CELL))
    t0 = time.perf_counter()
    simus_frame(tables.probe, ImageGrid(g.lateral_mm[cols], g.depth_mm[rows]), sc.positions_mm[:, 0],
                sc.positions_mm[:, 1], sc.elevation_mm, sc.amplitude, c_t, im.assumed_sound_speed_m_per_s)
    return time.perf_counter() - t0


@dataclass
class NominalImaging:
    """The run's ultrasound for the nominal manipulations: the whole-grid model, its windowed twin, the checks."""

    cfg: Config
    model: object  # UltrasoundModel: whole frames (fast), windows (simus)
    validation: dict

    @classmethod
    def prepare(cls, cfg: Config, tissue, data: dict, cache_dir: Optional[Path]) -> "NominalImaging":
        """The model of the ideal profile's draws from the run's `imaging_data`, and the validation."""
        ideal = error_model(TrialsConfig(profile="ideal"))
        model = sensor_model(cfg, tissue.scene, ideal, data, full_frames=cfg.imaging.model == "fast")
        return cls(cfg, model, fast_validation(cfg.imaging, imaging_tables_for(cfg.imaging, data), cache_dir))

    def sensors(self, index: int, desired: np.ndarray):
        """(closed loop's recording sensor, open loop's windowed sensor) of target `index`."""
        seed = int(self.cfg.seed)
        return (self.model.nominal(seed, index, desired, record=True),
                replace(self.model, full_frames=False).nominal(seed, index, desired))

    def hand_over(self, sink, target: str, plan, closed, sensor, tissue) -> list[Path]:
        """The closed loop's frames as an `ImagingRecord` to `sink.imaging` (a sink without it: nothing)."""
        rec = sensor.recorded
        im = self.cfg.imaging
        lost = f", {sensor.lost_frames} lost the lesion (the last position held)" if sensor.lost_frames else ""
        progress.info(f"imaging {target}: {len(rec.frames)} frames of {self.model.image_model} ultrasound, "
                      f"{1e3 * float(np.median(rec.frame_time_s)):.0f} ms each{lost}")
        if not hasattr(sink, "imaging"):
            return []
        true = np.array(rec.true, float).reshape(-1, 2)
        g = self.model.tables.grid
        attrs = {
            "probe": im.probe, "position_mm": list(im.position_mm), "axis": list(im.axis),
            "assumed_sound_speed_m_per_s": im.assumed_sound_speed_m_per_s,
            "sound_speed_m_per_s": im.sound_speed_m_per_s, "model": im.model, "depth_mm": im.depth_mm,
            "lesion_radius_mm": im.lesion_radius_mm, "lesion_echogenicity_db": im.lesion_echogenicity_db,
            "snr_db": "none" if im.snr_db is None else float(im.snr_db),
            "nominal_draws": "the ideal profile's: the configured pose and sound speeds, no electronic noise",
            "frame_time_s": float(self.validation["frame_time_s"]),
            **{f"validation_{k}": v for k, v in self.validation.items() if k != "frame_time_s"},
        }
        record = ImagingRecord(
            target=target, grid_lateral_mm=g.lateral_mm.copy(), grid_depth_mm=g.depth_mm.copy(),
            frames=whole_frames(rec.frames, sensor.grid, g), tracked=np.array(rec.tracked, float).reshape(-1, 2),
            true=true, strokes=frame_strokes(true, closed), needle_entry=np.asarray(plan.entry, float),
            needle_direction=np.asarray(plan.direction, float), desired=np.asarray(plan.desired, float),
            probe_position_mm=sensor.believed_pose.position_mm.copy(), probe_axis=sensor.believed_pose.axis.copy(),
            attrs=attrs,
        )
        return list(sink.imaging(record, tissue, list(rec.nodes)) or [])


def whole_frames(frames: list, grid, whole) -> np.ndarray:
    """Frames (K, H, W) float32 on the whole grid from frames on a window of it (0 outside the window)."""
    if grid.shape == whole.shape:
        return np.stack(frames).astype(np.float32)
    r0 = int(np.argmin(np.abs(whole.depth_mm - grid.depth_mm[0])))
    c0 = int(np.argmin(np.abs(whole.lateral_mm - grid.lateral_mm[0])))
    out = np.zeros((len(frames), *whole.shape), np.float32)
    h, w = grid.shape
    for k, f in enumerate(frames):
        out[k, r0:r0 + h, c0:c0 + w] = f
    return out


def frame_strokes(true: np.ndarray, loop) -> np.ndarray:
    """The strokes (K, C) mm of each frame: the history row whose true target the frame saw.

    The loop measures once per history row, and stop_frames − 1 more times
    at the same strokes before a stop (`control.loop`): frames follow the
    rows in order, and a frame with the row's true position belongs to it.
    """
    rows_true, rows_strokes = np.asarray(loop.hist_true, float), np.asarray(loop.hist_strokes, float)
    out = np.zeros((len(true), rows_strokes.shape[1] if rows_strokes.ndim == 2 else 0))
    r = 0
    for k, p in enumerate(true):
        while r + 1 < len(rows_true) and not np.array_equal(rows_true[r], p):
            r += 1
        if len(rows_strokes):
            out[k] = rows_strokes[r]
    return out


def prepare_imaging(cfg: Config, tissue, cache_dir: Optional[Path]) -> tuple[Optional[dict], Optional[NominalImaging]]:
    """(the run's `imaging_data` for the trials' tasks, the nominal stage's `NominalImaging`), (None, None) without
    imaging."""
    if cfg.imaging is None:
        return None, None
    data = imaging_data(cfg.imaging, cache_dir)
    return data, NominalImaging.prepare(cfg, tissue, data, cache_dir)
