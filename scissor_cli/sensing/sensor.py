"""The sensor interface: the true state in, the measured target out (docs/model.md §8, §17).

The closed loop (§6), the `depth` and `loop` insertion strategies (§12)
and the trials (§10) see the target only through a `Sensor`. A sensor is
made per trial by its run-wide `SensorModel` from that trial's draws, so
its bias and its frame noise are the trial's own; it may keep state from
frame to frame (an ultrasound tracker does). A new sensor plugs in as a
module of this package with a `SensorModel` and a config section; nothing
in `control/`, `insertion/` or `experiments/` names a particular sensor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Protocol

import numpy as np


@dataclass(frozen=True)
class TrueState:
    """What a sensor may look at: the true tissue as it stands.

    target_mm (d,): the true target (d = 2 in the layer, 3 in the slab,
    the layer's plane at the slab's layer height, 3 in a body: the lesion's
    centre in the body frame); nodes_mm (N, d): the true
    tissue's node positions, and mesh the mesh they belong to (None when
    the caller has only the target: a sensor that needs the tissue says so).
    """

    target_mm: np.ndarray
    nodes_mm: Optional[np.ndarray] = None
    mesh: Any = None


class Sensor(Protocol):
    """One trial's sensor."""

    @property
    def noise_mm(self) -> float:
        """σ (mm) of one reading's random part at the layer (0: repeated readings agree)."""

    def measure(self, state: TrueState) -> np.ndarray:
        """The measured target (2,) mm in the layer's plane; in a body (3,), NaN in the coordinates not seen."""

    def reseeded(self, rng: np.random.Generator) -> "Sensor":
        """The same sensor (bias, calibration, what it tracks) drawing its frame noise from rng."""


@dataclass(frozen=True)
class TrialDraws:
    """What a trial hands its sensor: the draws the sensor turns into its own errors.

    localisation_z (2,): standard normals the trial drew for the
    localisation bias (the sensor scales them by its σ); rng: the trial's
    stream for per-frame noise; key: (seed, target, trial), the root of any
    further draw a sensor makes on a stream of its own
    (`np.random.default_rng(key + (tag,))`); goal_mm (2,): where the trial
    is to move the target, when known (a sensor may aim at it: an
    ultrasound images a window around the target's way, a single 3-D
    camera reads on the plane through it; (3,) in a body; None: unknown).
    A 3-D camera sensor takes its localisation normals beyond these two
    from the key's stream (`sensing.camera3d_sensor.BodyCameraModel.biases`).
    """

    localisation_z: np.ndarray
    rng: np.random.Generator
    key: tuple[int, ...] = ()
    goal_mm: Optional[np.ndarray] = None


class SensorModel(Protocol):
    """A run's sensor: what is fixed for the run (optics, probe), and how a trial's sensor is drawn."""

    @property
    def exact(self) -> bool:
        """True when every trial's sensor reads the true target exactly (no bias, no noise)."""

    def for_trial(self, draws: TrialDraws) -> Sensor:
        """Trial k's sensor from its draws."""


@dataclass(frozen=True)
class ExactSensor:
    """The ideal sensor: the true target's in-plane part, no noise, no draws."""

    noise_mm: float = 0.0

    def measure(self, state: TrueState) -> np.ndarray:
        return np.array(state.target_mm, float)[:2]

    def reseeded(self, rng: np.random.Generator) -> "ExactSensor":
        return self


EXACT = ExactSensor()
