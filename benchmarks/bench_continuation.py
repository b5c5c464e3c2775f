"""The load continuation's two settings on the body's hardest move (docs/model.md §4, "Load continuation"); a
measurement, not a test.

A solve from rest takes the tangent predictor's step as far as STEP_FRACTION of the way to its first inverted
element, solves that intermediate state to SUBSTEP_TOL only, and predicts again (`solvers.newton.solve_newton`).
On configs/example_dome.yaml push10 needs several such load substeps (an element at the cup's rim nearly
collapses: `bench_cup_springs`). This times push10 from rest, Newton to 1e-8, over a grid of the two settings,
each the same way `bench_body` times its from-rest figure (a warm-up solve, then --repeats solves, each starting
with the factorisation the last one left): the median wall time, Newton iterations, factorisations and load
substeps, and how far the answer lies from the default settings' solved to 1e-10 (the largest node distance).

    PYTHONPATH=. python3 benchmarks/bench_continuation.py [--repeats 3] [--fractions 0.5 0.7 0.85]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import results_io

from scissor_cli import runtime

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"
PUSH_MM = 10.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.5, 0.7, 0.85])
    ap.add_argument("--substep-tols", type=float, nargs="+", default=[1e-4, 1e-3, 1e-2])
    args = ap.parse_args()
    runtime.configure()
    from scissor_cli.config import load_config
    from scissor_cli.experiments.build import body_model
    from scissor_cli.solvers import newton
    from scissor_cli.solvers.equilibrium import solve_equilibrium

    res = results_io.Results("bench_continuation")
    cfg = load_config(CONFIG)
    _, mesh, tissue = body_model(cfg, cache=ROOT / "runs" / ".mesh-cache")
    defaults = (newton.STEP_FRACTION, newton.SUBSTEP_TOL)
    res.data("element", cfg.tissue.mesh.element)
    res.data("defaults", {"step_fraction": defaults[0], "substep_tol": defaults[1]})
    res.figure("tetrahedra", mesh.n_elements, "1")
    push = np.array([PUSH_MM])
    reference = solve_equilibrium(tissue, push, tol=1e-10).x
    rows = []
    try:
        for fraction in args.fractions:
            for substep_tol in args.substep_tols:
                newton.STEP_FRACTION, newton.SUBSTEP_TOL = fraction, substep_tol
                solve_equilibrium(tissue, push, tol=1e-8)  # warm-up: each setting starts as the repeats do
                solved = []
                wall_s = results_io.median_s(
                    lambda solved=solved: solved.append(solve_equilibrium(tissue, push, tol=1e-8)), args.repeats)
                r = solved[-1]
                row = {"step_fraction": fraction, "substep_tol": substep_tol, "wall_s": wall_s,
                       "iterations": r.iterations, "factorizations": r.factorizations,
                       "substeps": r.substeps, "off_reference_mm": float(np.max(np.linalg.norm(
                           r.x - reference, axis=1))), "default": (fraction, substep_tol) == defaults}
                rows.append(row)
                print(f"fraction {fraction:g}, substep tol {substep_tol:g}: {row['wall_s']:.2f} s, "
                      f"{row['iterations']} iterations, {row['factorizations']} factorisations, "
                      f"{row['substeps']} substeps", flush=True)
    finally:
        newton.STEP_FRACTION, newton.SUBSTEP_TOL = defaults
    res.table("settings", rows, {"wall_s": "s", "off_reference_mm": "mm"})
    res.write()


if __name__ == "__main__":
    main()
