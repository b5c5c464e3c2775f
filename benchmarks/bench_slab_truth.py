"""Slab truth speed (docs/performance.md, "Slab truth"): kernels, one truth settle, one slab-truth trial.

Usage: python benchmarks/bench_slab_truth.py [CONFIG] [--moves N] [--trial] [--configured]
Default CONFIG: configs/paper_trials_prosthesis_slab.yaml (first target, first trial's perturbation).
The slab is the one `scissor simulate CONFIG` would use: with `layer_check.accuracy_mm` the ladder's pick
(read from runs/.scissor-cache beside the default output folder when a run of the scene made it, else
solved, minutes); --configured benches the configured (finest) slab instead.

Prints, with the machine's load:
* the slab's size; the compiled against the numpy gradient and stiffness (median of 5);
  one CHOLMOD refactorisation and one solve with it;
* the nominal slab's equilibrium at the plan's strokes (what each worker solves once per target);
* a loop-like replay on the trial's perturbed slab: the plan's strokes, then N moves closing
  geometrically on the stroke limit (as the loop does when the slab moves less than the model
  expects): the first move and the median of the others;
* with --trial: one whole slab-truth trial (the closed loop), its time and iterations.
Goals (issue: slab truth at the speed of an experiment): settle <= 0.3 s median, trial <= 10 s.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli import control, progress  # noqa: E402
from scissor_cli.config import load_config, resolved_yaml  # noqa: E402
from scissor_cli.experiments.layer_check_stage import slab_resolution_stage  # noqa: E402
from scissor_cli.experiments.profiles import draw_trial  # noqa: E402
from scissor_cli.experiments.run_cache import CACHE_DIR  # noqa: E402
from scissor_cli.experiments.simulate import robot_joint_check, trial_tasks  # noqa: E402
from scissor_cli.experiments.trials import TrialContext  # noqa: E402
from scissor_cli.mechanics import compiled3d, fem, materials  # noqa: E402
from scissor_cli.planning.needle_plan import plan_targets  # noqa: E402
from scissor_cli.solvers.linear import factorize_free  # noqa: E402
from scissor_cli.solvers.tracking import TrackedEquilibrium  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


class Printer(progress.SilentReporter):
    """The reporter the ladder's messages go to: printed."""

    def info(self, message: str) -> None:
        print(message, flush=True)


def kernels(slab) -> dict:
    x = slab.rest * 1.01
    compiled3d.element_stiffness(slab.ops, slab.params, x, False)  # compile (cached on disk after the first run)

    def numpy_stiffness():
        F = fem.deformation_gradients(slab.ops, x)
        fem.element_matrices(slab.ops, materials.evaluate(F, slab.params, order=2)[2])

    def numpy_gradient():
        F = fem.deformation_gradients(slab.ops, x)
        P = materials.evaluate(F, slab.params, order=1)[1]
        fem.scatter_vector(slab.ops, fem.element_forces(slab.ops, P))

    out = {"gradient_numpy_s": results_io.median_s(numpy_gradient),
           "gradient_compiled_s": results_io.median_s(lambda: compiled3d.energy_gradient(slab.ops, slab.params, x))}
    print(f"  gradient: numpy {out['gradient_numpy_s']:.3f} s, compiled {out['gradient_compiled_s']:.3f} s")
    out["stiffness_numpy_s"] = results_io.median_s(numpy_stiffness)
    out["stiffness_compiled_s"] = results_io.median_s(
        lambda: compiled3d.element_stiffness(slab.ops, slab.params, x, False))
    out["kff_assembled_s"] = results_io.median_s(lambda: slab.stiffness_free(x, upper=True))
    print(f"  element stiffness: numpy {out['stiffness_numpy_s']:.3f} s, compiled "
          f"{out['stiffness_compiled_s']:.3f} s; K_ff assembled {out['kff_assembled_s']:.3f} s")
    K = slab.stiffness_free(slab.rest, upper=True)
    slot: dict = {}
    factor = factorize_free(slab, K, slot)
    b = np.ones(K.shape[0])
    out["refactorisation_s"] = results_io.median_s(lambda: factorize_free(slab, K, slot), 3)
    out["solve_s"] = results_io.median_s(lambda: factor.solve(b), 7)
    print(f"  CHOLMOD refactorisation {out['refactorisation_s']:.2f} s, solve {out['solve_s'] * 1e3:.0f} ms")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "paper_trials_prosthesis_slab.yaml"))
    ap.add_argument("--moves", type=int, default=12, help="moves of the replay after the first (default 12)")
    ap.add_argument("--trial", action="store_true", help="also run one whole slab-truth trial")
    ap.add_argument("--configured", action="store_true", help="the configured slab, not accuracy_mm's pick")
    args = ap.parse_args()
    stem = Path(args.config).stem
    res = results_io.Results("bench_slab_truth", ".".join(p for p in (
        None if stem == "paper_trials_prosthesis_slab" else stem, None if args.moves == 12 else f"moves{args.moves}",
        "trial" if args.trial else None, "configured" if args.configured else None) if p) or None)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.2f}; {args.config}")
    cfg = load_config(args.config)
    if cfg.trials.truth != "slab" or cfg.layer_check is None:
        sys.exit(f"{args.config}: needs trials.truth: slab and a layer_check section")
    if cfg.layer_check.accuracy_mm is not None and not args.configured:
        with progress.reporting(Printer()):
            cfg, choice = slab_resolution_stage(cfg, Path("runs") / CACHE_DIR)
    t0 = time.perf_counter()
    ctx = TrialContext(resolved_yaml(cfg))
    slab = ctx.slab_truth.slab
    context_s = time.perf_counter() - t0
    print(f"slab: {slab.ops.corners.shape[1]} tetrahedra, {len(slab.free_dofs)} free dofs; "
          f"worker context (layer model + slab) {context_s:.1f} s")
    res.figure("tetrahedra", slab.ops.corners.shape[1], "tetrahedra")
    res.figure("free_dofs", len(slab.free_dofs), "unknowns")
    res.figure("worker_context_s", context_s, "s")
    for key, value in kernels(slab).items():
        res.figure(key, value, "s")
    # planned as `simulate` plans: the robot's joint limits decide which needle lines it can reach
    tasks = trial_tasks(ctx.tissue, plan_targets(ctx.tissue, ctx.scene, cfg.needle, robot_check=robot_joint_check(cfg)))
    task = tasks[0]
    t0 = time.perf_counter()
    factory = ctx.slab_truth.for_target(task.rest, task.plan_strokes)
    nominal_s = time.perf_counter() - t0
    print(f"nominal slab at the plan of {task.name} (strokes {np.round(task.plan_strokes, 2)} mm): "
          f"{nominal_s:.1f} s, once per worker and target")
    res.figure("nominal_start_s", nominal_s, "s", target=task.name)
    draw = draw_trial(ctx.errors, ctx.scene.material.nu, ctx.centroids, cfg.seed, task.index, 0)
    truth = control.TruthPerturbation(E_scale=draw.E_field, fiber_offset_rad=draw.fiber_offset_rad, nu=draw.nu,
                                      eta_scale=draw.eta_scale)
    tissue, view = factory(truth)
    lo = np.array([c.stroke_min_mm for c in ctx.scene.cups])
    hi = np.array([c.stroke_max_mm for c in ctx.scene.cups])
    limit = np.where(task.plan_strokes >= 0, hi, lo)
    k = np.arange(1, args.moves + 1)[:, None]
    sequence = [task.plan_strokes] + list(task.plan_strokes + (limit - task.plan_strokes) * (1 - 0.7 ** k))
    eq = TrackedEquilibrium(tissue, view.tol)
    eq.guesses.extend(view.guesses)
    times = []
    for s in sequence:
        t0 = time.perf_counter()
        eq.move_to(np.asarray(s, float), tangent=False)
        times.append(time.perf_counter() - t0)
    print(f"replay of {len(sequence)} settles: first {times[0]:.2f} s, then median {np.median(times[1:]):.2f} s "
          f"(min {min(times[1:]):.2f}, max {max(times[1:]):.2f}); {eq.stats['refactors']} factorisations, "
          f"{eq.stats['newton_iterations']} Newton iterations")
    res.figure("replay_settles", len(sequence), "settles")
    res.figure("replay_first_s", times[0], "s")
    res.figure("settle_median_s", float(np.median(times[1:])), "s", goal="<= 0.3 s")
    res.figure("settle_max_s", max(times[1:]), "s")
    res.figure("replay_factorisations", eq.stats["refactors"], "factorisations")
    res.figure("replay_newton_iterations", eq.stats["newton_iterations"], "iterations")
    if args.trial:
        t0 = time.perf_counter()
        outcome = ctx.run(task, 0)
        print(f"trial 0 of {task.name}: {time.perf_counter() - t0:.1f} s, {outcome.iterations} iterations, "
              f"stop {outcome.stop_reason}, final error {np.round(outcome.final_error, 3)} mm")
        res.figure("trial_s", time.perf_counter() - t0, "s", target=task.name, goal="<= 10 s")
        res.figure("trial_iterations", outcome.iterations, "iterations")
        res.data("trial_stop", str(outcome.stop_reason))
    res.write()


if __name__ == "__main__":
    main()
