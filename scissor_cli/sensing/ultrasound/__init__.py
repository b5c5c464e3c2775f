"""Ultrasound imaging of the layer: probe, scatterers, image formation and speckle tracking (docs/model.md §17).

Callers outside the package import from here. Per probe and run:
`probe_params`, `image_grid`, `build_psf` (cacheable: `PsfModel.to_arrays`),
`frame_kernels`. Per trial: `draw_scatterers`. Per frame: `fast_frame` (or
`simus_frame`, the reference), then `localise_lesion` on the first frame and
`SpeckleTracker.update` on the next ones. pymust and scikit-image are
imported only by the functions that use them.

As the loop's sensor (`imaging_sensor`): `imaging_tables` per run,
`UltrasoundModel` (a `sensing.sensor.SensorModel`), its `for_trial` and
`nominal` sensors (`UltrasoundSensor`). On a 3-D body (`body_pose`,
`body_scatter`, `body_sensor`): `BodyProbePose` on the skin,
`body_ultrasound_model` → `BodyUltrasoundModel` and its `BodyUltrasoundSensor`.
"""

from scissor_cli.sensing.ultrasound.body_pose import BodyProbePose, imaging_pose, skin_pose
from scissor_cli.sensing.ultrasound.body_sensor import BodyUltrasoundModel, BodyUltrasoundSensor, body_ultrasound_model
from scissor_cli.sensing.ultrasound.fast import FrameKernels, fast_frame, frame_kernels, log_compress
from scissor_cli.sensing.ultrasound.imaging_sensor import (
    ImagingErrors,
    ImagingTables,
    UltrasoundModel,
    UltrasoundSensor,
    imaging_tables,
    obstacle_echogenicity,
)
from scissor_cli.sensing.ultrasound.psf import PsfModel, build_psf, elevation_width_mm
from scissor_cli.sensing.ultrasound.scatterers import ECHOGENICITY_DB, Scatterers, draw_scatterers
from scissor_cli.sensing.ultrasound.simus_ref import simus_frame
from scissor_cli.sensing.ultrasound.speckle_tracking import (
    SpeckleTracker,
    TrackingParams,
    TrackState,
    block_match,
    localise_lesion,
)
from scissor_cli.sensing.ultrasound.transducer import (
    LINEAR_PROBES,
    ImageGrid,
    ProbeParams,
    ProbePose,
    image_grid,
    probe_params,
)
from scissor_cli.sensing.ultrasound.validation import FastValidation, validate_fast

__all__ = [
    "BodyProbePose", "BodyUltrasoundModel", "BodyUltrasoundSensor", "body_ultrasound_model", "imaging_pose",
    "skin_pose",
    "ECHOGENICITY_DB", "FastValidation", "FrameKernels", "ImageGrid", "ImagingErrors", "ImagingTables", "LINEAR_PROBES",
    "ProbeParams", "ProbePose", "PsfModel", "Scatterers", "SpeckleTracker", "TrackState", "TrackingParams",
    "UltrasoundModel", "UltrasoundSensor", "block_match", "build_psf", "draw_scatterers", "elevation_width_mm",
    "fast_frame", "frame_kernels", "image_grid", "imaging_tables", "localise_lesion", "log_compress",
    "obstacle_echogenicity", "probe_params", "simus_frame", "validate_fast",
]
