"""A 3-D scene's plans, nominal manipulations and trials (docs/model.md §19, "Plan", "Control", "Trials").

After the forward cases and the Jacobian (`experiments.body_run`):

* **plans**: every lesion's straight needle (`planning.body_plan`), the
  stroke search solving the body with warm starts, the robot's inverse
  kinematics on the body registered in its base frame;
* with trials, each planned lesion's **nominal manipulation**: the closed
  loop and the open-loop baseline on the body itself (the configured mesh;
  the controller's model the body at `controller.mesh_scale` or, with
  `layer`, the lesion's section), seen by the scene's
  camera(s) without error (one camera still does not see its depth);
* with `insertion`, every planned lesion's **nominal insertion** under
  every strategy (`body_insertion`);
* the **trials**: the profile's draws against the body
  (`experiments.body_trials`), run and stored as a layer's are.

Each product goes to the sink and is marked finished for `--resume`.
"""

from __future__ import annotations

import numpy as np

from scissor_cli import control, progress
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.experiments.body_imaging_stage import body_imaging_record
from scissor_cli.experiments.body_insertion import body_insertion_stage, body_needle_models, store_insertion
from scissor_cli.experiments.body_surrogate import body_surrogate_data
from scissor_cli.experiments.body_trials import (
    BodyTruth,
    body_sensor_model,
    loop_tolerances,
    model_controllers,
    nominal_manipulation,
)
from scissor_cli.experiments.error_budget import run_budget
from scissor_cli.experiments.insertion_stage import to_insert
from scissor_cli.experiments.profiles import CAMERA_SPREADS, IMAGING_SPREADS, INSERTION_SPREADS, error_model
from scissor_cli.experiments.run_cache import cache_dir
from scissor_cli.experiments.sink import Manipulation, RunSink, product_key
from scissor_cli.experiments.trial_stage import Execution, run_trial_stage
from scissor_cli.experiments.trial_types import NominalInsertion, NominalOutcome, TargetTask, law_attrs
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.planning.body_plan import BodyNeedlePlan, body_robot_check, plan_body_targets, stored_body_plan
from scissor_cli.robot.chain import RobotModel
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.tracking import TrackedEquilibrium


def body_loop_stages(cfg: BodyConfig, tissue: Tissue, sink: RunSink, summary, done: frozenset[str],
                     execution: Execution) -> None:
    """Plans; with trials, the nominal manipulations and the trials."""
    plans = _stored(sink, tissue.scene) if "plan" in done else None
    if plans is None:
        plans = _plan_stage(cfg, tissue, sink)
        sink.mark_finished("plan")
    summary.plans = plans
    truth = BodyTruth(cfg, tissue) if cfg.trials.count or cfg.insertion is not None else None
    needle, starts = {}, {}
    if cfg.insertion is not None and "loop" in cfg.insertion.strategies:
        # the controller's own body (its equilibria at the plans the insertion stage's too when it is the truth's)
        needle = body_needle_models(cfg, tissue, plans, cache_dir(sink.location),
                                    starts if tissue is truth.tissue else {})
    # With several local workers and trials, the nominal insertions and manipulations run in the trials' pool,
    # beside the trials (the run's own process would run them alone first, one core idle); with imaging their
    # frames are kept here, so not there.
    beside = (execution.executor == "local" and execution.jobs > 1 and cfg.imaging is None
              and cfg.trials.count > 0)
    if cfg.insertion is not None and not beside:
        summary.figures += body_insertion_stage(cfg, truth.tissue, plans, sink, done, needle, starts)
    if cfg.trials.count == 0:
        return
    model_data = None
    if cfg.controller.model == "surrogate":
        model_data = body_surrogate_data(cfg, tissue, cache_dir(sink.location))
    tasks = body_tasks(tissue, plans, model_data, needle)
    nominal = []
    if beside:
        if cfg.insertion is not None:  # the longest first; the truth's start where the run has solved it
            inserting = {target.name for target, _ in to_insert(truth.tissue.scene.targets, plans, done)}
            nominal += [(t, NominalInsertion(starts.get(t.name) if truth.tissue is tissue else None))
                        for t in tasks if t.name in inserting]
        nominal += [(t, None) for t in tasks if product_key("manipulation", t.name) not in done]
    else:
        summary.figures += _manipulation_stage(cfg, tissue, truth, plans, sink, done, model_data)
    if "trials" not in done:
        em = error_model(cfg.trials)
        other_sensor = IMAGING_SPREADS if cfg.imaging is None else CAMERA_SPREADS  # the sensor not used
        skipped = other_sensor + (INSERTION_SPREADS if cfg.insertion is None else ())
        attrs = {"count": cfg.trials.count, "profile": cfg.trials.profile, "seed": cfg.seed,
                 **law_attrs(cfg.controller),
                 **({"sensor": "camera", "cameras": len(cfg.cameras) if cfg.cameras else 1} if cfg.imaging is None
                    else {"sensor": "ultrasound"}), "controller_model": cfg.controller.model,
                 **({} if model_data is None else {"surrogate_error_mm": model_data.validation_error_mm}),
                 **{k: getattr(em, k) for k in em.__dataclass_fields__
                    if k not in ("profile",) + skipped},
                 **({} if cfg.insertion is None else {"insertion_strategies": list(cfg.insertion.strategies)})}
        planned = {t.name for t in tasks}
        sink.allocate_trials([p.target for p in plans], cfg.trials.count, attrs,
                             {p.target: p.reason for p in plans if p.target not in planned}, dim=3)
        sink.mark_finished("trials")
    summary.trials_run = run_trial_stage(sink, cfg, tasks, execution, nominal,
                                         lambda o: _store_nominal(tissue, truth, plans, sink, summary, o, needle))
    if cfg.trials.budget:  # the trials again with one source at a time, the body's own too (docs/model.md §20)
        summary.figures += run_budget(cfg, tasks, sink, execution, done)


def _plan_stage(cfg: BodyConfig, tissue: Tissue, sink: RunSink) -> list[BodyNeedlePlan]:
    plans = body_plans(cfg, tissue)
    for plan in plans:
        sink.body_plan(plan)
        where = (f"entry {np.round(plan.entry, 1).tolist()} along {np.round(plan.direction, 3).tolist()}, "
                 f"depth {plan.depth_mm:.1f} mm, " + ("no obstacles" if np.isinf(plan.clearance_mm) else
                                                      f"clearance {plan.clearance_mm:.2f} mm")
                 + (f", strokes {np.round(plan.strokes, 2).tolist()} mm" if np.any(plan.strokes) else ""))
        progress.info(f"plan {plan.target}: " + (where if plan.feasible else f"none: {plan.reason}")
                      + ("" if plan.robot_ok or not plan.feasible else f"; ROBOT: {plan.robot_note}"))
    return plans


def body_tasks(tissue: Tissue, plans: list[BodyNeedlePlan], model_data=None,
               needle: dict | None = None) -> list[TargetTask]:
    """Plain-data tasks of the lesions with a feasible plan (and the controller's model's data, if any; needle:
    {lesion: its NeedleModel} for `loop`)."""
    return [TargetTask(k, p.target, tissue.scene.targets[k].rest, np.asarray(p.desired, float),
                       np.asarray(p.strokes, float), "", np.asarray(p.direction, float),
                       np.asarray(p.entry, float), float(p.depth_mm), controller_model=model_data,
                       needle_model=(needle or {}).get(p.target))
            for k, p in enumerate(plans) if p.feasible]


def body_plans(cfg: BodyConfig, tissue: Tissue) -> list[BodyNeedlePlan]:
    """Every lesion's straight needle and strokes on the body (docs/model.md §19, "Plan"), in the scene's order."""
    robot = RobotModel.from_config(cfg.robot)
    check = body_robot_check(robot, np.asarray(cfg.robot.layer_origin_mm, float),
                             float(np.deg2rad(cfg.robot.layer_yaw_deg)))
    tracker = TrackedEquilibrium(tissue, 1e-8)

    def solve(strokes: np.ndarray) -> np.ndarray:
        # The search asks for states, not for ∂x/∂s: no factorisation at each state for it. Its samples jump
        # between strokes of opposite sign (`body_plan.stroke_grid`'s order), so each solved state is kept as a
        # start for a later sample nearer to it than the tracker's last (`TrackedEquilibrium.move_to`'s fallback).
        strokes = np.asarray(strokes, float)
        tracker.move_to(strokes, tangent=False)
        tracker.guesses.append((strokes.copy(), tracker.x))
        return tracker.x.copy()

    return plan_body_targets(tissue, tissue.scene, cfg.needle, robot_check=check, solve=solve)


def _manipulation_stage(cfg: BodyConfig, tissue: Tissue, truth: BodyTruth, plans: list, sink: RunSink,
                        done: frozenset[str], model_data=None) -> list:
    """Each planned lesion's closed loop and open-loop baseline on the body itself, seen without error."""
    sensors = body_sensor_model(cfg, error_model(cfg.trials), truth.tissue.mesh)
    controllers = model_controllers(cfg, model_data)
    paths = []
    for k, (plan, target) in enumerate(zip(plans, tissue.scene.targets)):
        if not plan.feasible or product_key("manipulation", target.name) in done:
            continue
        desired = np.asarray(plan.desired, float)
        imaging = cfg.imaging is not None  # the closed loop's frames kept: /imaging and the B-mode figure
        sensor = sensors.nominal(desired, k, cfg.seed, record=True) if imaging else sensors.nominal(desired, k,
                                                                                                    cfg.seed)
        run = control.TargetRun(sensor=sensor, target=target.name,
                                direction=np.asarray(plan.direction, float), controller_factory=controllers(k),
                                truth_factory=truth.factory(target.rest), **loop_tolerances(cfg.controller))
        closed, opened = nominal_manipulation(tissue, target.rest, desired, cfg.controller, run)
        paths += _stored_manipulation(truth, plan, target.rest, closed, opened, sink)
        if imaging and hasattr(sink, "imaging"):
            paths += sink.imaging(body_imaging_record(cfg.imaging, target.name, plan, closed, sensor), truth.tissue,
                                  [])
    return paths


def _store_nominal(tissue: Tissue, truth: BodyTruth, plans: list, sink: RunSink, summary,
                   outcome: NominalOutcome, needle: dict) -> None:
    """A nominal manipulation or a lesion's nominal insertions a trials' worker ran (`run_trial_stage`), stored as
    `_manipulation_stage` and `body_insertion_stage` store their own; a failure fails the run, as there.
    needle: {lesion: the NeedleModel `loop` steered with}."""
    target = tissue.scene.targets[outcome.target_index]
    if outcome.error:
        raise SolverError(f"the nominal {outcome.what} of {target.name}: {outcome.error}")
    plan = plans[outcome.target_index]
    if outcome.what == "insertion":
        lesion = truth.tissue.scene.targets[outcome.target_index]  # (its rest on the truth's mesh)
        summary.figures += store_insertion(sink, truth.tissue, lesion, plan, outcome.insertion,
                                           needle.get(lesion.name))
        return
    summary.figures += _stored_manipulation(truth, plan, target.rest, outcome.closed, outcome.opened, sink)


def _stored_manipulation(truth: BodyTruth, plan, rest: np.ndarray, closed, opened, sink: RunSink) -> list:
    """Store a lesion's closed loop and open-loop baseline (/manipulation), mark it finished, say so; its figures."""
    for r in (closed, opened):  # the plan's needle, for the figure (no corridor is checked in a body yet)
        r.corridor_direction = np.asarray(plan.direction, float)
        r.corridor_entry = np.asarray(plan.entry, float)
    target = closed.target
    # drawn on the truth's mesh: the nodes the loop ends with are its
    out = sink.manipulation(Manipulation(target, closed, opened, truth.tissue, rest, None))
    sink.mark_finished(product_key("manipulation", target))
    true_miss = float(np.linalg.norm((np.eye(3) - np.outer(plan.direction, plan.direction)) @ closed.final_error))
    progress.info(f"manipulation {target}: closed loop {closed.iterations} iterations ({closed.stop_reason}),"
                  f" true miss across the needle {true_miss:.3f} mm vs open loop {opened.miss_mm:.3f} mm")
    return [p for p in np.atleast_1d(out) if p is not None]


def _stored(sink: RunSink, scene) -> list | None:
    """The plans a resumed run stored, in the scene's order of its lesions."""
    stored = sink.plans()
    if stored is None:
        return None
    return [stored_body_plan(t.name, stored[t.name], bool(scene.obstacles)) for t in scene.targets]

