"""One thread against two in one process (`runtime.set_threads`), on the body's loops and solves; not a test.

On configs/example_dome.yaml (its default element and mesh, and the same dome at mesh scale SCALE_30K, about
30k tetrahedra), each with one compiled-loop thread and with two, the settings alternating repeat by repeat in
this process (the machine's drift falls on both alike):

* the loops the threads split, at push10's equilibrium: the nodal element's gradient, the tangent K_ff (the
  elements' packed Hessians and the two-ring coupling), the float32 factorisation of K_ff on its CHOLMOD layout
  and one float32 solve (`solvers/supernode_tree.py`: each part's and the top's share of the factorisation's
  flops beside them);
* push10 from rest (`bench_body`'s goal) and a 50 mm `none` insertion of T1 along −x in 0.5 mm steps
  (`bench_body_insertion`'s goal, at about 30k tetrahedra);
* the answers: each pair must be the same to the bit (the parts are fixed), and the script stops if not.

    PYTHONPATH=. python3 benchmarks/bench_threads.py [--repeats 5]     # about 2 minutes on 2 cores

Writes benchmarks/results/bench_threads.json.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import results_io
from bench_body_insertion import SCALE_30K, lesion_path

from scissor_cli import runtime

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"
#: kernel calls per timed repeat (a repeat's time is divided by this)
CALLS = {"gradient": 20, "tangent": 3, "float32 factorisation": 3, "float32 solve": 20}


def alternate(call, repeats: int, calls: int = 1) -> tuple[dict, dict]:
    """call() timed under one thread and two in turn, repeat by repeat: (median s per call, answer) per count."""
    times, answers = {1: [], 2: []}, {}
    for _ in range(repeats):
        for n in (1, 2):
            runtime.set_threads(n)
            t0 = time.perf_counter()
            for _ in range(calls):
                answers[n] = call()
            times[n].append((time.perf_counter() - t0) / calls)
    runtime.set_threads(runtime.MOST_THREADS)
    return {n: float(np.median(t)) for n, t in times.items()}, answers


def same_bits(a, b) -> bool:
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(same_bits(x, y) for x, y in zip(a, b))
    return bool(np.array_equal(np.asarray(a), np.asarray(b)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="repeats per count (kernels; the solves take 3, 2)")
    args = ap.parse_args()
    runtime.configure()
    from scissor_cli.config import load_config
    from scissor_cli.config.sections import InsertionConfig
    from scissor_cli.experiments.build import body_model
    from scissor_cli.insertion import InsertionOptions, NeedleParams, run_strategies
    from scissor_cli.solvers.equilibrium import solve_equilibrium
    from scissor_cli.solvers.linear import factorize_free
    from scissor_cli.solvers.single_factor import SingleFactorizer
    from scissor_cli.solvers.supernode_tree import factor_flops

    res = results_io.Results("bench_threads")
    res.data("cores", results_io.machine()["cores"])
    cfg = load_config(CONFIG)
    scene, mesh, tissue = body_model(cfg)
    push = np.array([10.0])
    rows = []

    def row(what: str, size: int, times: dict, answers: dict, repeats: int) -> None:
        if not same_bits(answers[1], answers[2]):
            raise SystemExit(f"{what}: one thread and two gave different numbers")
        rows.append({"what": what, "tetrahedra": size, "one_s": times[1], "two_s": times[2],
                     "speedup": times[1] / times[2], "repeats": repeats})
        print(f"  {what} ({size} tetrahedra): {times[1] * 1e3:.1f} ms on one thread, {times[2] * 1e3:.1f} ms on two "
              f"({times[1] / times[2]:.2f}×)", flush=True)

    print(f"{cfg.name}: {mesh.n_elements} tetrahedra ({cfg.tissue.mesh.element}), {args.repeats} repeats", flush=True)
    x = solve_equilibrium(tissue, push, tol=1e-8).x
    K_upper = tissue.stiffness_free(x, upper=True)
    layout = factorize_free(tissue, K_upper, {}).single()
    factorizer = SingleFactorizer(layout, K_upper.indptr, K_upper.indices)
    b = np.random.default_rng(0).standard_normal(K_upper.shape[0])
    kernels = {"gradient": lambda: tissue.energy_gradient(x),
               "tangent": lambda: tissue.stiffness_free(x, upper=True).data,
               "float32 factorisation": lambda: factorizer.factor(K_upper.data).blocks,
               "float32 solve": lambda: layout.solve(b)}
    for what, call in kernels.items():
        row(what, mesh.n_elements, *alternate(call, args.repeats, CALLS[what]), args.repeats)
    flops = factor_flops(layout.starts, layout.row_ptr)
    cuts = layout.cuts
    shares = [float(flops[cuts[k]:cuts[k + 1]].sum() / flops.sum()) for k in range(cuts.size - 1)]
    res.data("factor_shares", {"parts": shares[:-1], "top": shares[-1], "supernodes": int(cuts[-1])})
    print(f"  the factorisation's flops: parts {', '.join(f'{s:.0%}' for s in shares[:-1])}, top {shares[-1]:.0%}",
          flush=True)
    row("push10 from rest", mesh.n_elements,
        *alternate(lambda: solve_equilibrium(tissue, push, tol=1e-8).x, 3), 3)

    _, mesh_30k, tissue_30k = body_model(cfg, scale=SCALE_30K)
    strokes = np.zeros(len(scene.cups))
    x0 = solve_equilibrium(tissue_30k, strokes).x
    params = NeedleParams.from_config(InsertionConfig(), cfg.needle, cfg.tissue.mesh)
    path = lesion_path(mesh_30k, scene.targets[0], 50.0)

    def insertion():
        r = run_strategies(tissue_30k, x0, strokes, {"none": path}, params,
                           {"none": InsertionOptions("none", cfg.controller, keep_displacement=False)})[0]
        return r.target, r.needle_force_mN

    row("50 mm insertion, `none`", mesh_30k.n_elements, *alternate(insertion, 2), 2)
    res.table("loops", rows, {"one_s": "s", "two_s": "s"})
    res.write()


if __name__ == "__main__":
    main()
