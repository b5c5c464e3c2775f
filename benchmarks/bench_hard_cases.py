"""Hard cases (configs/hard/): iterations and time of every forward case with Newton, ADMM and ADMM+Anderson.

Usage: python benchmarks/bench_hard_cases.py [--scale S]
Prints a Markdown table; times are wall clock of one solve (2-core machine).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.config.body_sections import BodyConfig  # noqa: E402
from scissor_cli.experiments.build import body_model, build_model  # noqa: E402
from scissor_cli.solvers.common import SolverError  # noqa: E402
from scissor_cli.solvers.equilibrium import EquilibriumSolver  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scale", type=float, default=1.0, help="mesh scale (1: the configs' own mesh)")
    args = ap.parse_args()
    res = results_io.Results("bench_hard_cases", None if args.scale == 1.0 else f"scale{args.scale:g}")
    rows = []
    print("| case | forward | elements | solver | iterations | time (s) | residual | outcome |")
    print("|---|---|---|---|---|---|---|---|")
    for path in sorted((ROOT / "configs" / "hard").glob("*.yaml")):
        cfg = load_config(path)
        solvers = (("newton", "newton", 0), ("admm", "admm", 0), ("admm+anderson", "admm", 5))
        if isinstance(cfg, BodyConfig):  # a body: Newton on its own element (ADMM is a layer's solver)
            _, mesh, tissue = body_model(cfg, cache=ROOT / "runs" / ".mesh-cache", scale=args.scale)
            solvers = solvers[:1]
        else:
            _, mesh, tissue = build_model(cfg, mesh_scale=args.scale * cfg.tissue.mesh.scale)
        for label, kind, memory in solvers:
            solver_cfg = cfg.solver.model_copy(update={"kind": kind, "anderson_memory": memory})
            forward = EquilibriumSolver.from_config(tissue, solver_cfg)
            for case in cfg.forward:
                strokes = tissue.scene.strokes_vector(case.strokes)
                try:
                    r = forward.solve_case(strokes)
                    outcome = "converged" if r.converged else r.message
                    row = (r.iterations, f"{r.time_s:.3f}", f"{r.residual:.1e}", outcome)
                    rows.append({"case": path.stem, "forward": case.name, "elements": mesh.n_elements,
                                 "solver": label, "iterations": r.iterations, "time_s": r.time_s,
                                 "residual": r.residual, "converged": bool(r.converged), "outcome": outcome})
                except SolverError as exc:
                    row = ("-", "-", "-", f"failed: {exc}")
                    rows.append({"case": path.stem, "forward": case.name, "elements": mesh.n_elements,
                                 "solver": label, "iterations": None, "time_s": None, "residual": None,
                                 "converged": False, "outcome": f"failed: {exc}"})
                print(f"| {path.stem} | {case.name} | {mesh.n_elements} | {label} | {' | '.join(map(str, row))} |")
            sys.stdout.flush()
    res.table("solves", rows, {"time_s": "s", "residual": "relative force residual"})
    res.write()


if __name__ == "__main__":
    main()
