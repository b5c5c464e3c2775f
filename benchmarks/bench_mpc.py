"""Time of one step of the model-predictive law (`control.mpc.mpc_step`, docs/model.md §22) for 1, 2 and 3 cups.

    python3 benchmarks/bench_mpc.py [--calls 200] [--horizon 10]

Per cup count C, a layer scene's kind of problem: a fixed J (2, C) with
entries of a few tenths (mm of lesion per mm of stroke), the miss across a
needle along +x, strokes drawn in their limits [0, 15] mm, errors of
0.05–10 mm (log-uniform) in random directions, drives of 5 mm/s at 10 Hz (0.5 mm per
frame), horizon H = 10 and action weight ρ = 0.01. One call is the whole
step: the QP built, OSQP set up and run, the polish, the clip. Reported:

* the first call in the process for that C (it also builds the cached
  (C, H) structure: the constraint matrix and the Hessian's pattern);
* the median, 90th percentile and maximum over `--calls` calls, each on
  another drawn problem (fixed seed);
* for scale, the median of the built-in law's step (`allocation.stroke_step`)
  on the same problems.

Wall-clock (time.perf_counter) on the machine results_io records; the
machine has 2 cores and other work may share them, so a maximum is one
unlucky call as often as a hard problem. Writes
benchmarks/results/bench_mpc.json (another --calls or --horizon: a variant).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli.control.allocation import stroke_step  # noqa: E402
from scissor_cli.control.mpc import mpc_step  # noqa: E402

#: J (2, C) per cup count: columns like the layer scenes' cups (a few tenths, mixed signs)
JACOBIANS = {
    1: np.array([[0.45], [-0.30]]),
    2: np.array([[0.6, -0.2], [0.1, 0.5]]),
    3: np.array([[0.6, -0.2, 0.3], [0.1, 0.5, -0.4]]),
}
AXIS = np.array([1.0, 0.0])
LO_MM, HI_MM, SPEED_MM_PER_S, DT_S, RHO = 0.0, 15.0, 5.0, 0.1, 0.01


def problems(C: int, n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """n (error (2,) mm, strokes (C,) mm) pairs: errors of 0.05–10 mm in any direction, strokes in the limits."""
    rng = np.random.default_rng(seed + C)
    out = []
    for _ in range(n):
        angle, size = rng.uniform(0, 2 * np.pi), 10 ** rng.uniform(np.log10(0.05), 1.0)
        out.append((size * np.array([np.cos(angle), np.sin(angle)]), rng.uniform(LO_MM, HI_MM, C)))
    return out


def time_cups(C: int, calls: int, horizon: int) -> dict:
    """The row of one cup count: first call, median / p90 / max over the calls, and stroke_step's median (ms)."""
    J = JACOBIANS[C]
    lo, hi, m = np.full(C, LO_MM), np.full(C, HI_MM), np.full(C, SPEED_MM_PER_S * DT_S)
    cases = problems(C, calls + 1)

    def step(e, s):
        return mpc_step(J, e, s, lo, hi, m, horizon, RHO, AXIS)

    t0 = time.perf_counter()
    step(*cases[0])
    first = time.perf_counter() - t0
    times, limited = [], 0
    for e, s in cases[1:]:
        t0 = time.perf_counter()
        u = step(e, s)
        times.append(time.perf_counter() - t0)
        limited += bool(np.any(np.abs(u) >= m - 1e-12))
    builtin = []
    for e, s in cases[1:]:
        t0 = time.perf_counter()
        stroke_step(J, e, s, lo, hi, m, AXIS)
        builtin.append(time.perf_counter() - t0)
    ms = 1e3 * np.array(times)
    return {"cups": C, "horizon": horizon, "calls": calls, "first_ms": 1e3 * first, "median_ms": float(np.median(ms)),
            "p90_ms": float(np.percentile(ms, 90)), "max_ms": float(ms.max()),
            "speed_limited_share": limited / calls, "stroke_step_median_ms": 1e3 * float(np.median(builtin))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=200, help="timed calls per cup count (each another problem)")
    ap.add_argument("--horizon", type=int, default=10, help="the law's horizon H (frames)")
    args = ap.parse_args()
    variant = None if (args.calls, args.horizon) == (200, 10) else f"calls{args.calls}-h{args.horizon}"
    res = results_io.Results("bench_mpc", variant=variant)
    print(f"machine: {results_io.machine()}, load {results_io.load1()}")
    rows = []
    for C in (3, 1, 2):  # 3 first: its first call is the process's first (the goal's case)
        row = time_cups(C, args.calls, args.horizon)
        rows.append(row)
        print(f"C={C} H={args.horizon}: first {row['first_ms']:.2f} ms, median {row['median_ms']:.2f} ms, "
              f"p90 {row['p90_ms']:.2f} ms, max {row['max_ms']:.2f} ms "
              f"({100 * row['speed_limited_share']:.0f} % of moves at the speed limit); "
              f"stroke_step median {row['stroke_step_median_ms']:.3f} ms", flush=True)
        res.figure(f"c{C}_median_ms", row["median_ms"], "ms", calls=args.calls, horizon=args.horizon)
        res.figure(f"c{C}_first_ms", row["first_ms"], "ms", horizon=args.horizon)
    res.table("mpc_step", sorted(rows, key=lambda r: r["cups"]),
              units={"first_ms": "ms", "median_ms": "ms", "p90_ms": "ms", "max_ms": "ms",
                     "stroke_step_median_ms": "ms"})
    res.write()


if __name__ == "__main__":
    main()
