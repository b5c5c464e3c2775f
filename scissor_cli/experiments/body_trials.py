"""A 3-D scene's trial as a pure function of (config text, target, trial) (docs/model.md §19, "Trials").

The trial of a layer (`experiments.trials`) with a body: the controller's
model is the body (`controller.model: body`, meshed at `controller.mesh_scale`),
a surrogate learned from it (`surrogate`, `experiments.body_surrogate`) or
the paper's layer on the lesion's section (`layer`; `model_controllers`),
the truth the configured mesh (`BodyTruth`: the model's own when mesh_scale
is 1) with the profile's draws (E and its heterogeneity field over the tetrahedra'
centroids, ν, η, the fiber field turned about z), the cups' actuator with
the profile's resolution and backlash, and the scene's camera — or cameras,
which triangulate — with the profile's pixel noise and a localisation bias
per camera (`sensing.camera3d_sensor`). One camera does not see the depth
along its view: the loop drives the miss it sees (the seen part of P e) and
the outcome keeps the true 3-D miss across the needle. `trials.trial_context`
hands a body's config to `BodyTrialContext`; the executors (local pool,
Dask) run its `run` exactly as a layer's.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable, Optional

import numpy as np

from scissor_cli import control
from scissor_cli.config.loading import parse_config
from scissor_cli.control.allocation import along_mm, miss_mm
from scissor_cli.control.models import MapController, SectionController
from scissor_cli.control.plant import TruthView, true_tissue
from scissor_cli.experiments.build import body_model, section_model
from scissor_cli.experiments.profiles import BodyDraw, ErrorModel, draw_body, draw_trial, error_model, trial_needle
from scissor_cli.experiments.trial_types import TrialOutcome
from scissor_cli.insertion import InsertionOptions, NeedleParams, NeedlePath, run_strategies
from scissor_cli.layer3d.surrogate import Surrogate
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import target_positions
from scissor_cli.sensing.camera3d_sensor import BodyCameraModel
from scissor_cli.sensing.sensor import TrialDraws
from scissor_cli.solvers.equilibrium import solve_equilibrium

#: A body's loop (a trial's, and a lesion's nominal manipulation, which runs as a trial does without its errors)
#: settles the true body to this relative residual.
#: The camera reads the lesion to its noise (σ ≈ 0.15 mm on the paper's bench); along a loop's travel on the paper
#: dome the lesion stays decades below that noise from its 1e-10 settle, on p1 and on nodal, and a settle costs
#: fewer Newton iterations and factorisations (benchmarks/bench_body_truth_tol.py); the slab truth's
#: `SLAB_TRUTH_TOL` is chosen alike.
BODY_TRUTH_TOL = 1e-5
#: and the controller's model (the body itself) to this one: its J steers by a camera read to that noise, and the
#: actuator quantises the commands; settled this loosely it goes on with a factorisation that still preconditions
#: well instead of factoring at every move (`solvers.tracking.KEEP_FACTOR_FROM_TOL`; benchmarks/ab_trials.py,
#: docs/performance.md "Where a trial's time goes")
BODY_MODEL_TOL = 1e-5


def loop_tolerances(controller_cfg) -> dict[str, float]:
    """`control.TargetRun`'s tol and truth_tol for a body's loops, its trials' and its nominal manipulations':
    BODY_MODEL_TOL for the controller's model when that is the body (a layer or a surrogate keeps the loop's
    default), BODY_TRUTH_TOL for the truth (the model's own when the truth is the model)."""
    return {"tol": BODY_MODEL_TOL if controller_cfg.model == "body" else control.TargetRun.tol,
            "truth_tol": BODY_TRUTH_TOL}


def model_controllers(cfg, model_data=None) -> Callable[[int], Optional[Callable]]:
    """Target index → the loop's `controller_factory` for a 3-D run: None (the controller's model is the body
    itself); with controller.model layer, (lo, hi, resolution_mm, tol) → a `SectionController` on that target's
    section, each section built once; with surrogate, a `MapController` on the surrogate of `model_data`
    (`experiments.body_surrogate`)."""
    sections: dict[int, tuple] = {}
    if cfg.controller.model == "surrogate":
        if model_data is None or model_data.samples is None:
            raise ValueError("controller.model surrogate: the run's surrogate samples are needed (model_data)")
        surrogate = Surrogate(model_data.samples, components=3)
        return lambda index: (lambda lo, hi, resolution_mm, tol: MapController(
            surrogate.target_map(index), len(lo), lo, hi, resolution_mm))

    def factory_for(index: int) -> Optional[Callable]:
        if cfg.controller.model != "layer":
            return None
        if index not in sections:
            sections[index] = section_model(cfg, index)
        tissue, probe, plane = sections[index]
        return lambda lo, hi, resolution_mm, tol: SectionController(tissue, probe, plane.basis, lo, hi,
                                                                    resolution_mm, tol)

    return factory_for


class BodyTruth:
    """The trials' true body: the configured mesh, when the model's body is coarser (`controller.mesh_scale` > 1).

    `factory` is the loop's `TruthFactory` (the perturbed fine body and its view: each lesion probed in the fine
    tetrahedra) or None when the truth is the model's own mesh; `centroids` (M, 3) mm: the truth's tetrahedra, where
    a trial's E field is drawn.
    """

    def __init__(self, cfg, model: Tissue):
        self.tissue, self.centroids = model, model.mesh.nodes[model.mesh.tetrahedra].mean(axis=1)
        self.finer = cfg.controller.mesh_scale != 1.0
        if self.finer:
            _, mesh, self.tissue = body_model(cfg)
            self.centroids = mesh.nodes[mesh.tetrahedra].mean(axis=1)

    def lesion_scaled(self, E_field: np.ndarray, lesion: str, factor: float) -> np.ndarray:
        """The trial's E field (M,) on the truth's tetrahedra with the lesion's own times `factor`."""
        if factor == 1.0:
            return E_field
        mesh = self.tissue.mesh
        return np.where(mesh.region == mesh.region_names.index(lesion), factor, 1.0) * E_field

    def factory(self, target_rest: np.ndarray) -> Optional[Callable]:
        """The `TargetRun.truth_factory` of the lesion at target_rest (3,) mm, or None (the truth is the model)."""
        if not self.finer:
            return None
        fine = self.tissue
        probe = fine.probe(np.asarray(target_rest, float)[None])
        view = TruthView(target=lambda x: target_positions(probe, x)[0], layer=lambda x: x)
        return lambda perturbation: (true_tissue(fine, perturbation), view)


def nominal_manipulation(tissue: Tissue, rest: np.ndarray, desired: np.ndarray, controller_cfg,
                         run: control.TargetRun) -> tuple[control.LoopResult, control.LoopResult]:
    """A lesion's closed loop from rest to `desired` (3,) mm and its open-loop baseline, on `run`'s nominal truth.

    The baseline's one move goes from rest about as far as the loop went: on the same nominal truth, the
    loop's end is its warm start (from rest a nodal body's load continuation costs several factorisations).
    """
    closed = control.run_target(tissue, rest, desired, controller_cfg, run)
    ended = None if closed.final_x is None else (closed.hist_strokes[-1], closed.final_x)
    opened = control.run_target(tissue, rest, desired, controller_cfg, replace(run, mode="open", truth_guess=ended))
    return closed, opened


def nominal_insertions(cfg, truth: Tissue, sensors, index: int, path: NeedlePath, strokes: np.ndarray,
                       desired: np.ndarray, x0: np.ndarray, needle, on_step: Optional[Callable] = None) -> list:
    """A lesion's nominal insertions (every configured strategy, `insertion.run_strategies`) in the body `truth`
    along its plan's `path` from x0 (N, 3) mm, the body's equilibrium at the plan's strokes (C,) mm, seen without
    error by `sensors` (`body_sensor_model`'s; desired (3,) mm where the plan wants the lesion); the lesion is
    truth's target `index`, `loop` steered by `needle` (an `insertion.NeedleModel` or None). The same in the
    run's own process (`body_insertion.body_insertion_stage`) and in a trials' worker beside the trials
    (`BodyTrialContext.insert_nominal`). on_step(depth_mm): after each step."""
    params = NeedleParams.from_config(cfg.insertion, cfg.needle, cfg.tissue.mesh)
    strategies = list(cfg.insertion.strategies)
    sensor = sensors.nominal(np.asarray(desired, float), index, cfg.seed)
    return run_strategies(truth, x0, np.asarray(strokes, float), dict.fromkeys(strategies, path), params,
                          {k: InsertionOptions(k, cfg.controller, sensor=sensor, on_step=on_step, needle_model=needle)
                           for k in strategies})


def plan_path(plan, rest: np.ndarray, name: str) -> NeedlePath:
    """The needle of a plan (its entry, direction and depth mm: a `BodyNeedlePlan` or a trials' `TargetTask`) to
    the lesion `name` at rest (3,) mm."""
    return NeedlePath(np.asarray(plan.entry, float), np.asarray(plan.direction, float), float(plan.depth_mm),
                      np.asarray(rest, float), name)


def body_sensor_model(cfg, errors: ErrorModel, mesh=None):
    """The run's 3-D sensor model: with `imaging`, the ultrasound with its probe on `mesh`'s skin
    (`sensing.ultrasound.body_sensor`, the profile's imaging errors); else the camera model, `cameras`
    (triangulating) or `camera`, with the profile's pixel noise and bias."""
    if cfg.imaging is not None:
        from scissor_cli.experiments.sensor_models import imaging_tables_for  # noqa: PLC0415 (pymust: only here)
        from scissor_cli.sensing.ultrasound import ImagingErrors  # noqa: PLC0415
        from scissor_cli.sensing.ultrasound.body_sensor import body_ultrasound_model  # noqa: PLC0415

        if mesh is None:
            raise ValueError("the body's ultrasound needs the body's mesh (its skin holds the probe)")
        return body_ultrasound_model(cfg.imaging, mesh, cfg.targets, cfg.obstacles, imaging_tables_for(cfg.imaging),
                                     cfg.needle.direction, ImagingErrors(
                                         errors.sound_speed_sd_m_per_s, errors.probe_position_sd_mm,
                                         errors.probe_angle_sd_deg, errors.electronic_noise_scale))
    return BodyCameraModel.from_config(cfg.cameras if cfg.cameras else cfg.camera,
                                       pixel_noise_px=errors.pixel_noise_px,
                                       localisation_error_mm=errors.localisation_error_mm,
                                       ideal=errors.exact_measurement)


class BodyTrialContext:
    """What the trials of one 3-D run share in one process: the body, its sensor model, the error model."""

    def __init__(self, config_yaml: str):
        self.cfg = parse_config(config_yaml, "<run config>")
        self.scene, self.mesh, self.tissue = body_model(self.cfg, scale=self.cfg.controller.mesh_scale)
        self.truth = BodyTruth(self.cfg, self.tissue)
        self.errors: ErrorModel = error_model(self.cfg.trials)
        self.sensors = body_sensor_model(self.cfg, self.errors, self.truth.tissue.mesh)
        self._guesses: dict[int, np.ndarray] = {}  # per target: the model's equilibrium at the plan (`guess`)
        self.paths: dict[int, control.ModelPaths] = {}  # per target: the model's states the loops solved
        self.controllers: Optional[Callable] = None  # from the first task (a surrogate's samples come in it)

    def guess(self, task) -> tuple[np.ndarray, Callable[[], np.ndarray]] | None:
        """(the plan's strokes (C,) mm, the function solving the model's equilibrium there (N, 3) mm): a warm start
        for the loop's first big move, solved (once in this process) only when a move starts there — a body's
        load continuation from rest costs seconds, and a loop stepping at its drives' speed seldom needs it."""
        if not np.any(task.plan_strokes):
            return None

        def solved() -> np.ndarray:
            if task.index not in self._guesses:
                self._guesses[task.index] = solve_equilibrium(self.tissue, task.plan_strokes).x
            return self._guesses[task.index]

        return task.plan_strokes, solved

    def nominal_run(self, task) -> control.TargetRun:
        """The nominal manipulation's `control.TargetRun`: the nominal body as the truth, its camera(s) without
        error, the controller's model (what `simulate`'s manipulation stage runs)."""
        if self.controllers is None:
            self.controllers = model_controllers(self.cfg, task.controller_model)
        sensor = self.sensors.nominal(np.asarray(task.desired, float), task.index, self.cfg.seed)
        return control.TargetRun(sensor=sensor, target=task.name, direction=np.asarray(task.direction, float),
                                 controller_factory=self.controllers(task.index),
                                 truth_factory=self.truth.factory(task.rest), **loop_tolerances(self.cfg.controller))

    def manipulate(self, task) -> tuple[control.LoopResult, control.LoopResult]:
        """The lesion's nominal manipulation (`nominal_manipulation` of `nominal_run`), as `simulate`'s own
        process runs it: what a worker runs beside the trials."""
        return nominal_manipulation(self.tissue, np.asarray(task.rest, float), np.asarray(task.desired, float),
                                    self.cfg.controller, self.nominal_run(task))

    def insert_nominal(self, task, start: Optional[np.ndarray] = None) -> list:
        """The lesion's nominal insertions (`nominal_insertions` in the undrawn truth from start (N, 3) mm, its
        equilibrium at the plan's strokes, solved here when None), as `simulate`'s own process runs them: what
        a worker runs beside the trials."""
        truth = self.truth.tissue
        if start is None:
            start = solve_equilibrium(truth, task.plan_strokes).x
        return nominal_insertions(self.cfg, truth, self.sensors, task.index, plan_path(task, task.rest, task.name),
                                  task.plan_strokes, task.desired, start, task.needle_model)

    def target_run(self, task, trial: int) -> tuple[control.TargetRun, BodyDraw]:
        """How trial `trial` of `task` runs its loop (`control.TargetRun`: the drawn truth with the lesion's
        stiffness, the sensor, the actuator's errors, the controller's model), and its 3-D draw."""
        if self.controllers is None:
            self.controllers = model_controllers(self.cfg, task.controller_model)
        draw = draw_trial(self.errors, self.scene.material.nu, self.truth.centroids, self.cfg.seed, task.index, trial)
        body = draw_body(self.errors, self.cfg.seed, task.index, trial)
        truth = control.TruthPerturbation(E_scale=self.truth.lesion_scaled(draw.E_field, task.name,
                                                                           body.lesion_stiffness),
                                          fiber_offset_rad=draw.fiber_offset_rad, nu=draw.nu, eta_scale=draw.eta_scale)
        desired = np.asarray(task.desired, float)
        sensor = self.sensors.for_trial(TrialDraws(draw.localisation_z, draw.rng,
                                                   (int(self.cfg.seed), task.index, trial), goal_mm=desired))
        return control.TargetRun(
            **loop_tolerances(self.cfg.controller), truth=truth, sensor=sensor,
            resolution_mm=self.errors.actuator_resolution_mm,
            backlash_mm=self.errors.backlash_mm, target=task.name, guess=self.guess(task),
            direction=np.asarray(task.direction, float), controller_factory=self.controllers(task.index),
            truth_factory=self.truth.factory(task.rest),
            model_paths=self.paths.setdefault(task.index, control.ModelPaths())), body

    def run(self, task, trial: int):
        t0 = time.perf_counter()
        run, body = self.target_run(task, trial)
        truth, sensor, desired = run.truth, run.sensor, np.asarray(task.desired, float)
        r = control.run_target(self.tissue, task.rest, desired, self.cfg.controller, run)
        if r.stop_reason == "controller_failed":  # an outside controller's failure fails its trial (the run goes on)
            raise control.ControllerError(r.message)
        # the needle goes in along the plan's line where the robot, registered with the trial's error, puts it
        direction = body.rotation @ np.asarray(task.direction, float)
        entry = body.moved(np.asarray(task.entry, float))[0] if task.entry is not None else None
        miss, depth_error = self.insert(task, trial, truth, sensor, r, entry, direction)
        columns, table = r.history_table()
        final = np.asarray(r.final_error, float)
        across = final if body.registered_exactly else final + desired - body.moved(desired)[0]  # from the line
        return TrialOutcome(
            target_index=task.index, trial=trial, ok=True, message=r.message, final_error=final,
            iterations=int(r.iterations), time_s=float(r.time_s), corridor_clear=False, clearance_mm=float("nan"),
            stop_reason=r.stop_reason, correctable_mm=float(r.correctable_error_mm),
            uncorrectable_mm=float(r.uncorrectable_error_mm), history_columns=list(columns), history=table,
            miss_mm=miss_mm(across, direction), along_mm=along_mm(-across, direction),
            insertion_miss_mm=miss, insertion_depth_error_mm=depth_error, trial_time_s=time.perf_counter() - t0,
            lost_frames=int(getattr(sensor, "lost_frames", 0)), frames=int(getattr(sensor, "frames", 0)))

    def insert(self, task, trial: int, truth, sensor, loop, entry, direction) -> tuple[np.ndarray, np.ndarray]:
        """With `insertion`: each strategy's needle in the trial's true body from the loop's end, along the line
        from entry (3,) mm along direction (3,) (the plan's, moved by the registration's error), (miss, depth
        error) (S,) mm; else two empty arrays.

        As a layer's trial inserts (`trials.TrialContext.insert`): the profile's factors on the friction and
        the tip force, the trial's camera(s) going on from the loop's on a stream of their own, the plan's
        entry and axis. `loop` steers with the task's needle model (the nominal body's insertion at the plan,
        tabulated once per run: `body_insertion.body_needle_models`; docs/model.md §20), whatever model steered
        the manipulation; without one, with the undrawn body on the truth's mesh following the needle.
        """
        ins = self.cfg.insertion
        if ins is None or loop.final_x is None:
            return np.zeros(0), np.zeros(0)
        params = trial_needle(NeedleParams.from_config(ins, self.cfg.needle, self.cfg.tissue.mesh), self.errors,
                              self.cfg.seed, task.index, trial)
        rng = np.random.default_rng([int(self.cfg.seed), task.index, trial, 13])
        nominal = self.truth.tissue
        plant = control.true_tissue(nominal, truth)
        needle = task.needle_model
        model_x0 = None
        if plant is not nominal and "loop" in ins.strategies and needle is None:
            model_x0 = solve_equilibrium(nominal, loop.final_strokes, start=loop.final_x,
                                         start_strokes=loop.final_strokes).x
        path = NeedlePath(np.asarray(entry, float), np.asarray(direction, float), float(task.depth_mm),
                          np.asarray(task.rest, float), task.name)
        options = {k: InsertionOptions(k, self.cfg.controller, sensor.reseeded(rng), nominal, model_x0, needle,
                                       keep_displacement=False) for k in ins.strategies}
        results = run_strategies(plant, loop.final_x, loop.final_strokes, dict.fromkeys(ins.strategies, path),
                                 params, options)
        return np.array([x.miss_mm for x in results]), np.array([x.depth_error_mm for x in results])
