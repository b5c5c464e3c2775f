"""`scissor simulate`: mesh a scene, solve its forward cases, write results.

The pipeline: config → scene → mesh → tissue → forward solves → results.h5
and one figure per case. Progress and messages go through a `Reporter` so
the CLI decides what a terminal shows.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

import h5py

from scissor_cli import control
from scissor_cli.output.manipulation import manipulation_figure_inputs
from scissor_cli.output import figures
from scissor_cli.output import results
from scissor_cli.config import Config, SolverConfig, parse_config, resolved_yaml
from scissor_cli.solvers.jacobian import cup_target_jacobian
from scissor_cli.mesh.probe import probe_targets, target_positions
from scissor_cli.solvers.equilibrium import EquilibriumSolver
from scissor_cli.mesh.outlines import boundary_loop, deformed_outlines, embed_outlines
from scissor_cli.planning.corridor import corridor_radius
from scissor_cli.planning.needle import NeedlePlan, plan_target
from scissor_cli.planning.states import StateCache
from scissor_cli.experiments.profiles import error_model
from scissor_cli.robot.chain import RobotModel
from scissor_cli.robot.registration import plan_to_joints
from scissor_cli.experiments.selection import select
from scissor_cli.experiments.study import rows_as_columns, run_study
from scissor_cli.experiments.trials import TargetTask, execute
from scissor_cli.solvers.common import SolveResult, SolverError
from scissor_cli.mechanics.tissue import Tissue, build_model  # noqa: F401 - build_model is part of this module's API


class Reporter(Protocol):
    def info(self, message: str) -> None: ...

    def progress(self, description: str, total: int) -> Callable[[int], None]: ...


class SilentReporter:
    def info(self, message: str) -> None:
        pass

    def progress(self, description: str, total: int) -> Callable[[int], None]:
        return lambda advance=1: None


@dataclass
class RunSummary:
    out_dir: Path
    results_path: Path
    n_elements: int
    forward: dict[str, SolveResult] = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)
    plans: list = field(default_factory=list)
    status: str = "complete"
    failure: str = ""


class TrialsFailed(RuntimeError):
    """Some trials crashed; the others are stored and `--resume` re-runs the crashed ones."""


@dataclass(frozen=True)
class Execution:
    """How trials run: worker processes, or a Dask cluster at `scheduler`."""

    jobs: int = 1
    executor: str = "local"  # "local" | "dask"
    scheduler: str | None = None


def run_simulation(cfg: Config, out_dir: Path, reporter: Reporter | None = None,
                   execution: Execution = Execution()) -> RunSummary:
    """Everything `scissor simulate` does for a validated config, into out_dir.

    Forward cases, the rest Jacobian and the needle plans always; with
    `cfg.trials.count` > 0 also the nominal manipulation of every target
    (Fig. 11) and the trials (Fig. 14). Raises SolverError or TrialsFailed
    after writing the partial file, marked failed.
    """
    reporter = reporter or SilentReporter()
    out_dir.mkdir(parents=True, exist_ok=True)
    selection = None
    if cfg.solver.accuracy_mm is not None:
        selection = select(cfg, cfg.solver.accuracy_mm, reporter.info)
        # the file records the config that ran; the budget stays in /selection
        cfg = selection.apply(cfg)
        cfg = cfg.model_copy(update={"solver": cfg.solver.model_copy(update={"accuracy_mm": None})})
    t_mesh = time.perf_counter()
    scene, mesh, tissue = build_model(cfg)
    angles = mesh.angles_deg()
    reporter.info(
        f"mesh: {mesh.n_elements} triangles, {mesh.n_nodes} nodes, min angle {angles.min():.1f}°, "
        f"edges {mesh.edge_lengths().min():.2f}–{mesh.edge_lengths().max():.2f} mm ({time.perf_counter() - t_mesh:.2f} s)"
    )
    summary = RunSummary(out_dir, out_dir / "results.h5", mesh.n_elements)
    with results.ResultsFile(summary.results_path, resolved_yaml(cfg), cfg.seed) as out:
        results.write_model(out, tissue, cfg.material)
        if selection is not None:
            results.write_selection(out, selection)
        _forward_stage(cfg, tissue, out, summary, reporter)
        probe = probe_targets(mesh, np.array([t.rest for t in scene.targets]).reshape(-1, 2))
        if len(scene.targets):
            J = cup_target_jacobian(tissue, tissue.rest, probe)
            for k, target in enumerate(scene.targets):
                results.write_jacobian(out, target.name, J[2 * k : 2 * k + 2], scene.cup_names)
        if cfg.study is not None:
            _study_stage(cfg, out, reporter)
        summary.plans = _plan_stage(cfg, tissue, out, reporter)
        if cfg.trials.count > 0:
            _manipulation_stage(cfg, tissue, summary.plans, out, reporter)
            tasks = trial_tasks(tissue, summary.plans)
            allocate_trial_arrays(out, cfg, tasks, summary.plans)
            _trial_stage(out, cfg, tasks, reporter, execution)
    return summary


def _study_stage(cfg: Config, out: results.ResultsFile, reporter: Reporter) -> None:
    t0 = time.perf_counter()
    study = run_study(cfg, reporter.info)
    seconds = time.perf_counter() - t0
    results.write_study(out, rows_as_columns(study.rows), study.reference, study.notes, seconds)
    out.flush()
    for note in study.notes:
        reporter.info(f"study: {note}")
    reporter.info(f"study: {len(study.rows)} combinations in {seconds:.1f} s (speed vs error: scissor report {out.path.parent})")


def trial_tasks(tissue: Tissue, plans: list[NeedlePlan]) -> list[TargetTask]:
    """Plain-data tasks of the targets that have a plan with a desired position."""
    tasks = []
    for index, (target, plan) in enumerate(zip(tissue.scene.targets, plans)):
        if plan.feasible:
            tasks.append(TargetTask(index, target.name, target.rest, np.asarray(plan.desired, float),
                                    np.asarray(plan.strokes, float), plan.side, np.asarray(plan.direction, float)))
    return tasks


def allocate_trial_arrays(out: results.ResultsFile, cfg: Config, tasks: list[TargetTask], plans: list[NeedlePlan]) -> None:
    em = error_model(cfg.trials)
    attrs = {"count": cfg.trials.count, "profile": cfg.trials.profile, "seed": cfg.seed,
             **{k: v for k, v in asdict(em).items() if k != "profile"}}
    results.allocate_trials(out, [p.target for p in plans], cfg.trials.count, attrs)
    planned = {t.name for t in tasks}
    for plan in plans:  # a target without a plan has nothing to manipulate towards
        if plan.target not in planned:
            g = f"trials/{plan.target}"
            out.h5[f"{g}/done"][:] = True
            out.h5[f"{g}/stop_reason"][:] = "no_plan"
            out.h5[f"{g}/message"][:] = f"no plan: {plan.reason}"


def _manipulation_stage(cfg: Config, tissue: Tissue, plans: list[NeedlePlan], out: results.ResultsFile,
                        reporter: Reporter) -> None:
    """The nominal manipulation of each planned target (truth = model, exact camera): Fig. 11.

    The open-loop baseline (one Jacobian step from rest) is stored beside it.
    """
    radius = corridor_radius(cfg.needle)
    for target, plan in zip(tissue.scene.targets, plans):
        if not plan.feasible:
            continue
        corridor = control.Corridor.from_plan(plan, radius)
        kw = dict(corridor=corridor, target=target.name)
        closed = control.run_target(tissue, target.rest, plan.desired, cfg.controller, **kw)
        opened = control.run_target(tissue, target.rest, plan.desired, cfg.controller, mode="open", **kw)
        g = out.group(f"manipulation/{target.name}")
        g.attrs.update({
            "closed_final_error": closed.final_error, "closed_iterations": closed.iterations,
            "closed_stop_reason": closed.stop_reason, "closed_corridor_clear": bool(closed.corridor_clear),
            "closed_clearance_mm": closed.clearance_mm, "open_final_error": opened.final_error,
            "uncorrectable_mm": closed.uncorrectable_error_mm, "units": "mm",
        })
        names, table = closed.history_table()
        out.dataset(f"manipulation/{target.name}/history", table, "mm (time_s: s)", columns=names)
        fig = figures.manipulation_figure(**manipulation_figure_inputs(tissue, closed, target.rest, corridor))
        figures.save(fig, out.path.parent / f"manipulation_{target.name}.png")
        reporter.info(
            f"manipulation {target.name}: closed loop {closed.iterations} iterations ({closed.stop_reason}), "
            f"error {np.linalg.norm(closed.final_error):.3f} mm vs open loop {np.linalg.norm(opened.final_error):.3f} mm, "
            f"corridor {'clear' if closed.corridor_clear else 'BLOCKED'}"
        )


def _trial_stage(out: results.ResultsFile, cfg: Config, tasks: list[TargetTask], reporter: Reporter,
                 execution: Execution) -> None:
    """Run every pending trial of the file and store each as it finishes."""
    pending = results.pending_trials(out.h5)
    by_name = {t.name: t for t in tasks}
    work = [(by_name[name], int(k)) for name, ks in pending.items() if name in by_name for k in ks]
    if work:
        reporter.info(f"trials: {len(work)} to run ({cfg.trials.profile} profile, {execution.jobs} job(s), "
                      f"{execution.executor} executor)")
    advance = reporter.progress("trials", len(work))
    t0, failed = time.perf_counter(), 0
    config_yaml = out.h5.attrs["config_yaml"]
    for outcome in execute(config_yaml, work, execution.jobs, execution.executor, execution.scheduler):
        results.write_trial(out, tasks_by_index(tasks)[outcome.target_index].name, outcome)
        out.flush()
        failed += not outcome.ok
        advance(1)
    if work:
        reporter.info(f"trials done in {time.perf_counter() - t0:.1f} s")
    write_trial_figures(out.h5, out.path.parent, cfg.name)
    if failed:
        raise TrialsFailed(f"{failed} trial(s) crashed (see /trials/<target>/message); re-run them with --resume")


def tasks_by_index(tasks: list[TargetTask]) -> dict[int, TargetTask]:
    return {t.index: t for t in tasks}


def write_trial_figures(h5, out_dir: Path, name: str) -> list[Path]:
    """Fig. 14 box plots of the x and y error per target, and the iterations histogram."""
    errors = {t: g["final_error"][:][g["done"][:] & ~g["failed"][:]] for t, g in h5["trials"].items()}
    errors = {t: e[np.isfinite(e).all(axis=1)] for t, e in errors.items()}
    errors = {t: e for t, e in errors.items() if len(e)}
    if not errors:
        return []
    profile = h5["trials"].attrs.get("profile", "")
    paths = [figures.save(figures.error_boxplots([(f"{name} ({profile})", errors)]), out_dir / "trials_error_boxplot.png")]
    iterations = {t: g["iterations"][:][g["iterations"][:] >= 0] for t, g in h5["trials"].items()}
    paths.append(figures.save(figures.iterations_histogram(iterations, f"{name}: control iterations per trial"),
                              out_dir / "trials_iterations.png"))
    return paths


def resume_simulation(run_dir: Path, reporter: Reporter | None = None, execution: Execution = Execution()) -> int:
    """Finish the trials of an interrupted or partly failed run in place; returns how many ran."""
    reporter = reporter or SilentReporter()
    path = run_dir / "results.h5"
    with h5py.File(path, "r") as h5:
        config_yaml = h5.attrs["config_yaml"]
        if "trials" not in h5 or "plan" not in h5:
            raise ResumeError(f"{path}: nothing to resume: the run stopped before its trials; run simulate again")
        plans = {name: dict(g.attrs) for name, g in h5["plan"].items()}
        todo = sum(len(v) for v in results.pending_trials(h5).values())
    cfg = parse_config(config_yaml, str(path))
    scene, mesh, tissue = build_model(cfg)
    tasks = []
    for index, target in enumerate(scene.targets):
        p = plans.get(target.name)
        if p is not None and bool(p["feasible"]):
            tasks.append(TargetTask(index, target.name, target.rest, np.asarray(p["desired"]),
                                    np.asarray(p["strokes"]), str(p["side"]), np.asarray(p["direction"])))
    out = results.reopen(path)
    with out:
        _trial_stage(out, cfg, tasks, reporter, execution)
    return todo


class ResumeError(ValueError):
    """The run directory cannot be resumed."""


def _forward_stage(cfg: Config, tissue: Tissue, out: results.ResultsFile, summary: RunSummary, reporter: Reporter) -> None:
    scene, mesh = tissue.scene, tissue.mesh
    probe = probe_targets(mesh, np.array([t.rest for t in scene.targets]).reshape(-1, 2))
    solver = EquilibriumSolver.from_config(tissue, cfg.solver)
    advance = reporter.progress("forward cases", len(cfg.forward))
    for case in cfg.forward:
        strokes = scene.strokes_vector(case.strokes)
        try:
            result = solver.solve_case(strokes)
        except SolverError as exc:
            summary.status, summary.failure = "failed", f"forward case {case.name!r}: {exc}"
            raise SolverError(summary.failure, exc.result) from None
        summary.forward[case.name] = result
        targets_now = target_positions(probe, result.x)
        results.write_forward(
            out, case.name, {c.name: float(s) for c, s in zip(scene.cups, strokes)}, result, mesh.nodes,
            {t.name: p for t, p in zip(scene.targets, targets_now)},
        )
        out.flush()
        note = "" if result.message.startswith("converged") else f" ({result.message})"
        reporter.info(
            f"forward {case.name}: {result.solver} {result.iterations} iterations, "
            f"residual {result.residual:.2e}, {result.time_s * 1e3:.1f} ms{note}"
        )
        summary.figures.append(_forward_figure(out.path.parent, cfg.name, tissue, case.name, strokes, result, targets_now))
        advance(1)


def _plan_stage(cfg: Config, tissue: Tissue, out: results.ResultsFile, reporter: Reporter) -> list[NeedlePlan]:
    """Plan every target's insertion; the plan's desired position becomes the target's."""
    scene = tissue.scene
    robot_check = robot_joint_check(cfg)
    plans = []
    cache = StateCache(tissue)
    advance = reporter.progress("needle plans", len(scene.targets))
    for target in scene.targets:
        plan = plan_target(tissue, scene, target, cfg.needle, robot_check=robot_check, cache=cache)
        plans.append(plan)
        source = "config" if target.desired is not None else "planner"
        results.write_target(out, target.name, target.rest, plan.desired, source)
        results.write_plan(out, plan, plan.robot_note, plan.robot_ok)
        out.flush()
        how = (f"strokes {_fmt(plan.strokes)} mm" if plan.manipulated else "no manipulation needed")
        if plan.feasible and not plan.robot_ok:
            how += f"; ROBOT: {plan.robot_note}"
        reporter.info(
            f"plan {target.name}: " + (f"{plan.side} entry, {_clearance_text(plan.clearance_mm)}, {how} ({plan.time_s:.1f} s)"
                                       if plan.feasible else f"infeasible: {plan.reason}")
        )
        advance(1)
    return plans


def robot_joint_check(cfg: Config):
    """The planner's hook: joint values of the puncture module for an insertion (MODEL.md §11)."""
    robot = RobotModel.from_config(cfg.robot)
    origin = np.asarray(cfg.robot.layer_origin_mm, float)
    yaw = float(np.deg2rad(cfg.robot.layer_yaw_deg))

    def check(entry: np.ndarray, direction: np.ndarray, target: np.ndarray):
        r = plan_to_joints(robot, target, direction, origin, yaw)
        return r.q, r.reachable, r.reason

    return check


def _clearance_text(clearance_mm: float) -> str:
    return "no obstacles" if np.isinf(clearance_mm) else f"clearance {clearance_mm:.2f} mm"


def _fmt(values) -> str:
    return ", ".join(f"{v:+.2f}" for v in np.atleast_1d(values))


def _forward_figure(out_dir, name, tissue, case, strokes, result, targets_now) -> Path:
    mesh, scene = tissue.mesh, tissue.scene
    loop = boundary_loop(mesh)
    obstacles = embed_outlines(mesh, [o.outline for o in scene.obstacles])
    fig = figures.forward_case_figure(
        title=f"{name} — forward case {case}: " + ", ".join(f"{c.name} {s:+.1f} mm" for c, s in zip(scene.cups, strokes)),
        rest=mesh.nodes,
        deformed=result.x,
        triangles=mesh.triangles,
        outline_rest=mesh.nodes[loop],
        outline_deformed=result.x[loop],
        obstacles_rest=[(o.name, o.outline) for o in scene.obstacles],
        obstacles_deformed=deformed_outlines(obstacles, result.x),
        targets_rest={t.name: t.rest for t in scene.targets},
        targets_deformed={t.name: p for t, p in zip(scene.targets, targets_now)},
        cup_nodes=list(tissue.cup_nodes),
        fixed_nodes=tissue.fixed_nodes,
    )
    return figures.save(fig, out_dir / f"forward_{case}.png")

