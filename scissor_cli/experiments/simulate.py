"""`scissor simulate`: the pipeline from a validated config to a finished run (docs/contract.md#simulate).

The stages (selection, model, forward cases, Jacobian, study, plans,
manipulation, trials) compute; they hand every product to a `RunSink`
(`experiments.sink`), which keeps it: `output` provides the one that writes
results.h5 and the figures, and `cli.py` passes it in. Progress and messages
go to `scissor_cli.progress`, where the CLI decides what a terminal shows.
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from scissor_cli import control, progress
from scissor_cli.config import Config, parse_config, resolved_yaml
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.experiments.build import build_model, with_grips  # noqa: F401 - build_model: this module's API too
from scissor_cli.experiments.controller_model_stage import controller_model_stage, needs_slab, refitted_model
from scissor_cli.experiments.error_budget import run_budget
from scissor_cli.experiments.forward_stage import forward_stage
from scissor_cli.experiments.imaging_stage import prepare_imaging
from scissor_cli.experiments.insertion_stage import insertion_stage
from scissor_cli.experiments.model_planning import reserved_scene
from scissor_cli.experiments.needle_model_stage import needs_needle_models
from scissor_cli.experiments.profiles import (
    BODY_SPREADS,
    CAMERA_SPREADS,
    IMAGING_SPREADS,
    INSERTION_SPREADS,
    error_model,
)
from scissor_cli.experiments.run_cache import cache_dir
from scissor_cli.experiments.run_summary import RunSummary
from scissor_cli.experiments.selection import resolved_by_selection
from scissor_cli.experiments.sink import (  # noqa: F401 - raised through this module's API
    ForwardCase,
    Manipulation,
    NonFiniteError,
    ResumableSink,
    ResumeError,
    RunSink,
    SinkFactory,
    product_key,
)
from scissor_cli.experiments.slab_starts import with_slab_starts
from scissor_cli.experiments.study import run_study
from scissor_cli.experiments.trial_stage import Execution, TrialsFailed, expected_duration, run_trial_stage  # noqa: F401 (this module's API)
from scissor_cli.experiments.trial_types import law_attrs
from scissor_cli.experiments.trials import TargetTask
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.outlines import boundary_loop, deformed_outlines, embed_outlines
from scissor_cli.mesh.probe import probe_targets
from scissor_cli.planning.corridor import corridor_radius
from scissor_cli.planning.needle_plan import NeedlePlan, plan_target, stored_plan
from scissor_cli.planning.states import StateCache
from scissor_cli.robot.chain import RobotModel
from scissor_cli.robot.registration import plan_to_joints
from scissor_cli.solvers.jacobian import cup_target_jacobian
from scissor_cli.text import signed


def run_simulation(cfg: Config, run: SinkFactory,
                   execution: Execution = Execution()) -> RunSummary:
    """Everything `scissor simulate` does for a validated config, into the sink `run` opens.

    Forward cases, the rest Jacobian and the needle plans always; with
    `cfg.trials.count` > 0 also the nominal manipulation of every target
    (Fig. 11) and the trials (Fig. 14). Raises SolverError, TrialsFailed or
    NonFiniteError after the sink has kept what was finished, marked failed.
    """
    if isinstance(cfg, BodyConfig):  # a 3-D scene (docs/model.md §19)
        from scissor_cli.experiments.body_run import run_body_simulation  # noqa: PLC0415

        return run_body_simulation(cfg, run, execution)
    # the file records the config that ran; the budget stays in /selection
    cfg, selection = resolved_by_selection(cfg)
    grips = None
    if cfg.manipulation_points is not None:
        cfg, grips = grip_stage(cfg)
    slab_choice = None
    if cfg.layer_check is not None and cfg.layer_check.accuracy_mm is not None:
        from scissor_cli.experiments.layer_check_stage import slab_resolution_stage  # noqa: PLC0415

        cfg, slab_choice = slab_resolution_stage(cfg, cache_dir(run.location),
                                                 execution.jobs if execution.executor == "local" else 1)
    tissue = _build(cfg)
    summary = RunSummary(run.location, tissue.mesh.n_elements)
    with run.open(resolved_yaml(cfg), cfg.seed) as sink:
        if grips is not None and hasattr(sink, "manipulation_points"):
            path = sink.manipulation_points(grips, tissue.scene)
            if path is not None:
                summary.figures.append(path)
        if slab_choice is not None:
            sink.slab_resolution(slab_choice)
        _stages(cfg, tissue, sink, summary, execution, selection)
    return summary


def grip_stage(cfg: Config):
    """Choose where the cups grip (docs/model.md §7); the run goes on with the chosen contacts and axes.

    The config the run records has the chosen points in its first
    `manipulation_points.cups` cups and no `manipulation_points` section, so
    trials and `--resume` rebuild exactly the model that ran; the search
    itself is stored in /manipulation_points.
    """
    from scissor_cli.planning.manipulation_points import plan_grips  # noqa: PLC0415

    _, _, tissue = build_model(cfg)
    plan = plan_grips(cfg.manipulation_points, cfg.needle, tissue,
                      lambda contacts, axes: build_model(with_grips(cfg, contacts, axes))[2])
    placed = with_grips(cfg, plan.contacts, plan.axes).model_copy(update={"manipulation_points": None})
    where = "; ".join(f"{c.name} at {signed(p)} mm pushing {signed(a)}" for c, p, a in
                      zip(placed.cups, plan.contacts, plan.axes))
    progress.info(f"manipulation points: {len(plan.candidates)} candidates ranked in {plan.search_s:.2f} s, "
                  f"verified in {plan.verify_s:.2f} s: {where}")
    for note in plan.notes:
        progress.info(f"manipulation points: {note}")
    return placed, plan


def resume_simulation(sink: ResumableSink, execution: Execution = Execution()) -> int:
    """Finish an interrupted, killed or partly failed run in its sink; returns how many trials ran.

    The stored run's config is reused; every stage product the sink marks
    finished (`RunSink.finished`) is kept and not recomputed, the rest is
    done as a new run would do it (docs/contract.md#resume). When the sink
    lost the stored file, nothing is marked: the stages before the trials
    run again (they are deterministic) and the trials the sink recovered are
    kept.
    """
    for note in sink.notes():
        progress.info(note)
    with sink:
        cfg = parse_config(sink.config_yaml, str(sink.location / "results.h5"))
        done = sink.finished()
        if isinstance(cfg, BodyConfig):
            from scissor_cli.experiments.body_run import resume_body  # noqa: PLC0415

            return resume_body(cfg, sink, done, execution)
        tissue = build_model(cfg)[2] if "trials" in done else _build(cfg)
        summary = RunSummary(sink.location, tissue.mesh.n_elements)
        if done:
            progress.info(f"resume: {len(done)} finished stage product(s) kept")
        _stages(cfg, tissue, sink, summary, execution, done=done)
        return summary.trials_run


def _build(cfg: Config) -> Tissue:
    t_mesh = time.perf_counter()
    scene, mesh, tissue = build_model(cfg)
    angles = mesh.angles_deg()
    progress.info(
        f"mesh: {mesh.n_elements} triangles, {mesh.n_nodes} nodes, min angle {angles.min():.1f}°, "
        f"edges {mesh.edge_lengths().min():.2f}–{mesh.edge_lengths().max():.2f} mm "
        f"({time.perf_counter() - t_mesh:.2f} s)"
    )
    return tissue


def _stages(cfg: Config, tissue: Tissue, sink: RunSink, summary: RunSummary,
            execution: Execution, selection=None, done: frozenset[str] = frozenset()) -> None:
    """The stages after the model is built, in the order of docs/contract.md#simulate.

    Each product is marked finished in the sink once stored; one in `done`
    (a resumed run's) is not computed again.
    """
    scene, mesh = tissue.scene, tissue.mesh
    if "model" not in done:
        sink.model(tissue)
        if selection is not None:
            sink.selection(selection)
        sink.mark_finished("model")
    probe = probe_targets(mesh, np.array([t.rest for t in scene.targets]).reshape(-1, 2))
    forward_stage(cfg.forward, cfg.solver, tissue, probe, sink, summary,
                  lambda case, strokes, result, targets: _forward_figure_inputs(cfg.name, tissue, case, strokes,
                                                                                result, targets), done=done)
    if cfg.layer_check is not None and cfg.forward:
        from scissor_cli.experiments.layer_check_stage import run_layer_check

        summary.figures += run_layer_check(cfg, tissue, sink, done)
    probe = probe_targets(mesh, np.array([t.rest for t in scene.targets]).reshape(-1, 2))
    if len(scene.targets) and "jacobian" not in done:
        J = cup_target_jacobian(tissue, tissue.rest, probe)
        for k, target in enumerate(scene.targets):
            sink.jacobian(target.name, J[2 * k : 2 * k + 2], scene.cup_names)
        sink.mark_finished("jacobian")
    if cfg.study is not None and "study" not in done:
        _study_stage(cfg, sink)
        sink.mark_finished("study")
    stored = sink.plans() if "plan" in done else None
    if stored is not None:
        obstacles = bool(tissue.scene.obstacles)
        summary.plans = [stored_plan(t.name, stored[t.name], obstacles) for t in tissue.scene.targets]
        model_data = stored_model(cfg, tissue, sink, summary.plans)
    else:
        summary.plans, model_data = _plan_stage(cfg, tissue, sink, summary, execution.jobs)
        sink.mark_finished("plan")
    imaging_data, nominal_imaging = None, None
    if cfg.imaging is not None and cfg.trials.count > 0:  # the probe's tables, once per run (docs/model.md §17)
        imaging_data, nominal_imaging = prepare_imaging(cfg, tissue, cache_dir(sink.location))
    if cfg.trials.count > 0:
        summary.figures += _manipulation_stage(cfg, tissue, summary.plans, sink, done, nominal_imaging)
    if cfg.insertion is not None:
        summary.figures += insertion_stage(cfg, tissue, summary.plans, sink, done,
                                           None if model_data is None else model_data.needle)
    if cfg.trials.count > 0:
        tasks = [replace(t, imaging=imaging_data) for t in trial_tasks(tissue, summary.plans, model_data)]
        if "trials" not in done:
            allocate_trial_arrays(sink, cfg, tasks, summary.plans)
            sink.mark_finished("trials")
        if cfg.trials.truth == "slab" and (cfg.trials.budget or any(len(ks) for ks in sink.pending_trials().values())):
            tasks = with_slab_starts(cfg, sink.config_yaml, tasks, cache_dir(sink.location), execution.jobs)
        summary.trials_run = run_trial_stage(sink, cfg, tasks, execution)
        if cfg.trials.budget:
            summary.figures += run_budget(cfg, tasks, sink, execution, done)


def _study_stage(cfg: Config, sink: RunSink) -> None:
    t0 = time.perf_counter()
    study = run_study(cfg)
    seconds = time.perf_counter() - t0
    sink.study(study, seconds)
    for note in study.notes:
        progress.info(f"study: {note}")
    progress.info(f"study: {len(study.rows)} combinations in {seconds:.1f} s "
                  f"(speed vs error: scissor report {sink.location})")


def trial_tasks(tissue: Tissue, plans: list[NeedlePlan], model_data=None) -> list[TargetTask]:
    """Plain-data tasks of the targets that have a plan with a desired position (and the controller's model
    when it is not the layer)."""
    tasks = []
    for index, (target, plan) in enumerate(zip(tissue.scene.targets, plans)):
        if plan.feasible:
            tasks.append(TargetTask(index, target.name, target.rest, np.asarray(plan.desired, float),
                                    np.asarray(plan.strokes, float), plan.side, np.asarray(plan.direction, float),
                                    np.asarray(plan.entry, float), float(plan.depth_mm),
                                    model_data if model_data is not None and model_data.kind != "layer" else None))
    return tasks


def allocate_trial_arrays(sink: RunSink, cfg: Config, tasks: list[TargetTask], plans: list[NeedlePlan]) -> None:
    """Room for every trial, with the error model's resolved values; a target without a plan is done at once."""
    em = error_model(cfg.trials)
    # the sensor's sources: the camera's, or with imaging the ultrasound's (the camera's do not apply then)
    other_sensor = CAMERA_SPREADS if cfg.imaging is not None else IMAGING_SPREADS
    attrs = {"count": cfg.trials.count, "profile": cfg.trials.profile, "seed": cfg.seed, **law_attrs(cfg.controller),
             "sensor": "camera" if cfg.imaging is None else "ultrasound",
             **{k: v for k, v in asdict(em).items()
                if k not in ("profile",) + INSERTION_SPREADS + other_sensor + BODY_SPREADS}}
    if cfg.insertion is not None:
        attrs.update({k: getattr(em, k) for k in INSERTION_SPREADS})
        attrs["insertion_strategies"] = list(cfg.insertion.strategies)
    planned = {t.name for t in tasks}
    without_plan = {p.target: p.reason for p in plans if p.target not in planned}
    sink.allocate_trials([p.target for p in plans], cfg.trials.count, attrs, without_plan)


def _manipulation_stage(cfg: Config, tissue: Tissue, plans: list[NeedlePlan], sink: RunSink,
                        done: frozenset[str] = frozenset(), imaging=None) -> list[Path]:
    """The nominal manipulation of each planned target (truth = model, exact camera): Fig. 11.

    The open-loop baseline (one Jacobian step from rest) is kept beside it.
    With `imaging` (an `imaging_stage.NominalImaging`) the target is seen by
    the ultrasound with the ideal profile's draws, and the closed loop's
    frames go to the sink (docs/model.md §17).
    """
    radius = corridor_radius(cfg.needle)
    paths = []
    for index, (target, plan) in enumerate(zip(tissue.scene.targets, plans)):
        if not plan.feasible or product_key("manipulation", target.name) in done:
            continue
        corridor = control.Corridor.from_plan(plan, radius)
        run = control.TargetRun(corridor=corridor, target=target.name)
        seen = (run.sensor, run.sensor) if imaging is None else imaging.sensors(index, plan.desired)
        closed = control.run_target(tissue, target.rest, plan.desired, cfg.controller, replace(run, sensor=seen[0]))
        opened = control.run_target(tissue, target.rest, plan.desired, cfg.controller,
                                    replace(run, mode="open", sensor=seen[1]))
        path = sink.manipulation(Manipulation(target.name, closed, opened, tissue, target.rest, corridor))
        if imaging is not None:
            paths += imaging.hand_over(sink, target.name, plan, closed, seen[0], tissue)
        sink.mark_finished(product_key("manipulation", target.name))
        if path is not None:
            paths.append(path)
        progress.info(
            f"manipulation {target.name}: closed loop {closed.iterations} iterations ({closed.stop_reason}), "
            f"miss {closed.miss_mm:.3f} mm (along the needle {closed.along_error_mm:+.3f} mm, for the depth) "
            f"vs open loop {opened.miss_mm:.3f} mm, "
            f"corridor {'clear' if closed.corridor_clear else 'BLOCKED'}"
        )
    return paths


def _plan_stage(cfg: Config, tissue: Tissue, sink: RunSink, summary: RunSummary, jobs: int = 1):
    """Plan every target's insertion (the plan's desired position becomes the target's), then with the
    controller's model where it is not the layer (docs/model.md §15); (plans, the model's data or None)."""
    scene = tissue.scene
    robot_check = robot_joint_check(cfg)
    cache = StateCache(tissue)
    plans = layer_plans(cfg, tissue, cache)
    reserved = reserved_scene(scene, cfg.controller.stroke_reserve)  # a 3-D-aware model plans again inside it

    def replan(t: int, target_at, layer_at=None) -> NeedlePlan:
        return plan_target(tissue, reserved, scene.targets[t], cfg.needle, robot_check=robot_check, cache=cache,
                           target_at=target_at, layer_at=layer_at)

    model_data, plans, paths = controller_model_stage(cfg, tissue, plans, sink.location, jobs, replan)
    if model_data is not None and hasattr(sink, "controller_model"):
        figure = sink.controller_model(model_data, [t.name for t in scene.targets], paths,
                                       cfg.controller.jacobian_update, cfg.name)
        if figure is not None:
            summary.figures.append(figure)
    for target, plan in zip(scene.targets, plans):
        sink.plan(target, plan, "config" if target.desired is not None else
                  "planner" if plan.planned_with == "layer" else "model")
        how = (f"strokes {signed(plan.strokes)} mm" if plan.manipulated else "no manipulation needed")
        if plan.slab_strokes is not None and plan.feasible:
            off = "" if plan.model_error_mm is None else f"; the model's target there {plan.model_error_mm:.2f} mm off"
            how += f" (the nominal slab needs {signed(plan.slab_strokes)} mm{off})"
        if plan.feasible and not plan.robot_ok:
            how += f"; ROBOT: {plan.robot_note}"
        progress.info(
            f"plan {target.name}: "
            + (f"{plan.side} entry, {_clearance_text(plan.clearance_mm)}, {how} ({plan.time_s:.1f} s)"
               if plan.feasible else f"infeasible: {plan.reason}")
        )
    return plans, model_data


def layer_plans(cfg: Config, tissue: Tissue, cache: StateCache | None = None) -> list[NeedlePlan]:
    """Every target's needle plan on the layer (docs/model.md §8), in the scene's order; `cache` keeps the
    solved states for a later replanning."""
    robot_check = robot_joint_check(cfg)
    cache = StateCache(tissue) if cache is None else cache
    plans = []
    advance = progress.bar("needle plans", len(tissue.scene.targets))
    for target in tissue.scene.targets:
        plans.append(plan_target(tissue, tissue.scene, target, cfg.needle, robot_check=robot_check, cache=cache))
        advance(1)
    return plans


def stored_model(cfg: Config, tissue: Tissue, sink: RunSink, plans: list):
    """A resumed run's controller model: what its file holds (the plans were made with it), else fitted again."""
    if not needs_slab(cfg):
        return None
    names = [t.name for t in tissue.scene.targets]
    data = sink.stored_controller_model(names) if hasattr(sink, "stored_controller_model") else None
    if data is not None and (data.needle is not None or not needs_needle_models(cfg)):
        return data
    with progress.reporting(progress.SilentReporter()):  # a detail of the resume, not news
        return refitted_model(cfg, tissue, sink.location, plans)


def robot_joint_check(cfg: Config):
    """The planner's hook: joint values of the puncture module for an insertion (docs/model.md §11)."""
    robot = RobotModel.from_config(cfg.robot)
    origin = np.asarray(cfg.robot.layer_origin_mm, float)
    yaw = float(np.deg2rad(cfg.robot.layer_yaw_deg))

    def check(entry: np.ndarray, direction: np.ndarray, target: np.ndarray):
        r = plan_to_joints(robot, target, direction, origin, yaw)
        return r.q, r.reachable, r.reason

    return check


def _clearance_text(clearance_mm: float) -> str:
    return "no obstacles" if np.isinf(clearance_mm) else f"clearance {clearance_mm:.2f} mm"


def _forward_figure_inputs(name, tissue, case, strokes, result, targets_now: dict) -> dict:
    """Keyword arguments of `output.figures.forward_case_figure` for one forward case."""
    mesh, scene = tissue.mesh, tissue.scene
    loop = boundary_loop(mesh)
    obstacles = embed_outlines(mesh, [o.outline for o in scene.obstacles])
    return dict(
        title=f"{name} — forward case {case}: "
        + ", ".join(f"{c.name} {s:+.1f} mm" for c, s in zip(scene.cups, strokes)),
        rest=mesh.nodes,
        deformed=result.x,
        triangles=mesh.triangles,
        outline_rest=mesh.nodes[loop],
        outline_deformed=result.x[loop],
        obstacles_rest=[(o.name, o.outline) for o in scene.obstacles],
        obstacles_deformed=deformed_outlines(obstacles, result.x),
        targets_rest={t.name: t.rest for t in scene.targets},
        targets_deformed=dict(targets_now),
        cup_nodes=list(tissue.cup_nodes),
        fixed_nodes=tissue.fixed_nodes,
    )
