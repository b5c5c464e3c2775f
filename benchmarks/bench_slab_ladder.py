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
            finest_case(path.name, model, spec, planes, cases, args.finest)
            continue
        t0 = time.perf_counter()
        choice = choose_slab(model, spec, cases, accuracy, planes, ladder_runner(args.jobs), args.jobs)
        wall = time.perf_counter() - t0
        print(f"\n{path.name}: accuracy {accuracy:g} mm, {len(cases)} case(s), --jobs {args.jobs}: picked in {wall:.1f} s, "
              f"{choice.solved} of {len(choice.candidates)} candidates solved; {choice.explain()}")
        print("| in-plane scale | levels | tetrahedra | error (mm) | forward solves (s) |")
        print("|---|---|---|---|---|")
        for c in choice.candidates:
            if c.solved:
                print(f"| {c.in_plane_scale:g} | {c.levels} | {c.n_tetrahedra} | {c.error_mm:.4f} | {c.solve_s:.1f} |")
        if not args.exhaustive:
            continue
        t0 = time.perf_counter()
        candidates, true = exhaustive_errors(model, spec, cases, planes)
        print(f"every candidate solved in {time.perf_counter() - t0:.0f} s")
        within = [k for k in range(len(candidates)) if true[k] <= accuracy]
        best = min(within, key=lambda k: candidates[k].n_tetrahedra)
        print(f"the full ladder's pick: {candidates[best].n_tetrahedra} tetrahedra, error {true[best]:.4f} mm "
              f"({'the same' if best == choice.pick else 'NOT the same'})")
    print(f"\nload {os.getloadavg()[0]:.2f}")


def finest_case(name: str, model, spec, planes, cases, case: int) -> None:
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


if __name__ == "__main__":
    main()
