"""A body's nominal manipulation seen by the ultrasound on its skin: the frames as an `ImagingRecord`
(docs/contract.md `/imaging`, docs/ultrasound.md "On the body (3-D)").

The closed loop's sensor records every frame (`BodyUltrasoundSensor.recorded`); its windows are placed
on the whole image grid (`imaging_stage.whole_frames`), so every lesion's frames share the run's one grid.
The record is in the body's frame: the lesion the scanner reports (at the plan's elevation, which the
plane does not see) and the true one (K, 3), the needle line and the desired point (3,), the probe's
believed pose with its lateral axis in the attrs. `output.imaging` writes /imaging and the B-mode
figure (before | after, the points projected into the image plane).
"""

from __future__ import annotations

import numpy as np

from scissor_cli.experiments.imaging_stage import frame_strokes, whole_frames
from scissor_cli.experiments.sink import ImagingRecord


def body_imaging_record(imaging, target: str, plan, closed, sensor) -> ImagingRecord:
    """The record of a body's closed loop (its sensor made with record=True): imaging the body's `imaging`
    section, plan the lesion's body plan (entry, direction, desired), closed its `TargetResult`."""
    rec = sensor.recorded
    if rec is None or not rec.frames:
        raise ValueError(f"imaging {target}: the sensor recorded no frame")
    pose = sensor.believed_pose
    true = np.array(rec.true, float).reshape(-1, 3)
    attrs = {
        "probe": imaging.probe, "lateral_axis": pose.lateral.copy(),
        "assumed_sound_speed_m_per_s": imaging.assumed_sound_speed_m_per_s,
        "sound_speed_m_per_s": imaging.sound_speed_m_per_s, "model": imaging.model, "depth_mm": imaging.depth_mm,
        "lesion_radius_mm": float(sensor.radius_mm), "lesion_echogenicity_db": imaging.lesion_echogenicity_db,
        "snr_db": "none" if imaging.snr_db is None else float(imaging.snr_db),
        "nominal_draws": "the ideal profile's: the configured pose and sound speeds, no electronic noise",
        "frame_time_s": float(np.median(rec.frame_time_s)),
    }
    whole = sensor.model.tables.grid
    return ImagingRecord(
        target=target, grid_lateral_mm=whole.lateral_mm.copy(), grid_depth_mm=whole.depth_mm.copy(),
        frames=whole_frames(rec.frames, sensor.grid, whole), tracked=np.array(rec.tracked, float).reshape(-1, 3),
        true=true, strokes=frame_strokes(true, closed), needle_entry=np.asarray(plan.entry, float),
        needle_direction=np.asarray(plan.direction, float), desired=np.asarray(plan.desired, float),
        probe_position_mm=pose.origin_mm.copy(), probe_axis=pose.axis.copy(), attrs=attrs)
