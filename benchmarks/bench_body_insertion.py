"""The needle in the body (docs/model.md §20): one insertion per strategy, timed; not a test.

On configs/example_dome.yaml's body (the configured mesh): the needle along −x through T1 at rest from
where that line enters the skin, 50 mm deep (past the lesion) in 0.5 mm steps, with the default needle–tissue
parameters (§12), under `none`, `depth` and `loop` (both cups would move it; the dome has one). Per strategy:
the wall time, steps, the lesion's miss at the end, the last force, active-set passes that did not settle.
Goal (§20): a 50 mm insertion in 0.5 mm steps ≤ 5 s at 30k tetrahedra.

    PYTHONPATH=. python benchmarks/bench_body_insertion.py [--depth-mm 50] [--step-mm 0.5]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import results_io

from scissor_cli import runtime

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--depth-mm", type=float, default=50.0)
    ap.add_argument("--step-mm", type=float, default=0.5)
    args = ap.parse_args()
    runtime.configure()
    from scissor_cli.config import load_config
    from scissor_cli.config.sections import InsertionConfig
    from scissor_cli.experiments.build import body_model
    from scissor_cli.insertion import InsertionOptions, NeedleParams, NeedlePath, run_strategies
    from scissor_cli.planning.body_lines import skin_entries
    from scissor_cli.solvers.equilibrium import solve_equilibrium

    res = results_io.Results("bench_body_insertion")
    cfg = load_config(CONFIG)
    scene, mesh, tissue = body_model(cfg)
    params = NeedleParams.from_config(InsertionConfig(step_mm=args.step_mm), cfg.needle, cfg.tissue.mesh)
    lesion = scene.targets[0]
    n = np.array([-1.0, 0.0, 0.0])
    entries, _, _ = skin_entries(mesh.nodes, mesh.boundary_triangles, np.zeros(len(mesh.boundary_triangles), bool),
                                 lesion.rest, n[None])
    strokes = np.zeros(len(scene.cups))
    x0 = solve_equilibrium(tissue, strokes).x
    path = NeedlePath(entries[0], n, args.depth_mm, lesion.rest, lesion.name)
    print(f"{cfg.name}: {mesh.n_elements} tetrahedra; {lesion.name} from {np.round(entries[0], 1).tolist()} along "
          f"{n.tolist()}, {args.depth_mm:g} mm in {args.step_mm:g} mm steps", flush=True)
    res.figure("tetrahedra", mesh.n_elements, "1")
    rows = []
    for strategy in ("none", "depth", "loop"):
        t0 = time.perf_counter()
        r = run_strategies(tissue, x0, strokes, {strategy: path}, params,
                           {strategy: InsertionOptions(strategy, cfg.controller, keep_displacement=False)})[0]
        wall = time.perf_counter() - t0
        rows.append({"strategy": strategy, "steps": r.steps, "depth_mm": float(r.depth_mm[-1]), "wall_s": wall,
                     "miss_mm": r.miss_mm, "force_mN": float(r.needle_force_mN[-1]), "unsettled": r.unsettled,
                     "stop": r.stop_reason})
        print(f"  {strategy}: {r.steps} steps to {r.depth_mm[-1]:.1f} mm in {wall:.1f} s, miss {r.miss_mm:.3f} mm, "
              f"force {r.needle_force_mN[-1]:.0f} mN ({r.stop_reason})", flush=True)
    res.table("strategies", rows, {"depth_mm": "mm", "wall_s": "s", "miss_mm": "mm", "force_mN": "mN"})
    res.data("config", str(CONFIG.relative_to(ROOT)))
    res.write()


if __name__ == "__main__":
    main()
