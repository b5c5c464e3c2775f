"""What a trial is handed and what it hands back, as plain data: `TargetTask`, `TrialOutcome` (docs/model.md §10).

Shared by the trials of a layer (`experiments.trials`) and of a body
(`experiments.body_trials`), by the executors and by the run's sink.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np


@dataclass(frozen=True)
class TargetTask:
    """What a worker needs to know of one target's plan, as plain data (mm)."""

    index: int
    name: str
    rest: np.ndarray  # (2,)
    desired: np.ndarray  # (2,)
    plan_strokes: np.ndarray  # (C,) where the planner found the desired position
    side: str  # corridor entry side, "" when there is no corridor
    direction: np.ndarray  # (2,) corridor direction, NaN when none
    entry: Optional[np.ndarray] = None  # (2,) the plan's needle entry (insertion)
    depth_mm: float = 0.0  # the plan's depth (insertion)
    #: the controller's model when it is not the layer (`layer3d.controller_model.ModelData`, docs/model.md §15)
    controller_model: Optional[object] = None
    #: slab truth: the nominal slab's (strokes (C,), x (N3, 3)) mm at the plan, solved once per run
    #: (`experiments.slab_starts`); None: the worker solves it
    slab_start: Optional[tuple] = None
    #: with `imaging`: the probe and its PSF as plain data (`sensor_models.imaging_data`), made once per run;
    #: None: the worker makes them
    imaging: Optional[dict] = None
    #: a body with the needle and `loop`: the controller's model of the target under the needle
    #: (`insertion.NeedleModel`, made once per run); None: none
    needle_model: Optional[object] = None


@dataclass
class TrialOutcome:
    """One finished trial. A crashed one (`ok` False) carries the finite fill values of
    docs/contract.md#resultsh5: zeros, `iterations` −1 and no history."""

    target_index: int
    trial: int
    ok: bool
    message: str
    final_error: np.ndarray  # (2,) true − desired, mm
    iterations: int
    time_s: float  # wall clock of the loop
    corridor_clear: bool
    clearance_mm: float
    stop_reason: str
    correctable_mm: float
    uncorrectable_mm: float
    history_columns: list[str]
    history: np.ndarray  # (K, n)
    miss_mm: float = 0.0  # across the plan's needle axis after the loop (docs/model.md §6)
    along_mm: float = 0.0  # desired − true along the axis, for the depth
    #: with insertion: the final miss and depth error (mm) per strategy (S,), in the config's order
    insertion_miss_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    insertion_depth_error_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: wall clock of the whole trial: the loop and, with insertion, every strategy's insertion (s)
    trial_time_s: float = 0.0
    #: with `imaging`: frames on which the tracking lost the lesion (the loop's and the insertions'), and all frames
    lost_frames: int = 0
    frames: int = 0


def law_attrs(controller) -> dict:
    """/trials attrs naming the control law (docs/contract.md): `controller_law`, and the class or the MPC's
    horizon and weight."""
    attrs = {"controller_law": controller.law}
    if controller.law == "python":
        attrs["controller_class"] = controller.class_path
    elif controller.law == "mpc":
        attrs |= {"mpc_horizon": controller.mpc.horizon, "mpc_action_weight": controller.mpc.action_weight}
    return attrs


@dataclass(frozen=True)
class NominalInsertion:
    """A work item's second element (`trials.WorkItem`) for a lesion's nominal insertions (a body's), run by a
    trials' worker beside the trials: the truth's equilibrium at the plan's strokes (N, 3) mm when the run has
    solved it already, else None (the worker solves it)."""

    start: Optional[np.ndarray] = None


@dataclass
class NominalOutcome:
    """A lesion's nominal manipulation or nominal insertions run by a trials' worker beside the trials (a body's,
    docs/model.md §19, "Trials"): its closed loop and open-loop baseline (`control.LoopResult`), or (`what`
    "insertion") every strategy's `insertion.InsertionResult`; or `error`, why it failed (the run fails with it,
    as when the run's own process solves it)."""

    target_index: int
    closed: Optional[object] = None
    opened: Optional[object] = None
    error: str = ""
    what: str = "manipulation"
    insertion: Optional[list] = None
