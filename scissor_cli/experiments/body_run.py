"""`scissor simulate` on a 3-D scene: the body meshed, solved over its forward cases, its Jacobian (docs/model.md §19).

The stages of a 2-D run that a body has today: the model (the mesh, its
regions and materials), every forward case (Newton on the 3-D tissue with
its kept factor, `solvers.equilibrium`), each lesion's position under it,
and the cups-to-lesions Jacobian at rest (3 × cups per lesion). With
`tissue.accuracy_mm` the model's mesh (and with `element: auto` the
element) is picked first (`body_resolution`; the run's body is meshed at
`controller.mesh_scale`, the trials' truth at the configured mesh). Each
product goes to the run's sink as a 2-D run's does, and is marked finished
for `--resume`.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from scissor_cli import progress
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.config.loading import resolved_yaml
from scissor_cli.experiments.body_resolution import BodyChoice, resolved_by_accuracy
from scissor_cli.experiments.build import body_model, with_grips
from scissor_cli.experiments.forward_stage import forward_stage
from scissor_cli.experiments.run_cache import cache_dir
from scissor_cli.experiments.run_summary import RunSummary
from scissor_cli.experiments.sink import RunSink, SinkFactory
from scissor_cli.experiments.trial_stage import Execution
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.planning.body_grips import BodyGripPlan, plan_body_grips, verify
from scissor_cli.solvers.jacobian import cup_target_jacobian
from scissor_cli.text import signed


def run_body_simulation(cfg: BodyConfig, run: SinkFactory, execution: Execution) -> RunSummary:
    """Everything `scissor simulate` does for a 3-D scene, into the sink `run` opens; returns the run's summary."""
    cache = cache_dir(run.location)
    cfg, choice = resolved_by_accuracy(cfg, cache)
    if choice is not None:
        progress.info(f"mesh by accuracy: {choice.explain()}")
    grips = None
    if cfg.manipulation_points is not None:
        cfg, grips = body_grip_stage(cfg, cache)
    tissue = _build(cfg, cache)
    summary = RunSummary(run.location, tissue.mesh.n_elements)
    with run.open(resolved_yaml(cfg), cfg.seed) as sink:
        if grips is not None:
            summary.figures.append(sink.manipulation_points(grips, tissue))
        body_stages(cfg, tissue, sink, summary, choice=choice, execution=execution)
    return summary


def body_grip_stage(cfg: BodyConfig, cache: Path | None) -> tuple[BodyConfig, BodyGripPlan]:
    """Choose where the first `manipulation_points.cups` cups grip the skin (docs/model.md §20); the run goes on
    with them. The config the run records has the chosen contacts and axes and no `manipulation_points`, so
    trials and `--resume` rebuild the body that ran; the search is in /manipulation_points."""
    mp = cfg.manipulation_points
    _, _, tissue = body_model(cfg, cache, scale=cfg.controller.mesh_scale)
    limit = min(min(-c.stroke_mm[0], c.stroke_mm[1]) for c in cfg.cups[:mp.cups])
    plan = plan_body_grips(tissue, mp.skin.center_mm, mp.skin.radius_mm, mp.spacing_mm, mp.cups,
                           cfg.needle.direction, cfg.cups[0].radius_mm, limit)
    placed = with_grips(cfg, plan.contacts, plan.axes).model_copy(update={"manipulation_points": None})
    verify(plan, lambda contacts, axes: body_model(placed, cache, scale=cfg.controller.mesh_scale)[2],
           np.array([c.stroke_mm for c in placed.cups[:mp.cups]], float))
    where = "; ".join(f"{c.name} at {signed(p)} mm pushing {signed(a)}" for c, p, a in
                      zip(placed.cups, plan.contacts, plan.axes))
    progress.info(f"manipulation points: {len(plan.candidates)} candidates on the skin ranked in "
                  f"{plan.search_s:.2f} s for {plan.controls}, verified in {plan.verify_s:.2f} s: {where}")
    return placed, plan


def _build(cfg: BodyConfig, cache: Path | None) -> Tissue:
    t0 = time.perf_counter()
    _, mesh, tissue = body_model(cfg, cache, scale=cfg.controller.mesh_scale)
    progress.info(f"mesh: {mesh.n_elements} tetrahedra, {mesh.n_nodes} nodes, min dihedral "
                  f"{mesh.min_dihedral_deg:.1f}°, regions {', '.join(mesh.region_names)} "
                  f"({time.perf_counter() - t0:.2f} s)")
    return tissue


def body_stages(cfg: BodyConfig, tissue: Tissue, sink: RunSink, summary, done: frozenset[str] = frozenset(),
                choice: BodyChoice | None = None, execution: Execution | None = None) -> None:
    """The stages after the body is built: model, forward cases, targets, Jacobian at rest; the plans, and with
    trials the nominal manipulation of each planned lesion and the trials (`body_closed_loop`)."""
    scene = tissue.scene
    if "model" not in done:
        sink.model(tissue)
        if choice is not None:
            sink.body_resolution(choice)
        for t in scene.targets:
            sink.target(t.name, t.rest, t.rest if t.desired is None else t.desired,
                        "rest" if t.desired is None else "config")
        sink.mark_finished("model")
    probe = tissue.probe(np.array([t.rest for t in scene.targets]).reshape(-1, 3))
    forward_stage(cfg.forward, cfg.solver, tissue, probe, sink, summary,
                  lambda case, strokes, result, targets: dict(
                      title=f"{cfg.name}: forward case {case}", tissue=tissue, x=result.x,
                      strokes=dict(zip(scene.cup_names, strokes)), targets=targets,
                      needle_direction=np.asarray(cfg.needle.direction, float)),
                  kind="body", done=done)
    if len(scene.targets) and "jacobian" not in done:
        J = cup_target_jacobian(tissue, tissue.rest, probe)
        for k, target in enumerate(scene.targets):
            sink.jacobian(target.name, J[3 * k:3 * k + 3], scene.cup_names)
        sink.mark_finished("jacobian")
    if scene.targets:
        from scissor_cli.experiments.body_closed_loop import body_loop_stages  # noqa: PLC0415

        body_loop_stages(cfg, tissue, sink, summary, done, execution or Execution())


def resume_body(cfg: BodyConfig, sink, done: frozenset[str], execution: Execution | None = None) -> int:
    """`--resume` of a 3-D run: the stages not marked finished, into its sink (the config it recorded has the mesh
    that ran: its accuracy choice already applied). Returns how many trials ran."""
    tissue = _build(cfg, cache_dir(sink.location))
    if done:
        progress.info(f"resume: {len(done)} finished stage product(s) kept")
    summary = RunSummary(sink.location, tissue.mesh.n_elements)
    body_stages(cfg, tissue, sink, summary, done=done, execution=execution)
    return summary.trials_run
