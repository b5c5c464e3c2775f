"""The slab's resolution ladder (docs/model.md §13, §18): its time, and its pick against the full ladder; not a test.

For a scene with `layer_check` (its `accuracy_mm`, or 0.1 mm by default):

* the choice as `scissor simulate` makes it (`layer3d.resolution.choose_slab`:
  the finest slab, then coarse to fine until one is within the accuracy):
  wall time, candidates solved, the pick and its error, and per solved
  candidate its error and forward solves' time (goal: ≤ 60 s on the paper
  scenes);
* with `--exhaustive`, every candidate solved and compared with the finest
  slab (`exhaustive_errors`, the old way: minutes), and whether the choice
  is the full ladder's pick;
* with `--finest CASE`, instead, the finest slab's forward case CASE alone
  in this process (what bounds the ladder with `--jobs 2`): its build, and
  its Newton solve's time, load substeps, iterations and factorisations.

    PYTHONPATH=. python benchmarks/bench_slab_ladder.py [CONFIG.yaml ...] [--jobs N] [--exhaustive | --finest CASE]

The machine, its cores and load average are printed with the figures.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.experiments.build import build_model  # noqa: E402
from scissor_cli.experiments.layer_check_stage import ladder_cases, ladder_runner  # noqa: E402
from scissor_cli.layer3d.check import plane_ladder, slab_spec  # noqa: E402
from scissor_cli.layer3d.resolution import SOLVE_TOL, _Ladder, choose_slab, exhaustive_errors  # noqa: E402
from scissor_cli.layer3d.slab import build_slab  # noqa: E402
from scissor_cli.solvers.newton import solve_newton  # noqa: E402

DEFAULT_CONFIGS = [ROOT / "configs" / "paper_trials_prosthesis_slab.yaml", ROOT / "configs" / "example_3d.yaml"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("configs", nargs="*", type=Path, default=DEFAULT_CONFIGS)
    ap.add_argument("--exhaustive", action="store_true", help="also solve every candidate (minutes)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes, as `simulate --jobs` (default 2)")
    ap.add_argument("--finest", type=int, metavar="CASE", help="instead: the finest slab's forward case CASE alone")
    args = ap.parse_args()
    default = [Path(p).resolve() for p in args.configs] == DEFAULT_CONFIGS
    res = results_io.Results("bench_slab_ladder", ".".join(p for p in (
        None if default else "-".join(Path(p).stem for p in args.configs),
        None if args.jobs == 2 else f"jobs{args.jobs}", "exhaustive" if args.exhaustive else None,
        None if args.finest is None else f"finest{args.finest}") if p) or None)
    picks = []
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.2f}")
    for path in args.configs:
        cfg = load_config(path)
        lc = cfg.layer_check
        accuracy = lc.accuracy_mm if lc.accuracy_mm is not None else 0.1
        _, _, model = build_model(cfg)
        spec, planes = slab_spec(lc, cfg.tissue.mesh), plane_ladder(lc, cfg.tissue.mesh)
        cases = ladder_cases(cfg, model.scene)
        if args.finest is not None:
            picks.append(finest_case(path.name, model, spec, planes, cases, args.finest))
            continue
        t0 = time.perf_counter()
        choice = choose_slab(model, spec, cases, accuracy, planes, ladder_runner(args.jobs), args.jobs)
        wall = time.perf_counter() - t0
        print(f"\n{path.name}: accuracy {accuracy:g} mm, {len(cases)} case(s), --jobs {args.jobs}: picked in "
              f"{wall:.1f} s, "
              f"{choice.solved} of {len(choice.candidates)} candidates solved; {choice.explain()}")
        print("| in-plane scale | levels | tetrahedra | error (mm) | forward solves (s) |")
        print("|---|---|---|---|---|")
        for c in choice.candidates:
            if c.solved:
                print(f"| {c.in_plane_scale:g} | {c.levels} | {c.n_tetrahedra} | {c.error_mm:.4f} | {c.solve_s:.1f} |")
        picked = choice.candidates[choice.pick]
        picks.append({"config": path.name, "accuracy_mm": accuracy, "cases": len(cases), "jobs": args.jobs,
                      "wall_s": wall, "solved": choice.solved, "candidates": len(choice.candidates),
                      "pick_tetrahedra": picked.n_tetrahedra, "pick_in_plane_scale": picked.in_plane_scale,
                      "pick_levels": picked.levels, "pick_error_mm": picked.error_mm, "load1": results_io.load1(),
                      "solved_candidates": [{"in_plane_scale": c.in_plane_scale, "levels": c.levels,
                                             "tetrahedra": c.n_tetrahedra, "error_mm": c.error_mm,
                                             "solve_s": c.solve_s} for c in choice.candidates if c.solved]})
        if not args.exhaustive:
            continue
        t0 = time.perf_counter()
        candidates, true = exhaustive_errors(model, spec, cases, planes)
        print(f"every candidate solved in {time.perf_counter() - t0:.0f} s")
        within = [k for k in range(len(candidates)) if true[k] <= accuracy]
        best = min(within, key=lambda k: candidates[k].n_tetrahedra)
        print(f"the full ladder's pick: {candidates[best].n_tetrahedra} tetrahedra, error {true[best]:.4f} mm "
              f"({'the same' if best == choice.pick else 'NOT the same'})")
        picks[-1].update({"full_ladder_tetrahedra": candidates[best].n_tetrahedra,
                          "full_ladder_error_mm": true[best], "same_pick": bool(best == choice.pick)})
    print(f"\nload {os.getloadavg()[0]:.2f}")
    res.table("ladders", picks, {"accuracy_mm": "mm", "wall_s": "s", "pick_error_mm": "mm",
                                 "full_ladder_error_mm": "mm", "build_s": "s", "solve_s": "s"})
    res.write()


def finest_case(name: str, model, spec, planes, cases, case: int) -> dict:
    """The finest slab (the ladder's candidate 0) built and solved at one forward case, as `solve_group` does."""
    if not 0 <= case < len(cases):
        raise SystemExit(f"--finest: the scene has forward cases 0..{len(cases) - 1}, not {case}")
    _, finest_spec, surface, *_ = _Ladder(model, spec, cases, planes).task(0, [case])
    t0 = time.perf_counter()
    slab = build_slab(model.scene, surface, finest_spec, model=model.params.model)
    built = time.perf_counter() - t0
    r = solve_newton(slab, cases[case], tol=SOLVE_TOL, factors={})
    print(f"\n{name}: the finest slab ({slab.ops.corners.shape[1]} tetrahedra), case {case} (strokes "
          f"{cases[case].tolist()} mm): built in {built:.1f} s, solved in {r.time_s:.1f} s: {r.message}, "
          f"{r.iterations} Newton iterations, {r.factorizations} factorisations")
    return {"config": name, "tetrahedra": slab.ops.corners.shape[1], "case": case, "build_s": built,
            "solve_s": r.time_s, "message": r.message, "iterations": r.iterations,
            "factorisations": r.factorizations}


if __name__ == "__main__":
    main()
