"""A cheaper factor to precondition the `nodal` tangent: the linear tetrahedra's (`p1`) on the same mesh; not a test.

A body's trial spends much of its time factoring the `nodal` element's tangent, whose pattern reaches two
rings of neighbours (docs/performance.md, "Where a trial's time goes"). The `p1` tangent on the same mesh and state
has a one-ring pattern and factors several times faster, so it could precondition conjugate gradients on the nodal
tangent in place of the nodal tangent's own factor. On configs/example_dome.yaml (the scene's mesh), at rest and at
push10's equilibrium, this measures for each preconditioner its refactorisation (the symbolic analysis done once
before; median of --repeats), and the conjugate-gradient iterations and time to solve K_ff d = b (b a fixed random
vector) to a relative residual of 1e-2 (a Newton step's forcing term far from the solution) and 1e-5 (a body
trial's settle): the nodal tangent's own factor at the state, the nodal factor kept from 1 mm of stroke before (what
a trial's tracker holds), and the p1 factor at the state.

    PYTHONPATH=. python3 benchmarks/bench_preconditioner.py [--repeats 3]
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
RTOLS = (1e-2, 1e-5)
MAX_ITER = 500


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    runtime.configure()
    from scissor_cli.config import load_config
    from scissor_cli.experiments.build import body_model
    from scissor_cli.mechanics.body_tissue import build_body
    from scissor_cli.solvers.equilibrium import solve_equilibrium
    from scissor_cli.solvers.linear import factorize_free, preconditioned_cg

    res = results_io.Results("bench_preconditioner")
    cfg = load_config(CONFIG)
    scene, mesh, nodal = body_model(cfg)
    if cfg.tissue.mesh.element != "nodal":
        raise SystemExit(f"{CONFIG.name}: expected the `nodal` element, got {cfg.tissue.mesh.element!r}")
    p1 = build_body(scene, mesh, element="p1")
    res.figure("tetrahedra", mesh.n_elements, "1")
    before = solve_equilibrium(nodal, np.array([PUSH_MM - 1.0]), tol=1e-8).x
    pushed = solve_equilibrium(nodal, np.array([PUSH_MM]), start=before, start_strokes=np.array([PUSH_MM - 1.0]),
                               tol=1e-8).x
    b = np.random.default_rng(0).standard_normal(nodal.free_dofs.size)

    def factored(tissue, x):
        """(the slot's factor of tissue's K_ff at x, median refactorisation s, stored entries of the upper K_ff)."""
        K, slot = tissue.stiffness_free(x, upper=True), {}
        factorize_free(tissue, K, slot)  # the symbolic analysis, once
        return slot["free"], results_io.median_s(lambda: factorize_free(tissue, K, slot), args.repeats), K.nnz

    rows = []
    for state, x, earlier in (("rest", nodal.rest, None), (f"push{PUSH_MM:g}", pushed, before)):
        K = nodal.stiffness_free(x, upper=True)
        candidates = [("nodal, at the state", x, nodal), ("p1, at the state", x, p1)]
        if earlier is not None:
            candidates.insert(1, ("nodal, 1 mm of stroke before", earlier, nodal))
        for name, at, tissue in candidates:
            factor, factor_s, nnz = factored(tissue, at)
            row = {"state": state, "preconditioner": name, "kept": at is not x, "factor_s": factor_s,
                   "stored_entries": nnz}
            for rtol in RTOLS:
                d, k, why = preconditioned_cg(K, b, factor, rtol, MAX_ITER)
                if d is None:
                    raise SystemExit(f"{state}, {name}: conjugate gradients did not reach {rtol:g} ({why})")
                row[f"iterations_{rtol:g}"] = k
                row[f"solve_s_{rtol:g}"] = results_io.median_s(
                    lambda K=K, factor=factor, rtol=rtol: preconditioned_cg(K, b, factor, rtol, MAX_ITER), args.repeats)
            rows.append(row)
            print(f"{state}, {name}: refactor {factor_s:.3f} s ({nnz} stored entries); "
                  + "; ".join(f"to {t:g}: {row[f'iterations_{t:g}']} iterations, {row[f'solve_s_{t:g}']:.3f} s"
                              for t in RTOLS), flush=True)
    res.table("preconditioners", rows, {"factor_s": "s", **{f"solve_s_{t:g}": "s" for t in RTOLS}})
    res.data("rtols", list(RTOLS))
    res.write()


if __name__ == "__main__":
    main()
