"""What the stages of `scissor simulate` hand over, and to whom: the run sink.

The pipeline (`experiments.simulate`) computes; a sink keeps. The pipeline
calls the sink once per product of a stage, in the order of the stages, and
never reads a file or draws a figure itself. `output` implements the sink
with results.h5 and the figures (docs/contract.md#resultsh5,
docs/contract.md#figures); `cli.py` wires the two. Tests may pass any
object with these methods.

A sink's promises:

* **Stored as given.** Every number it is handed is kept exactly (the
  golden test compares results to 1e-9; trials are bit for bit).
* **No non-finite number is kept.** A value that is absent by definition
  (no obstacle to clear, no plan, a trial not run yet) is stored as the
  finite fill value the contract documents, beside the mask that says so.
  Any other NaN or infinity is refused with `NonFiniteError`, naming where
  it was to go; the run then fails (exit 1) keeping what it finished.
* **A stored trial survives any kill.** `trial` returns only once the
  trial is durable: a later SIGKILL, even in the middle of storing the next
  trial, cannot lose it (docs/contract.md#resume).
* **What is finished is known.** After a stage has handed over one product
  whole (a forward case with its figure, a target's insertions, the plans),
  the pipeline marks its key (`product_key`) with `mark_finished`; the mark
  is durable when the call returns. `--resume` asks `finished()` and redoes
  only what is not marked, so a run killed in any stage loses nothing it
  finished.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional, Protocol

import numpy as np

if TYPE_CHECKING:  # the types the stages produce; annotations only
    from scissor_cli.control.corridor_check import Corridor
    from scissor_cli.control.result import LoopResult
    from scissor_cli.experiments.selection import Selection
    from scissor_cli.experiments.study import StudyResult
    from scissor_cli.experiments.trials import TrialOutcome
    from scissor_cli.insertion.steering import NeedleModel
    from scissor_cli.layer3d.check import LayerCheckCase
    from scissor_cli.layer3d.extrude import SlabMesh
    from scissor_cli.layer3d.resolution import SlabChoice
    from scissor_cli.layer3d.slab import SlabProbe
    from scissor_cli.mechanics.tissue import Tissue
    from scissor_cli.planning.needle_plan import NeedlePlan
    from scissor_cli.scene.scene import Target
    from scissor_cli.solvers.common import SolveResult


def product_key(stage: str, name: str = "") -> str:
    """The key under which a stage's product is marked finished: `stage` or `stage/name`.

    Stages: model, jacobian, study, plan (all targets' plans), trials (the
    trial arrays allocated), per forward case or target: forward/<case>,
    layer_check/<case>, manipulation/<target>, insertion/<target>; and per
    error-budget row: budget/<source>.
    """
    return f"{stage}/{name}" if name else stage


class NonFiniteError(RuntimeError):
    """A NaN or infinity was about to be stored; the message names the dataset (and trial) it was for."""


class ResumeError(ValueError):
    """The run directory cannot be resumed."""


@dataclass(frozen=True)
class ForwardCase:
    """One solved forward case (docs/model.md §4) and the inputs of its figure."""

    name: str
    strokes: dict[str, float]  # mm per cup
    result: "SolveResult"  # x (N, d) mm, the solver's report
    rest: np.ndarray  # (N, d) mm
    targets: dict[str, np.ndarray]  # deformed target positions (d,) mm
    #: keyword arguments of the figure: `output.figures.forward_case_figure` (kind "layer") or
    #: `output.body.figures.body_figures` (kind "body")
    figure: dict
    kind: str = "layer"


@dataclass(frozen=True)
class Manipulation:
    """The nominal closed loop of one target beside its open-loop baseline (docs/model.md §6, Fig. 11)."""

    target: str
    closed: "LoopResult"
    opened: "LoopResult"
    tissue: "Tissue"  # the truth the loop ran on (here the model itself)
    target_rest: np.ndarray  # (2,) mm
    corridor: Optional["Corridor"]  # the planned corridor to draw, None without one


@dataclass(frozen=True)
class Insertion:
    """The nominal insertions of one target, one per strategy (docs/model.md §12).

    results: `insertion.InsertionResult` per strategy; manipulation_frames:
    node positions (N, 2) mm from rest to the insertion's start (the cups
    ramping to the plan's strokes), for the animation; animate: draw the GIF.
    tissue is the layer; layer: the layer's nodes as points of the slab
    (`layer3d.slab.layer_probe`) when the insertions ran in the slab
    (docs/model.md §14), None in the layer. needle_model: on a body, the
    `insertion.NeedleModel` `loop` steered with (docs/model.md §20), stored
    beside `loop`'s insertion.
    """

    target: str
    results: list
    tissue: "Tissue"
    target_rest: np.ndarray  # (2,) mm
    desired: np.ndarray  # (2,) mm, the planned position
    manipulation_frames: list
    animate: bool = False
    layer: Optional["SlabProbe"] = None
    needle_model: Optional["NeedleModel"] = None


@dataclass(frozen=True)
class ImagingRecord:
    """The ultrasound frames of one target's nominal manipulation (docs/model.md §17, docs/contract.md `/imaging`).

    grid_lateral_mm (W,), grid_depth_mm (H,): the image grid in the probe's
    frame (depth along `axis`, lateral along axis turned +90°; depth is the
    scanner's apparent depth); frames (K, H, W) float32: the envelope of
    each frame, linear (before log compression); tracked (K, 2) mm: where
    the tracking put the lesion, in the layer's frame; true (K, 2) mm: the
    true target there (in-plane); strokes (K, C) mm: the strokes of each
    frame; needle_entry (2,), needle_direction (2,): the plan's needle line
    in the layer; desired (2,) mm; probe_position_mm (2,), probe_axis (2,):
    the probe's pose in the layer (as the scanner assumes it); attrs: the
    /imaging attributes (probe, sound speeds, model, frame_time_s, the fast
    model's validation against SIMUS, …).
    """

    target: str
    grid_lateral_mm: np.ndarray
    grid_depth_mm: np.ndarray
    frames: np.ndarray
    tracked: np.ndarray
    true: np.ndarray
    strokes: np.ndarray
    needle_entry: np.ndarray
    needle_direction: np.ndarray
    desired: np.ndarray
    probe_position_mm: np.ndarray
    probe_axis: np.ndarray
    attrs: dict


class RunSink(Protocol):
    """Where the stages' products go. A context manager: leaving it ends the run.

    On a normal exit the run is `complete`; on an exception it is `failed`
    with the reason (`interrupted` for Ctrl-C or a termination signal).
    """

    location: Path  # the run directory, for messages
    config_yaml: str  # the resolved config the run stores (what the trial workers rebuild the model from)

    def __enter__(self) -> "RunSink": ...

    def __exit__(self, exc_type, exc, tb) -> None: ...

    def notes(self) -> list[str]:
        """What the sink wants the user told (e.g. what a resume recovered or lost)."""

    def finished(self) -> frozenset[str]:
        """The `product_key`s marked finished (a new run: none)."""

    def mark_finished(self, key: str) -> None:
        """Mark a product stored whole; durable when this returns."""

    def model(self, tissue: "Tissue") -> None:
        """The mesh, material and cups the run computes on."""

    def selection(self, selection: "Selection") -> None:
        """What `solver.accuracy_mm` picked (docs/model.md §9)."""

    def slab_resolution(self, choice: "SlabChoice") -> None:
        """What `layer_check.accuracy_mm` picked (docs/model.md §13)."""

    def target(self, name: str, rest: np.ndarray, desired: np.ndarray, source: str) -> None:
        """A target's definition without a plan (a 3-D scene's lesions): rest and desired (d,) mm."""

    def body_resolution(self, choice) -> None:
        """What `tissue.accuracy_mm` picked for a 3-D scene's mesh (docs/model.md §19)."""

    def forward_case(self, case: ForwardCase) -> Optional[Path] | list[Path]:
        """One forward case and its figure(s); returns the figures' paths."""

    def layer_check_mesh(self, mesh: "SlabMesh") -> None:
        """The slab of the layer check (docs/model.md §13), once before its cases."""

    def layer_check(self, case: "LayerCheckCase", figure: dict) -> Optional[Path]:
        """One forward case's layer check and its figure (`output.layer_check.layer_check_figure` kwargs)."""

    def jacobian(self, target: str, J: np.ndarray, cup_names: list[str]) -> None:
        """J (d, C) mm/mm of one target at rest (docs/model.md §5), d = 2 or 3."""

    def study(self, study: "StudyResult", seconds: float) -> None:
        """The solver study's rows (docs/model.md §9)."""

    def plan(self, target: "Target", plan: "NeedlePlan", desired_source: str) -> None:
        """A target's definition and its needle plan (docs/model.md §7, §11)."""

    # Optional: `manipulation_points(plan, scene) -> Optional[Path]` keeps the manipulation-point plan
    # (docs/model.md §7); a sink without it skips it.

    def manipulation(self, manipulation: Manipulation) -> Optional[Path]:
        """The nominal manipulation of one target and its figure; returns the figure's path."""

    def imaging(self, record: ImagingRecord, tissue: "Tissue", layer_frames: list) -> list[Path]:
        """With `imaging`: /imaging/<target> and its figures (B-mode before/after, the manipulation's animation
        beside the tissue; layer_frames: the tissue's nodes (N, 2) mm at each frame). Returns the figures."""

    def insertion(self, insertion: Insertion) -> list[Path]:
        """One target's insertions under every strategy and their figures; returns the figures' paths."""

    def allocate_trials(self, targets: list[str], count: int, attrs: dict, without_plan: dict[str, str]) -> None:
        """Room for `count` trials per target; `without_plan` maps a target with no plan to the planner's reason."""

    def pending_trials(self) -> dict[str, np.ndarray]:
        """Trial indices per target still to run: not done, or done but crashed."""

    def trial(self, target: str, outcome: "TrialOutcome") -> None:
        """Store one finished trial durably (see the module docstring)."""

    def trial_figures(self, title: str) -> list[Path]:
        """(Re)draw the figures of the finished trials."""

    def budget_row(self, row: str, fields: dict, outcomes: dict[str, list]) -> None:
        """Store one error-budget row whole: per target its trials' outcomes in trial order (docs/model.md §16)."""

    def budget_figures(self, title: str, rows: list[str], profile: str) -> list[Path]:
        """Note the budget's rows and (re)draw its figure from what is stored."""


class SinkFactory(Protocol):
    """Opens the sink of a new run once the config it runs is final (after the selection)."""

    location: Path

    def open(self, config_yaml: str, seed: int) -> RunSink: ...


class ResumableSink(RunSink, Protocol):
    """A run directory opened by `--resume`: the stored run, ready to take the rest of it.

    The pipeline redoes every product `finished()` does not name. When the
    stored file was lost (a run killed in the middle of writing it), nothing
    is marked and `plans()` is None: every stage before the trials runs
    again into this sink, which already holds every trial that had finished
    (from the journal), so none is computed twice.
    """

    def plans(self) -> Optional[dict[str, dict]]:
        """The /plan/<target> attributes of the stored run, or None (see above)."""
