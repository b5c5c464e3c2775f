"""The run's sensor, picked from the config: the camera, or the ultrasound with `imaging` (docs/model.md §8, §17).

`sensor_model` is what the trials (`TrialContext`) and the nominal stages
use; control, insertion and the trials read whichever it gives through the
`sensing.sensor` interface. Without `imaging` it is exactly the camera
model the trials always had.

With `imaging`, what is fixed per probe, assumed sound speed and depth —
the probe's parameters and the PSF measured on SIMUS (`imaging_data`, plain
arrays) — is made once per run in the main process, kept in the cache
beside the runs (`run_cache`) and handed to the trial workers with their
tasks, so no worker simulates it; the fast model's tables made from it are
kept once per process (`imaging_tables_for`), so a worker builds them
once whatever the budget row it runs.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config import Config, ImagingConfig
from scissor_cli.experiments import run_cache
from scissor_cli.experiments.profiles import ErrorModel
from scissor_cli.sensing.camera import Camera, CameraModel
from scissor_cli.sensing.sensor import SensorModel

_TABLES: dict[tuple, object] = {}  # this process's imaging tables by (probe, assumed speed, depth, PSF)


def sensor_model(cfg: Config, scene, errors: ErrorModel, imaging: Optional[dict] = None,
                 full_frames: bool = False) -> SensorModel:
    """The run's SensorModel: the camera (no `imaging`), else the ultrasound (`UltrasoundModel`).

    scene: the `scene.Scene` (targets' rest positions, obstacles); imaging:
    the run's `imaging_data` (None: made here, simulating the PSF);
    full_frames: the ultrasound images the whole grid (the nominal record).
    """
    if cfg.imaging is None:
        return CameraModel(Camera.from_config(cfg.camera), errors.pixel_noise_px, errors.localisation_error_mm,
                           ideal=errors.exact_measurement)
    from scissor_cli.sensing.ultrasound import (  # noqa: PLC0415
        ImagingErrors,
        ProbePose,
        UltrasoundModel,
        obstacle_echogenicity,
    )

    im = cfg.imaging
    tables = imaging_tables_for(im, imaging)
    names = [o.name for o in scene.obstacles]
    obstacles = tuple(zip([np.asarray(o.outline, float) for o in scene.obstacles],
                          obstacle_echogenicity(names, im.obstacle_echogenicity_db)))
    return UltrasoundModel(
        tables=tables, pose=ProbePose(im.position_mm, im.axis), sound_speed_m_per_s=im.sound_speed_m_per_s,
        lesion_radius_mm=im.lesion_radius_mm, lesion_echogenicity_db=im.lesion_echogenicity_db,
        targets_rest_mm=np.array([t.rest for t in scene.targets], float).reshape(-1, 2), obstacles=obstacles,
        snr_db=im.snr_db, image_model=im.model, full_frames=full_frames,
        errors=ImagingErrors(errors.sound_speed_sd_m_per_s, errors.probe_position_sd_mm, errors.probe_angle_sd_deg,
                             errors.electronic_noise_scale),
    )


def _psf_key(im: ImagingConfig) -> dict:
    return {"what": "ultrasound-psf", "probe": im.probe, "assumed_sound_speed_m_per_s": im.assumed_sound_speed_m_per_s,
            "depth_mm": im.depth_mm}


def imaging_data(im: ImagingConfig, cache_dir: Optional[Path] = None) -> dict:
    """The probe's parameters and its PSF as plain data ({'probe': dict, 'psf': arrays}), from the cache or made.

    Made: the probe from pymust and the PSF measured on SIMUS
    (`sensing.ultrasound.build_psf`), then written whole to the cache.
    """
    from scissor_cli.sensing.ultrasound import build_psf, probe_params  # noqa: PLC0415

    path = None if cache_dir is None else Path(cache_dir) / f"ultrasound-psf-{run_cache.key(_psf_key(im))}.npz"
    if path is not None and path.exists():
        try:
            with np.load(path, allow_pickle=False) as f:
                arrays = {k: f[k] for k in f.files}
            probe = {k[len("probe/"):]: arrays.pop(k).item() for k in list(arrays) if k.startswith("probe/")}
            probe["name"] = str(probe["name"].decode() if isinstance(probe["name"], bytes) else probe["name"])
            return {"probe": probe, "psf": arrays}
        except (OSError, KeyError, ValueError):
            pass  # unreadable: made again
    t0 = time.perf_counter()
    probe = probe_params(im.probe)
    psf = build_psf(probe, im.assumed_sound_speed_m_per_s, im.depth_mm)
    progress.info(f"imaging: {probe.name}'s PSF measured on SIMUS to {im.depth_mm:g} mm "
                  f"in {time.perf_counter() - t0:.1f} s")
    data = {"probe": asdict(probe), "psf": psf.to_arrays()}
    if path is not None:
        flat = {**data["psf"], **{f"probe/{k}": np.asarray(v) for k, v in data["probe"].items()}}
        flat["probe/name"] = np.bytes_(probe.name.encode("ascii"))
        run_cache.write_whole(path, lambda partial: np.savez(partial, **flat))
    return data


def imaging_tables_for(im: ImagingConfig, data: Optional[dict] = None):
    """This process's `ImagingTables` of the section's probe, speed and depth (made once; data: `imaging_data`)."""
    from scissor_cli.sensing.ultrasound import ProbeParams, PsfModel, imaging_tables  # noqa: PLC0415

    key = (im.probe, im.assumed_sound_speed_m_per_s, im.depth_mm)
    if key not in _TABLES:
        data = imaging_data(im) if data is None else data
        probe = ProbeParams(**data["probe"])
        _TABLES.clear()  # one probe at a time per process
        _TABLES[key] = imaging_tables(probe, PsfModel.from_arrays(data["psf"]), im.depth_mm)
    return _TABLES[key]
