"""Trials: many closed-loop manipulations per target under drawn error sources (docs/model.md §10).

A trial is a pure function of (resolved config text, target task, trial
index): the worker rebuilds the same mesh and model from the config text,
draws the trial's error sources from a generator seeded by (seed, target,
trial) and runs the loop. So a trial gives the same numbers in this
process, in a pool of processes or on a Dask worker, and any trial can be
re-run alone (`--resume`).
"""

from __future__ import annotations

import hashlib
import time
from typing import Iterator, Optional

import numpy as np

from scissor_cli import control, runtime
from scissor_cli.config import parse_config
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.control.allocation import along_mm, miss_mm
from scissor_cli.experiments.build import build_model
from scissor_cli.experiments.pool import run_pool
from scissor_cli.experiments.profiles import ErrorModel, TrialDraw, draw_trial, error_model, trial_needle
from scissor_cli.experiments.sensor_models import sensor_model
from scissor_cli.experiments.trial_types import NominalInsertion, NominalOutcome, TargetTask, TrialOutcome
from scissor_cli.insertion import InsertionOptions, NeedleParams, needle_path, run_strategies
from scissor_cli.planning.corridor import corridor_radius
from scissor_cli.sensing.sensor import Sensor, SensorModel, TrialDraws
from scissor_cli.solvers.equilibrium import solve_equilibrium


class TrialContext:
    """Everything trials of one run share in one process: model, sensor, error model, warm starts."""

    def __init__(self, config_yaml: str):
        self.cfg = parse_config(config_yaml, "<run config>")
        self.scene, self.mesh, self.tissue = build_model(self.cfg)
        self.errors: ErrorModel = error_model(self.cfg.trials)
        self._sensors: Optional[SensorModel] = None  # made on first use (with imaging, from a task's tables)
        self.centroids = self.mesh.nodes[self.mesh.triangles].mean(axis=1)
        self._guesses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._controller_model = None  # built from the first task's ModelData (every task of a run has the same)
        self.slab_truth = None  # trials.truth: slab — the 3-D slab is the truth (docs/model.md §13)
        if self.cfg.trials.truth == "slab":
            from scissor_cli.layer3d.check import slab_spec
            from scissor_cli.layer3d.truth import SlabTruth

            self.slab_truth = SlabTruth(self.tissue, slab_spec(self.cfg.layer_check, self.cfg.tissue.mesh))

    @property
    def sensors(self) -> SensorModel:
        """The run's sensor model (`sensor_models.sensor_model`): the camera, or the ultrasound with `imaging`."""
        if self._sensors is None:
            self._sensors = sensor_model(self.cfg, self.scene, self.errors)
        return self._sensors

    def guess(self, task: TargetTask) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """The model's equilibrium at the plan's strokes: a warm start for the loop's first big move."""
        if not np.any(task.plan_strokes):
            return None
        if task.index not in self._guesses:
            r = solve_equilibrium(self.tissue, task.plan_strokes)
            self._guesses[task.index] = (task.plan_strokes, r.x)
        return self._guesses[task.index]

    def controller_factory(self, task: TargetTask):
        """How the loop makes its controller: None for the layer (`run_target`'s own), else from the task's model."""
        if task.controller_model is None:
            return None
        if self._controller_model is None:
            from scissor_cli.layer3d.tissue_models import ControllerModel  # noqa: PLC0415

            slab = self.slab_truth.slab if self.slab_truth is not None else None
            if slab is None and task.controller_model.kind == "slab":
                from scissor_cli.layer3d.check import slab_spec  # noqa: PLC0415
                from scissor_cli.layer3d.slab import build_slab  # noqa: PLC0415

                slab = build_slab(self.scene, self.mesh, slab_spec(self.cfg.layer_check, self.cfg.tissue.mesh),
                                  model=self.tissue.params.model, element=self.tissue.element.name)
            self._controller_model = ControllerModel(task.controller_model, self.tissue, slab)
        model = self._controller_model
        return lambda lo, hi, resolution_mm, tol: model.controller(task.index, lo, hi, resolution_mm, tol)

    def needle_model(self, task: TargetTask):
        """The controller's 3-D model of the task's target under the needle (docs/model.md §18), or None."""
        data = task.controller_model
        if self.slab_truth is None or data is None or not data.needle:
            return None
        return data.needle.get(task.name)

    def sensor(self, task: TargetTask, trial: int, draw) -> Sensor:
        """The trial's sensor: its localisation bias from the trial's normals, its frame noise from the trial's stream
        (the ultrasound: its own streams, and the plan's desired position to aim its window at)."""
        if self._sensors is None and task.imaging is not None:
            self._sensors = sensor_model(self.cfg, self.scene, self.errors, task.imaging)
        return self.sensors.for_trial(TrialDraws(draw.localisation_z, draw.rng, (int(self.cfg.seed), task.index, trial),
                                                 goal_mm=np.asarray(task.desired, float)))

    def target_run(self, task: TargetTask, trial: int) -> tuple[control.TargetRun, TrialDraw]:
        """How trial `trial` of `task` runs its loop (`control.TargetRun`: the drawn truth, the sensor, the
        actuator's errors, the corridor, the controller's model), and its draw."""
        if self.slab_truth is not None and task.slab_start is not None:
            self.slab_truth.remember(*task.slab_start)
        draw = draw_trial(self.errors, self.scene.material.nu, self.centroids, self.cfg.seed, task.index, trial)
        truth = control.TruthPerturbation(
            E_scale=draw.E_field, fiber_offset_rad=draw.fiber_offset_rad, nu=draw.nu, eta_scale=draw.eta_scale
        )
        corridor = None
        if task.side:
            corridor = control.Corridor(task.side, task.direction, corridor_radius(self.cfg.needle))
        return control.TargetRun(
            truth=truth, sensor=self.sensor(task, trial, draw),
            resolution_mm=self.errors.actuator_resolution_mm, backlash_mm=self.errors.backlash_mm,
            corridor=corridor, target=task.name, guess=self.guess(task),
            truth_factory=None if self.slab_truth is None else self.slab_truth.for_target(task.rest, task.plan_strokes),
            controller_factory=self.controller_factory(task),
        ), draw

    def nominal_run(self, task: TargetTask) -> control.TargetRun:
        """The nominal manipulation's `control.TargetRun`: the model as the truth, the exact camera, the plan's
        corridor and needle axis (what `simulate`'s manipulation stage runs, Fig. 11)."""
        corridor = None
        if task.side:
            corridor = control.Corridor(task.side, task.direction, corridor_radius(self.cfg.needle))
        return control.TargetRun(corridor=corridor, target=task.name, direction=np.asarray(task.direction, float),
                                 controller_factory=self.controller_factory(task))

    def run(self, task: TargetTask, trial: int) -> TrialOutcome:
        t0 = time.perf_counter()
        run, draw = self.target_run(task, trial)
        truth, sensor = run.truth, run.sensor
        r = control.run_target(self.tissue, task.rest, task.desired, self.cfg.controller, run)
        if r.stop_reason == "controller_failed":  # an outside controller's failure fails its trial (the run goes on)
            raise control.ControllerError(r.message)
        # The optional release slip moves the target along the (first) cup's axis after the loop.
        slip = draw.release_slip_mm * self.scene.cups[0].axis if len(self.scene.cups) else np.zeros(2)
        columns, table = r.history_table()
        final = np.asarray(r.final_error, float) + slip
        miss, depth_error = self.insert(task, trial, truth, sensor, r)
        return TrialOutcome(
            target_index=task.index, trial=trial, ok=True, message=r.message,
            final_error=final, iterations=int(r.iterations), time_s=float(r.time_s),
            corridor_clear=bool(r.corridor_clear) if r.corridor_clear is not None else False,
            clearance_mm=float(r.clearance_mm), stop_reason=r.stop_reason,
            correctable_mm=float(r.correctable_error_mm), uncorrectable_mm=float(r.uncorrectable_error_mm),
            history_columns=list(columns), history=table,
            miss_mm=miss_mm(final, task.direction), along_mm=along_mm(-final, task.direction),
            insertion_miss_mm=miss, insertion_depth_error_mm=depth_error, trial_time_s=time.perf_counter() - t0,
            lost_frames=int(getattr(sensor, "lost_frames", 0)), frames=int(getattr(sensor, "frames", 0)),
        )

    def insert(self, task: TargetTask, trial: int, truth, sensor: Sensor, loop) -> tuple[np.ndarray, np.ndarray]:
        """With `insertion:`, each strategy from the loop's final true state (docs/model.md §12): miss, depth
        error (S,).

        The truth tissue carries the trial's drawn friction and tip force;
        the plan's entry and direction are the ones the robot was given; the
        trial's sensor sees the target during insertion as during the loop
        (its frame noise on a stream of the insertion's own). The
        `loop` strategy's controller runs on its model (`self.tissue`): J at
        the model's equilibrium under the needle, starting from the model's
        equilibrium at the loop's final strokes (the truth's final state
        when truth and model are one object).

        With the slab truth (docs/model.md §14) the plant is the trial's
        perturbed slab from the loop's final slab state; the needle's entry
        and axis are the plan's lifted to the layer's height; the target is
        the slab's, at the layer; the sensor reads its in-plane part. With a
        3-D-aware controller model the plan's `NeedleModel` aims the needle's
        height per strategy and `loop` steers with its held Jacobian
        (docs/model.md §18); with the layer model the needle lies in the
        layer's plane and `loop`'s 2-D model runs the insertion its own way
        (`insertion.model_state.ModelInsertion`), from its own equilibrium
        at the loop's final strokes.
        """
        ins = self.cfg.insertion
        if ins is None or loop.final_x is None or task.entry is None:
            return np.zeros(0), np.zeros(0)
        params = trial_needle(NeedleParams.from_config(ins, self.cfg.needle, self.cfg.tissue.mesh), self.errors,
                              self.cfg.seed, task.index, trial)
        # each strategy's sensor goes on from the loop's on its own (a tracker follows one needle), all drawing
        # their frame noise from the one insertion stream, in the order they measure
        rng = np.random.default_rng([int(self.cfg.seed), task.index, trial, 13])
        needle = self.needle_model(task)
        if self.slab_truth is None:
            tissue = control.true_tissue(self.tissue, truth)
            model_start = (loop.final_strokes, loop.final_x)  # the model's warm start: the truth's, same mesh
        else:
            tissue = self.slab_truth.perturbed(truth)
            model_start = self.guess(task)  # the model's own equilibrium at the plan's strokes (or None: rest)
        model_x0 = None
        if tissue is not self.tissue and "loop" in ins.strategies and needle is None:
            s0, x0 = model_start if model_start is not None else (None, None)
            model_x0 = solve_equilibrium(self.tissue, loop.final_strokes, start=x0, start_strokes=s0).x
        options = {strategy: InsertionOptions(strategy, self.cfg.controller, sensor.reseeded(rng), self.tissue,
                                              model_x0, needle, keep_displacement=False)
                   for strategy in ins.strategies}
        paths = {strategy: needle_path(tissue, task.entry, task.direction, task.depth_mm, task.rest, task.name,
                                       None if needle is None else needle.height_for(strategy))
                 for strategy in ins.strategies}
        results = run_strategies(tissue, loop.final_x, loop.final_strokes, paths, params, options)
        miss = [r.miss_mm for r in results]
        depth_error = [r.depth_error_mm for r in results]
        return np.array(miss), np.array(depth_error)


_CONTEXTS: dict[str, TrialContext] = {}


def trial_context(config_yaml: str):
    """This process's context of the run with this config (built on first use; one run at a time)."""
    key = hashlib.sha256(config_yaml.encode()).hexdigest()
    if key not in _CONTEXTS:
        _CONTEXTS.clear()  # one run at a time per process
        if isinstance(parse_config(config_yaml, "<run config>"), BodyConfig):  # a 3-D scene's trials
            from scissor_cli.experiments.body_trials import BodyTrialContext  # noqa: PLC0415

            _CONTEXTS[key] = BodyTrialContext(config_yaml)
        else:
            _CONTEXTS[key] = TrialContext(config_yaml)
    return _CONTEXTS[key]


def run_trial(config_yaml: str, task: TargetTask, trial: int) -> TrialOutcome:
    """One trial, in whatever process runs it; a failure is an outcome, not an exception.

    A crashed trial's numbers are the fill values (no NaN): its `failed`
    mask in results.h5 says they mean nothing, and `--resume` re-runs it.
    """
    t0 = time.perf_counter()
    try:
        return trial_context(config_yaml).run(task, trial)
    except Exception as exc:  # noqa: BLE001 - a crashed trial is recorded and the run goes on
        elapsed = time.perf_counter() - t0
        return TrialOutcome(
            target_index=task.index, trial=trial, ok=False, message=f"{type(exc).__name__}: {exc}",
            final_error=np.zeros(2), iterations=-1, time_s=elapsed, trial_time_s=elapsed,
            corridor_clear=False, clearance_mm=0.0,
            stop_reason="controller_failed" if isinstance(exc, control.ControllerError) else "solver_failed",
            correctable_mm=0.0, uncorrectable_mm=0.0, history_columns=[], history=np.zeros((0, 0)),
        )


#: a work item: (task, trial k), or for a body's lesion (task, None), its nominal manipulation, or
#: (task, NominalInsertion(...)), its nominal insertions
WorkItem = tuple[TargetTask, Optional[int | NominalInsertion]]
#: what a work item gives
Outcome = TrialOutcome | NominalOutcome


def run_nominal(config_yaml: str, task: TargetTask, insertion: Optional[NominalInsertion] = None) -> NominalOutcome:
    """A body lesion's nominal manipulation (`BodyTrialContext.manipulate`), or with `insertion` its nominal
    insertions (`BodyTrialContext.insert_nominal`), in whatever process runs it; a failure is an outcome carrying its
    message (the run fails with it where the outcome is stored)."""
    what = "manipulation" if insertion is None else "insertion"
    try:
        context = trial_context(config_yaml)
        if insertion is not None:
            return NominalOutcome(task.index, what=what, insertion=context.insert_nominal(task, insertion.start))
        closed, opened = context.manipulate(task)
    except Exception as exc:  # noqa: BLE001 - the run's process reports it
        return NominalOutcome(task.index, error=f"{type(exc).__name__}: {exc}", what=what)
    return NominalOutcome(task.index, closed, opened)


def _is_trial(k) -> bool:
    """Whether a work item's second element is a trial's number (not a nominal manipulation or insertion)."""
    return k is not None and not isinstance(k, NominalInsertion)


def _run_item(config_yaml: str, task: TargetTask, k) -> Outcome:
    """Trial k of the task, or (k None) its nominal manipulation, or (k a `NominalInsertion`) its nominal
    insertions."""
    return run_trial(config_yaml, task, k) if _is_trial(k) else run_nominal(config_yaml, task, k)


def _run_batch(row: str, config_yaml: str, work: list[WorkItem]) -> list[tuple[str, Outcome]]:
    return [(row, _run_item(config_yaml, task, k)) for task, k in work]


def _run_batch_dask(row: str, config_yaml: str, work: list[WorkItem]) -> list[tuple[str, Outcome]]:
    """`_run_batch` in a Dask worker: scissor did not start that process, so its settings (one BLAS thread and one
    compiled-loop thread, freed memory kept: `runtime.configure`, idempotent) are applied here; without them Dask
    workers ran slab-truth trials markedly slower than the local pool (benchmarks/bench_dask_slab.py)."""
    runtime.configure(threads=1)
    return _run_batch(row, config_yaml, work)


def _batches(work: list[tuple[TargetTask, int]], size: int) -> list[list[tuple[TargetTask, int]]]:
    return [work[i : i + size] for i in range(0, len(work), size)]


def _batched(work: list[WorkItem], size: int) -> list[list[WorkItem]]:
    """`_batches` of the trials after one batch per nominal manipulation or insertion."""
    return [[w] for w in work if not _is_trial(w[1])] + _batches([w for w in work if _is_trial(w[1])], size)


def execute(
    config_yaml: str,
    work: list[WorkItem],
    jobs: int = 1,
    executor: str = "local",
    scheduler: Optional[str] = None,
) -> Iterator[Outcome]:
    """Run trials and yield outcomes as they finish (order not guaranteed).

    A work item (task, None) is the task's nominal manipulation, (task, `NominalInsertion`) its nominal
    insertions (a body's; each yields a `NominalOutcome`), run first and on its own, so it goes on beside the
    trials. jobs 1 runs in this process; a local pool sends
    small batches so each worker builds its model once, and its workers die with the run
    (`pool.run_pool`); "dask" submits batches to the dask.distributed
    scheduler at `scheduler`. Close the generator (or let an exception leave
    the loop over it) to stop the workers at once.
    """
    for _, outcome in execute_rows({"": config_yaml}, {"": work}, jobs, executor, scheduler):
        yield outcome


def execute_rows(
    rows: dict[str, str],
    work: dict[str, list[WorkItem]],
    jobs: int = 1,
    executor: str = "local",
    scheduler: Optional[str] = None,
) -> Iterator[tuple[str, Outcome]]:
    """`execute` for trials under several configs {row: config YAML} on one set of workers, {row: its trials}.

    Yields (row, outcome). Batches go row by row, so a worker rebuilds its
    model (`_context`) only when it moves to the next row; one pool serves
    every row instead of one pool started per row (the error budget).
    """
    todo = {row: work.get(row, []) for row in rows}
    total = sum(len(w) for w in todo.values())
    if not total:
        return
    if executor == "dask":
        yield from _execute_dask(rows, todo, scheduler)
        return
    if jobs <= 1:
        for row, config_yaml in rows.items():
            for task, k in todo[row]:
                yield row, _run_item(config_yaml, task, k)
        return
    jobs = min(jobs, total)  # a worker without a trial would only cost its start-up
    # Batches amortise the per-task overhead while keeping both workers busy to the end; a nominal manipulation
    # or insertion is a batch of its own, first.
    size = max(1, min(8, total // (len(rows) * 4 * jobs)))
    yield from run_pool(_run_batch, [(row, config_yaml, batch) for row, config_yaml in rows.items()
                                     for batch in _batched(todo[row], size)], jobs)


def _execute_dask(rows: dict[str, str], work: dict, scheduler: Optional[str]) -> Iterator[tuple[str, Outcome]]:
    try:
        from dask.distributed import Client, as_completed
    except ImportError:  # pragma: no cover - depends on the installation
        raise RuntimeError("--executor dask needs dask.distributed: pip install 'scissor[cluster]'") from None
    if not scheduler:
        raise RuntimeError("--executor dask needs --scheduler ADDRESS (e.g. tcp://127.0.0.1:8786)")
    with Client(scheduler, timeout="20s") as client:
        n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        size = max(1, min(8, sum(len(w) for w in work.values()) // (len(rows) * 4 * n_workers)))
        futures = [client.submit(_run_batch_dask, row, config_yaml, batch, pure=False)
                   for row, config_yaml in rows.items() for batch in _batched(work[row], size)]
        for future in as_completed(futures):
            yield from future.result()
