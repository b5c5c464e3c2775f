"""Time per control iteration of the closed loop (docs/model.md §6) on a scene's full mesh.

One iteration = actuate and solve the truth (warm-started) + solve the
controller's model at the command (warm-started) + update J there. Three
measurements, each the median over iterations (time.perf_counter):

* corrective steps: both tissues at an operating stroke, then small moves
  (a few tenths of a mm, with reversals) as in the loop's later iterations,
  truth ≠ model (E ×1.3, fibers +10°); the step of the law
  (`control.allocation.stroke_step`, the miss across +x) is included;
  with the scene's cups and, for the table, with configs/example.yaml (one
  cup) and configs/two_cups.yaml (two);
* the manipulation-point search (`planning.manipulation_points`): the
  candidates on the top, left and right sides every 2 mm, the adjoint
  responses and the ranking (without the verifying solves, timed apart);
* the same with truth = model (one solve serves both);
* real closed loops over the scene's targets: ideal, and trials with
  camera noise, localisation bias, backlash and a mismatched truth; the
  first iteration (the big move from rest) is reported apart.

    python benchmarks/bench_control.py [CONFIG.yaml] [--repeats N]
    python benchmarks/bench_control.py --table      # the goal table of docs/performance.md
    python benchmarks/bench_control.py configs/example_full.yaml --models
        # the controller's side of an iteration with each controller.model (docs/model.md §15):
        # the model moved to the command, its J, the law's step; and each model's build time
        # (the surrogate's from runs/.scissor-cache when it is there, else trained and cached)

The machine has 2 cores and other work may share them: the numbers are
wall-clock medians, not CPU time.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli import control as ct  # noqa: E402
from scissor_cli.config import ManipulationPointsConfig, load_config  # noqa: E402
from scissor_cli.control.allocation import stroke_step  # noqa: E402
from scissor_cli.experiments.build import build_model, with_grips  # noqa: E402
from scissor_cli.mesh.probe import probe_targets  # noqa: E402
from scissor_cli.planning.corridor import corridor_radius  # noqa: E402
from scissor_cli.planning.manipulation_points import plan_grips  # noqa: E402
from scissor_cli.planning.needle_plan import plan_targets  # noqa: E402
from scissor_cli.planning.states import StateCache  # noqa: E402
from scissor_cli.sensing.camera import Camera, CameraSensor  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def corrective_steps(model, truth_tissue, target, operating_mm: float, n: int,
                     counts: dict | None = None) -> np.ndarray:
    """Wall time (n,) s of n small control iterations around operating_mm (every cup).

    `counts`, if given, receives the trackers' work per iteration: Newton/chord
    steps and factorisations of the truth and of the model.
    """
    probe = probe_targets(model.mesh, target.rest[None])
    act = ct.Actuator.from_scene(model.scene)
    plant = ct.Plant(truth_tissue, act, probe)
    ctrl = ct.Controller(model, probe, act.lo, act.hi)
    shared = ctrl.shares(plant)
    if shared:
        plant.eq.adopt(ctrl.eq)
    C = model.n_cups
    s = np.full(C, operating_mm)
    plant.apply(s, tangent=shared)
    ctrl.update(s, plant)
    rng = np.random.default_rng(0)
    axis, desired = np.array([1.0, 0.0]), plant.position + [0.3, 0.2]
    times = []
    before = {who: dict(eq.stats) for who, eq in (("truth", plant.eq), ("model", ctrl.eq))}
    for _ in range(n):
        t0 = time.perf_counter()
        stroke_step(ctrl.jacobian, desired - plant.position, s, act.lo, act.hi, act.speed_mm_per_s * 0.1, axis)
        s = np.clip(s + rng.choice([-1, 1], C) * rng.uniform(0.02, 0.5, C), act.lo, act.hi)
        plant.apply(s, tangent=shared)
        ctrl.update(s, plant)
        times.append(time.perf_counter() - t0)
    if counts is not None:
        for who, eq in (("truth", plant.eq), ("model", ctrl.eq)):
            for key in ("newton_iterations", "refactors"):
                counts[f"{who} {key}"] = (eq.stats[key] - before[who][key]) / n
    return np.array(times)


def grip_search(path: Path, repeats: int = 3) -> tuple[float, float, int]:
    """(median search s, verification s, candidates) of the manipulation-point plan on a scene."""
    cfg = load_config(path)
    cfg = cfg.model_copy(update={"manipulation_points": ManipulationPointsConfig(
        sides=["top", "left", "right"], spacing_mm=2.0, cups=1)})
    _, _, model = build_model(cfg)
    search, verify, n = [], [], 0
    for _ in range(repeats):
        plan = plan_grips(cfg.manipulation_points, cfg.needle, model,
                          lambda contacts, axes: build_model(with_grips(cfg, contacts, axes))[2])
        search.append(plan.search_s)
        verify.append(plan.verify_s)
        n = len(plan.candidates)
    return float(np.median(search)), float(np.median(verify)), n


def table(repeats: int, res: results_io.Results) -> None:
    """The goals of docs/model.md §6 and §7 on the example scene with one and with two cups."""
    print("| measurement | scene | median | goal |")
    print("|---|---|---|---|")
    work, rows = [], []
    for name in ("example", "two_cups"):
        cfg = load_config(ROOT / "configs" / f"{name}.yaml")
        scene, _, model = build_model(cfg)
        truth = model.with_material(1.3, fiber_angle_rad=scene.material.fiber_angle_rad + np.deg2rad(10))
        operating = 0.6 * scene.cups[0].stroke_max_mm
        corrective_steps(model, truth, scene.targets[0], operating, 3)
        counts = {}
        t = corrective_steps(model, truth, scene.targets[0], operating, repeats, counts)
        print(f"| corrective control iteration, truth != model | {name} ({model.n_cups} cup(s)) | "
              f"{np.median(t) * 1e3:.1f} ms | <= 10 ms |")
        rows.append({"scene": name, "cups": model.n_cups, "iteration_ms": np.median(t) * 1e3,
                     "truth_steps": counts["truth newton_iterations"], "model_steps": counts["model newton_iterations"],
                     "truth_factorisations": counts["truth refactors"],
                     "model_factorisations": counts["model refactors"]})
        work.append(f"{name}: steps truth {counts['truth newton_iterations']:.2f} + model "
                    f"{counts['model newton_iterations']:.2f}, factorisations truth {counts['truth refactors']:.2f} "
                    f"+ model {counts['model refactors']:.2f} per iteration")
    search, verify, n = grip_search(ROOT / "configs" / "example.yaml")
    print(f"| manipulation-point search, {n} candidates (adjoint + ranking) | example | {search * 1e3:.0f} ms | "
          "<= 500 ms |")
    print(f"| its verification (3 re-meshed full solves) | example | {verify * 1e3:.0f} ms | - |")
    res.table("corrective_iteration", rows, {"iteration_ms": "ms", "truth_steps": "per iteration",
                                             "model_steps": "per iteration", "truth_factorisations": "per iteration",
                                             "model_factorisations": "per iteration"})
    res.figure("grip_search_ms", search * 1e3, "ms", candidates=n, goal="<= 500 ms")
    res.figure("grip_verify_ms", verify * 1e3, "ms")
    res.figure("grip_candidates", n, "candidates")
    print("\n".join(["", "work per corrective iteration (the steadier evidence on a shared machine):"] + work))


def loop_steps(cfg, model, plans, trials: int, cache=None) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """(first-iteration times, later-iteration times, iterations per run) over closed loops.

    With the planner's `cache`, each loop starts its big moves from the
    model's state at the plan's strokes.
    """
    cam = Camera.from_config(cfg.camera)
    rng = np.random.default_rng(cfg.seed)
    first, later, iterations = [], [], []
    for target, plan in zip(model.scene.targets, plans):
        cases = [dict()]
        for _ in range(trials):
            cases.append(dict(
                truth=ct.TruthPerturbation(E_scale=float(rng.uniform(0.8, 1.2)),
                                           fiber_offset_rad=float(np.deg2rad(rng.normal(0, 5)))),
                sensor=CameraSensor(cam, tuple(rng.normal(0, 0.2, 2)),
                                    rng=np.random.default_rng(int(rng.integers(1 << 31)))),
                backlash_mm=0.1,
            ))
        corridor = ct.Corridor.from_plan(plan, corridor_radius(cfg.needle))
        guess = None if cache is None else (plan.strokes, cache.state(plan.strokes))
        for kw in cases:
            r = ct.run_target(model, target.rest, plan.desired, cfg.controller,
                              ct.TargetRun(corridor=corridor, guess=guess, **kw))
            iterations.append(r.iterations)
            first.extend(r.step_wall_s[:1])
            later.extend(r.step_wall_s[1:])
    return np.array(first), np.array(later), iterations


def ms(a: np.ndarray) -> str:
    if len(a) == 0:
        return "n/a"
    p10, p50, p90 = np.percentile(a, [10, 50, 90]) * 1e3
    return f"median {p50:6.1f} ms  (p10 {p10:.1f}, p90 {p90:.1f}, n={len(a)})"


def stats_ms(a: np.ndarray) -> dict:
    """median, p10, p90 (ms) and the count of a, as `ms` prints them."""
    if len(a) == 0:
        return {"median_ms": None, "p10_ms": None, "p90_ms": None, "n": 0}
    p10, p50, p90 = np.percentile(a, [10, 50, 90]) * 1e3
    return {"median_ms": p50, "p10_ms": p10, "p90_ms": p90, "n": len(a)}


def model_iterations(path: Path, repeats: int, res: results_io.Results) -> None:
    """Median time of the controller's side of a control iteration with each model, and its build time."""
    from scissor_cli.experiments.controller_model_stage import fitted_model  # noqa: PLC0415
    from scissor_cli.experiments.run_cache import CACHE_DIR  # noqa: PLC0415
    from scissor_cli.layer3d.check import slab_spec  # noqa: PLC0415
    from scissor_cli.layer3d.slab import build_slab  # noqa: PLC0415
    from scissor_cli.layer3d.tissue_models import ControllerModel  # noqa: PLC0415

    cfg = load_config(path).model_copy(update={"manipulation_points": None})
    scene, mesh, layer = build_model(cfg)
    slab = build_slab(scene, mesh, slab_spec(cfg.layer_check, cfg.tissue.mesh), model=layer.params.model)
    plans = plan_targets(layer, scene, cfg.needle)
    print(f"{cfg.name}: layer {mesh.n_elements} triangles, slab {slab.mesh.n_elements} tetrahedra; "
          f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    print("| model | build | controller side of one iteration (median) | goal |")
    print("|---|---|---|---|")
    act = ct.Actuator.from_scene(scene)
    res.data("scene", {"config": cfg.name, "triangles": mesh.n_elements, "tetrahedra": slab.mesh.n_elements})
    rows = []
    for kind in ("layer", "calibrated", "surrogate", "slab"):
        kcfg = cfg.model_copy(update={"controller": cfg.controller.model_copy(update={"model": kind})})
        data, cached = fitted_model(kcfg, layer, slab, plans, ROOT / "runs" / CACHE_DIR, jobs=2)
        model = ControllerModel(data, layer, slab)
        ctrl = model.controller(0, act.lo, act.hi)
        s = np.full(layer.n_cups, 0.4 * scene.cups[0].stroke_max_mm)
        ctrl.update(s)
        rng = np.random.default_rng(0)
        axis, desired = np.array([1.0, 0.0]), scene.targets[0].rest + [0.3, -1.0]
        times = []
        for _ in range(repeats if kind != "slab" else max(5, repeats // 10)):
            t0 = time.perf_counter()
            s = np.clip(s + rng.choice([-1, 1], layer.n_cups) * rng.uniform(0.02, 0.5, layer.n_cups), act.lo, act.hi)
            ctrl.update(s)
            stroke_step(ctrl.jacobian, desired - scene.targets[0].rest, s, act.lo, act.hi, act.speed_mm_per_s * 0.1,
                        axis)
            times.append(time.perf_counter() - t0)
        build = "-" if kind in ("layer", "slab") else f"{data.build_time_s:.1f} s" + (" (cached)" if cached else "")
        goal = "-" if kind == "slab" else "<= 10 ms"
        error = "" if data.validation_error_mm is None else f"; error vs slab {data.validation_error_mm:.3g} mm"
        print(f"| {kind} | {build}{error} | {np.median(times) * 1e3:.2f} ms | {goal} |")
        rows.append({"model": kind, "build_s": None if kind in ("layer", "slab") else data.build_time_s,
                     "cached": bool(cached), "error_mm": data.validation_error_mm,
                     "iteration_ms": np.median(times) * 1e3})
    res.table("models", rows, {"build_s": "s", "error_mm": "mm", "iteration_ms": "ms"})
    print(f"load average now {os.getloadavg()[0]:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "example.yaml"))
    ap.add_argument("--repeats", type=int, default=60, help="corrective steps per measurement")
    ap.add_argument("--trials", type=int, default=3, help="noisy trials per target in the loop measurement")
    ap.add_argument("--table", action="store_true", help="only the goal table (one and two cups, grip search)")
    ap.add_argument("--models", action="store_true", help="the controller's side of an iteration per controller.model")
    args = ap.parse_args()
    stem = Path(args.config).stem
    mode = "models" if args.models else "table" if args.table else None
    variant = ".".join(p for p in (mode, None if stem == ("example_full" if args.models else "example") else stem,
                                   None if args.repeats == 60 and args.trials == 3 else
                                   f"r{args.repeats}t{args.trials}") if p)
    res = results_io.Results("bench_control", variant or None)
    if args.models:
        model_iterations(Path(args.config), args.repeats, res)
        res.write()
        return
    if args.table:
        print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
        table(args.repeats, res)
        print(f"load average now {os.getloadavg()[0]:.2f}")
        res.write()
        return

    cfg = load_config(args.config)
    scene, mesh, model = build_model(cfg)
    print(f"{cfg.name}: {mesh.n_elements} elements, {mesh.n_nodes} nodes, {len(model.free_dofs)} free dofs; "
          f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    target = scene.targets[0]
    operating = 0.6 * scene.cups[0].stroke_max_mm
    truth = model.with_material(1.3, fiber_angle_rad=scene.material.fiber_angle_rad + np.deg2rad(10))
    corrective_steps(model, truth, target, operating, 3)  # warm-up: imports, allocations
    res.data("scene", {"config": cfg.name, "elements": mesh.n_elements, "nodes": mesh.n_nodes,
                       "free_dofs": len(model.free_dofs)})
    t_mismatch = corrective_steps(model, truth, target, operating, args.repeats)
    print(f"corrective iteration, truth != model : {ms(t_mismatch)}")
    t_match = corrective_steps(model, model, target, operating, args.repeats)
    print(f"corrective iteration, truth == model : {ms(t_match)}")
    rows = [dict(measurement="corrective, truth != model", **stats_ms(t_mismatch)),
            dict(measurement="corrective, truth == model", **stats_ms(t_match))]

    cache = StateCache(model)
    plans = plan_targets(model, scene, cfg.needle, cache=cache)
    for label, c in (("from rest", None), ("from the planner's state", cache)):
        first, later, its = loop_steps(cfg, model, plans, args.trials, c)
        print(f"closed loops, big moves {label} ({len(its)} runs, {sum(its)} iterations, {min(its)}-{max(its)} "
              "per run):")
        print(f"  first iteration (the big move)       : {ms(first)}")
        print(f"  later iterations                     : {ms(later)}")
        print(f"  all iterations                       : {ms(np.concatenate([first, later]))}")
        rows.append(dict(measurement=f"loop {label}: first iteration", runs=len(its), **stats_ms(first)))
        rows.append(dict(measurement=f"loop {label}: later iterations", runs=len(its), **stats_ms(later)))
        rows[-1]["iterations_per_run"] = [min(its), max(its)]
    print(f"load average now {os.getloadavg()[0]:.2f}")
    res.table("iterations", rows, {"median_ms": "ms", "p10_ms": "ms", "p90_ms": "ms"})
    res.write()


if __name__ == "__main__":
    main()
