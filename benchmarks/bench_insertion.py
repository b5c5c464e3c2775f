"""Speed of the needle insertion (docs/model.md §12) on a scene's full mesh; not a timed test.

For the first target with a plan, from the equilibrium at the plan's
strokes, along the plan's entry and direction (strategy `none`):

* one insertion step: the median wall time of the steps of a 50 mm
  insertion in 0.5 mm steps (target: ≤ 10 ms);
* the whole 50 mm insertion in 0.5 mm steps (target: ≤ 1 s);
* cost against step size: 2, 1, 0.5, 0.25 mm, each with the final target
  position's distance from the 0.25 mm run's (the step-size error).

    PYTHONPATH=. python benchmarks/bench_insertion.py [CONFIG.yaml] [--depth MM]

The config needs an `insertion:` section (its friction and tip force are
used; the step sizes are the benchmark's). The machine has 2 cores and other
work may share them: the numbers are wall-clock medians, not CPU time.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from scissor_cli import runtime
from scissor_cli.config import load_config
from scissor_cli.insertion import NeedleParams, run_insertion
from scissor_cli.insertion.needle import NeedleState, advance, free_nodes
from scissor_cli.mechanics.tissue import build_model
from scissor_cli.planning.needle import plan_target
from scissor_cli.solvers.equilibrium import solve_equilibrium

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "example_insertion.yaml"))
    ap.add_argument("--depth", type=float, default=50.0, help="insertion depth (mm)")
    args = ap.parse_args()
    runtime.configure()
    cfg = load_config(args.config)
    if cfg.insertion is None:
        raise SystemExit(f"{args.config}: no insertion section")
    scene, mesh, tissue = build_model(cfg)
    params = NeedleParams.from_config(cfg.insertion, cfg)
    for target in scene.targets:
        plan = plan_target(tissue, scene, target, cfg.needle)
        if plan.feasible:
            break
    else:
        raise SystemExit("no target has a plan")
    x0 = solve_equilibrium(tissue, plan.strokes).x
    print(f"{cfg.name}: {mesh.n_nodes} nodes, {mesh.n_elements} elements; target {target.name}, "
          f"{plan.side} entry, f_s {params.friction_static_mN_per_mm:g}, f_k {params.friction_kinetic_mN_per_mm:g} mN/mm, "
          f"F_tip {params.tip_force_mN:g} mN")

    # one step: every step of a 0.5 mm insertion to args.depth
    state, x, times = NeedleState(plan.entry, plan.direction), x0.copy(), []
    cand = free_nodes(tissue)
    while state.depth_mm < args.depth - 1e-9:
        t0 = time.perf_counter()
        out = advance(tissue, state, x, plan.strokes, 0.5, params, cand)
        times.append(time.perf_counter() - t0)
        x = out.x
    t = np.array(times) * 1e3
    print(f"one step (0.5 mm): median {np.median(t):.1f} ms (min {t.min():.1f}, max {t.max():.1f}; "
          f"{t.size} steps; target ≤ 10 ms)")
    print(f"{args.depth:g} mm in 0.5 mm steps: {t.sum() / 1e3:.2f} s (target ≤ 1 s)")

    print("step (mm)  steps  time (s)  ms/step  final target (mm)          |Δ| vs 0.25 mm (mm)")
    rows = []
    for step in (2.0, 1.0, 0.5, 0.25):
        p = dataclasses.replace(params, step_mm=step)
        t0 = time.perf_counter()
        r = run_insertion(tissue, x0, plan.strokes, plan.entry, plan.direction, args.depth, target.rest, p, "none",
                          keep_displacement=False)
        rows.append((step, r.steps, time.perf_counter() - t0, r.target[-1]))
    ref = rows[-1][3]
    for step, k, wall, y in rows:
        print(f"{step:9.2f}  {k:5d}  {wall:8.2f}  {1e3 * wall / k:7.1f}  ({y[0]:.3f}, {y[1]:.3f})"
              f"  {np.linalg.norm(y - ref):10.4f}")


if __name__ == "__main__":
    main()
