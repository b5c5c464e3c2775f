"""Forward-solve benchmark: Newton (tol 1e-10) vs ADMM-PD (its tolerance) on a scene's forward cases.

    python benchmarks/bench_forward.py [CONFIG.yaml] [--repeats 5]

For each forward case (configs/example.yaml: push10, pull8) prints the
Newton time (median of the repeats) and iterations, then for plain ADMM and
ADMM with Anderson acceleration (memory 5):

* cold   — a freshly built solver, first solve from scratch: includes the
           weight boosts and their refactorisations (setup = construction,
           one factorisation, reported separately);
* settled — from scratch again on the same solver, its weights learned (what
           every later solve of a control loop pays);
* warm   — from the previous state to a stroke 0.05 mm / 0.3 mm away;

with iterations, time per iteration in µs per element (settled solve: no
refactorisation in it), the relative L2 displacement error against Newton
and the common relative force residual. Wall times: time.perf_counter,
median over the repeats. Runs in well under 2 minutes on the 2-core box.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.experiments.build import scene_of  # noqa: E402
from scissor_cli.experiments.study import timed  # noqa: E402
from scissor_cli.mechanics.tissue import build_tissue  # noqa: E402
from scissor_cli.mesh.mesh import mesh_for_config  # noqa: E402
from scissor_cli.solvers.admm.solver import AdmmSolver  # noqa: E402
from scissor_cli.solvers.newton import solve_newton  # noqa: E402


def rel_error(x, ref, rest):
    return float(np.linalg.norm(x - ref) / np.linalg.norm(ref - rest))


def main(argv=None) -> int:
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=os.path.join(root, "configs", "example.yaml"))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--tol", type=float, default=None, help="ADMM tolerance (default: the config's)")
    args = parser.parse_args(argv)
    n_rep = max(args.repeats, 5)
    default_config = os.path.abspath(args.config) == os.path.join(root, "configs", "example.yaml")
    res = results_io.Results("bench_forward", None if default_config and args.tol is None
                             else f"{os.path.splitext(os.path.basename(args.config))[0]}-tol{args.tol}")
    rows = []

    t_start = time.perf_counter()
    cfg = load_config(args.config)
    scene = scene_of(cfg)
    mesh = mesh_for_config(scene, cfg.tissue.mesh)
    tissue = build_tissue(scene, mesh)
    tol = args.tol if args.tol is not None else cfg.solver.tolerance
    M = mesh.n_elements
    print(f"scene {scene.name!r}: {M} elements, {mesh.n_nodes} nodes, {len(tissue.free_dofs)} free dofs, "
          f"model {scene.material.model}; ADMM tol {tol:g}, Newton tol 1e-10; median of {n_rep} runs")
    res.data("scene", {"name": scene.name, "elements": M, "nodes": mesh.n_nodes, "free_dofs": len(tissue.free_dofs),
                       "model": scene.material.model, "admm_tol": tol, "newton_tol": 1e-10, "repeats": n_rep})

    for case in cfg.forward:
        strokes = scene.strokes_vector(case.strokes)
        print(f"\n== {case.name}: strokes {strokes.tolist()} mm")
        ref, t_newton = timed(lambda strokes=strokes: solve_newton(tissue, strokes, tol=1e-10), n_rep, math.inf)
        print(f"  newton          {t_newton * 1e3:8.1f} ms  {ref.iterations:4d} it  residual {ref.residual:.1e}")
        rows.append({"case": case.name, "solver": "newton", "mode": "cold", "ms": t_newton * 1e3,
                     "iterations": ref.iterations, "residual": ref.residual})
        for memory in (0, 5):
            name = "admm" if memory == 0 else f"admm+AA({memory})"
            solver, t_setup = timed(lambda memory=memory: AdmmSolver(tissue, anderson_memory=memory), n_rep, math.inf)

            def cold(memory=memory, strokes=strokes):
                s = AdmmSolver(tissue, anderson_memory=memory)
                r, _ = s.solve(strokes, tol=tol)
                return r, s.n_factorizations

            (r_cold, n_fact), t_cold = timed(cold, n_rep, math.inf)
            solver.solve(strokes, tol=tol)  # learn the weights
            n_before = solver.n_factorizations
            (r_set, state), t_set = timed(lambda solver=solver, strokes=strokes: solver.solve(strokes, tol=tol),
                                          n_rep, math.inf)
            per_it = t_set / r_set.iterations / M * 1e6
            refact = solver.n_factorizations - n_before
            print(f"  {name:14s}  setup {t_setup * 1e3:6.1f} ms (1 factorisation)")
            print(f"  {'':14s}  cold    {t_cold * 1e3:8.1f} ms  {r_cold.iterations:4d} it  "
                  f"{n_fact - 1} refactorisations  err {rel_error(r_cold.x, ref.x, tissue.rest):.1e}  "
                  f"residual {r_cold.residual:.1e}  {'converged' if r_cold.converged else 'NOT CONVERGED'}")
            print(f"  {'':14s}  settled {t_set * 1e3:8.1f} ms  {r_set.iterations:4d} it  {per_it:5.2f} µs/element/it  "
                  f"({refact} refactorisations)  err {rel_error(r_set.x, ref.x, tissue.rest):.1e}  "
                  f"residual {r_set.residual:.1e}")
            rows.append({"case": case.name, "solver": name, "mode": "setup", "ms": t_setup * 1e3})
            rows.append({"case": case.name, "solver": name, "mode": "cold", "ms": t_cold * 1e3,
                         "iterations": r_cold.iterations, "refactorisations": n_fact - 1,
                         "error_rel": rel_error(r_cold.x, ref.x, tissue.rest), "residual": r_cold.residual,
                         "converged": bool(r_cold.converged)})
            rows.append({"case": case.name, "solver": name, "mode": "settled", "ms": t_set * 1e3,
                         "iterations": r_set.iterations, "us_per_element_iteration": per_it,
                         "refactorisations": refact, "error_rel": rel_error(r_set.x, ref.x, tissue.rest),
                         "residual": r_set.residual})
            for ds in (0.05, 0.3):
                s2 = strokes + ds
                ref2 = solve_newton(tissue, s2, x0=ref.x, strokes0=strokes)
                (r_warm, _), t_warm = timed(lambda solver=solver, s2=s2, state=state: solver.solve(s2, state, tol=tol),
                                            n_rep, math.inf)
                r_cold2, _ = solver.solve(s2, tol=tol)
                print(f"  {'':14s}  warm +{ds:<4g} {t_warm * 1e3:6.1f} ms  {r_warm.iterations:4d} it "
                      f"(from scratch {r_cold2.iterations} it)  err {rel_error(r_warm.x, ref2.x, tissue.rest):.1e}")
                rows.append({"case": case.name, "solver": name, "mode": f"warm+{ds:g}", "ms": t_warm * 1e3,
                             "iterations": r_warm.iterations, "iterations_from_scratch": r_cold2.iterations,
                             "error_rel": rel_error(r_warm.x, ref2.x, tissue.rest)})
    print(f"\ntotal {time.perf_counter() - t_start:.1f} s")
    res.table("solves", rows, {"ms": "ms", "us_per_element_iteration": "µs", "error_rel": "relative L2 vs Newton",
                               "residual": "relative force residual"})
    res.figure("total_s", time.perf_counter() - t_start, "s")
    res.write()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
