"""The paper's 4 x 30 trial studies (prosthesis and ex vivo): wall time and error statistics vs the paper.

Usage: python benchmarks/bench_trials.py [--jobs N]
Goal: each study <= 60 s on the 2-core machine. Prints max/median |x| and |y| error beside the paper's maxima.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.experiments.simulate import Execution, run_simulation  # noqa: E402
from scissor_cli.output.results_sink import RunDirectory  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PAPER_MAX = {"prosthesis": (0.7, 1.7), "ex_vivo": (1.3, 2.5)}  # max |x|, |y| error (mm), paper section 4.2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    res = results_io.Results("bench_trials", None if args.jobs == 2 else f"jobs{args.jobs}")
    rows = []
    for profile in ("prosthesis", "ex_vivo"):
        cfg = load_config(ROOT / "configs" / f"paper_trials_{profile}.yaml")
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            run_simulation(cfg, RunDirectory(tmp), execution=Execution(jobs=args.jobs))
            wall = time.perf_counter() - t0
            with h5py.File(Path(tmp) / "results.h5") as f:
                e = np.concatenate([f[f"trials/{t}/final_error"][:] for t in f["trials"]])
                it = np.concatenate([f[f"trials/{t}/iterations"][:] for t in f["trials"]])
                clear = np.concatenate([f[f"trials/{t}/corridor_clear"][:] for t in f["trials"]])
        a = np.abs(e)
        px, py = PAPER_MAX[profile]
        print(f"{profile}: {len(e)} trials in {wall:.1f} s (jobs {args.jobs}, 2-core machine)")
        print(f"  |x| error: max {a[:, 0].max():.2f} mm (paper {px}), median {np.median(a[:, 0]):.2f}, "
              f"95th percentile {np.percentile(a[:, 0], 95):.2f}")
        print(f"  |y| error: max {a[:, 1].max():.2f} mm (paper {py}), median {np.median(a[:, 1]):.2f}, "
              f"95th percentile {np.percentile(a[:, 1], 95):.2f}")
        print(f"  control iterations: mean {it.mean():.1f}, max {it.max()}; corridor clear in "
              f"{100 * clear.mean():.0f}% of trials")
        rows.append({"profile": profile, "trials": len(e), "wall_s": wall, "jobs": args.jobs,
                     "load1": results_io.load1(),
                     "max_x_mm": a[:, 0].max(), "paper_max_x_mm": px, "median_x_mm": np.median(a[:, 0]),
                     "p95_x_mm": np.percentile(a[:, 0], 95), "max_y_mm": a[:, 1].max(), "paper_max_y_mm": py,
                     "median_y_mm": np.median(a[:, 1]), "p95_y_mm": np.percentile(a[:, 1], 95),
                     "iterations_mean": it.mean(), "iterations_max": int(it.max()),
                     "corridor_clear_pct": 100 * clear.mean()})
    res.table("studies", rows, {"wall_s": "s", **{k: "mm" for k in rows[0] if k.endswith("_mm")},
                                "corridor_clear_pct": "%"})
    res.write()


if __name__ == "__main__":
    main()
