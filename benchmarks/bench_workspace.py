"""Workspace benchmark: 10^6 joint samples -> tips -> box coverage (goal <= 5 s on 2 cores).

Usage: python benchmarks/bench_workspace.py [--samples N] [--repeats R]
Times with time.perf_counter, median of repeats.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli.robot.chain import RobotModel  # noqa: E402
from scissor_cli.robot.workspace import run_workspace  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    res = results_io.Results("bench_workspace", None if args.samples == 1_000_000 else f"samples{args.samples}")
    robot = RobotModel.paper()
    times, result = [], None
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        result = run_workspace(robot, samples=args.samples, seed=0)
        times.append(time.perf_counter() - t0)
    c, r = result.coverage, result.reachable
    print(f"samples {args.samples}: median {np.median(times):.3f} s over {args.repeats} repeats (2-core machine)")
    print("  stages (last run): " + ", ".join(f"{k} {v:.3f} s" for k, v in result.timings.items()))
    print(f"  coverage sampled {100 * c.coverage:.1f}% (>= 3 directions {100 * c.coverage_multi_direction:.1f}%)")
    print(f"  coverage reachable by IK {100 * r.coverage:.1f}% (>= 3 directions "
          f"{100 * r.coverage_multi_direction:.1f}%)")
    print(f"  {r.summary}")
    res.figure("samples", args.samples, "samples")
    res.figure("repeats", args.repeats, "runs")
    res.figure("median_s", float(np.median(times)), "s", goal="<= 5 s")
    for k, v in result.timings.items():
        res.figure(f"stage_{k}_s", v, "s")
    res.figure("coverage_sampled", 100 * c.coverage, "%")
    res.figure("coverage_sampled_3dirs", 100 * c.coverage_multi_direction, "%")
    res.figure("coverage_reachable", 100 * r.coverage, "%")
    res.figure("coverage_reachable_3dirs", 100 * r.coverage_multi_direction, "%")
    res.data("summary", r.summary)
    res.write()


if __name__ == "__main__":
    main()
