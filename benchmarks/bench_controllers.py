"""MPC against the built-in PID on the paper's prosthesis scene (docs/model.md §22): the trials of each law.

For each scene, `scissor simulate`'s whole run (through the Python API) with `controller.law: pid` and then
`mpc` (its defaults), the same seed, profile and trials; from each results.h5: the control iterations
(median), the robot's time to tolerance (median over the trials that stopped there), the true miss across the
needle after the loop (median, p95, max), the stroke-limit stops, and the loop's wall time (median).

Scenes: configs/paper_trials_prosthesis.yaml (the layer, its truth the perturbed layer; 4 targets x 30)
and configs/paper_trials_prosthesis_dome.yaml (the same study on the dome, its truth the perturbed body).

    PYTHONPATH=. python3 benchmarks/bench_controllers.py              # about 15 minutes on 2 cores
    PYTHONPATH=. python3 benchmarks/bench_controllers.py --quick      # the layer only, 4 x 5 (variant "quick")

Writes benchmarks/results/bench_controllers.json (or bench_controllers.quick.json).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

import scissor_cli.api as scissor  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCENES = {"layer": "configs/paper_trials_prosthesis.yaml", "body": "configs/paper_trials_prosthesis_dome.yaml"}
LAWS = ("pid", "mpc")


def law_row(scene: str, law: str, trials: int, jobs: int) -> dict:
    """One run of `scene` with `law`: the figures of the module docstring over every target's trials."""
    cfg = scissor.load_config(ROOT / SCENES[scene])
    cfg = cfg.model_copy(update={"controller": cfg.controller.model_copy(update={"law": law}),
                                 "trials": cfg.trials.model_copy(update={"count": trials})})
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        scissor.simulate(cfg, out, jobs=jobs)
        run_s = time.perf_counter() - t0
        per_target = scissor.read_trials(Path(out) / "results.h5")
        histories = _tolerance_times(Path(out) / "results.h5")
    done = [t for t in per_target.values() if "failed" in t]
    ok = np.concatenate([~t["failed"] & (t["stop_reason"] != "no_plan") for t in done])
    cat = {key: np.concatenate([t[key] for t in done])[ok]
           for key in ("iterations", "manipulation_miss_mm", "stop_reason", "time_s")}
    miss = cat["manipulation_miss_mm"]
    return {"scene": scene, "law": law, "trials": int(ok.sum()), "failed": int((~ok).sum()),
            "iterations_median": float(np.median(cat["iterations"])),
            "tolerance_stops": int(np.sum(cat["stop_reason"] == "tolerance")),
            "stroke_limit_stops": int(np.sum(cat["stop_reason"] == "stroke_limit")),
            "time_to_tolerance_s_median": float(np.median(histories)) if histories else None,
            "miss_median_mm": float(np.median(miss)), "miss_p95_mm": float(np.percentile(miss, 95)),
            "miss_max_mm": float(np.max(miss)), "loop_wall_s_median": float(np.median(cat["time_s"])),
            "run_s": run_s}


def _tolerance_times(path: Path) -> list[float]:
    """The robot's time (s) at the end of each trial whose loop stopped at tolerance (its history's last row)."""
    import h5py  # noqa: PLC0415

    times = []
    with h5py.File(path, "r") as f:
        for name in f["trials"]:
            group = f[f"trials/{name}"]
            if "history" not in group:
                continue
            reasons = group["stop_reason"].asstr()[:]
            for k, history in group["history"].items():
                if reasons[int(k)] == "tolerance":
                    columns = list(history.attrs["columns"])
                    times.append(float(history[-1, columns.index("time_s")]))
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the layer only, 5 trials per target")
    ap.add_argument("--jobs", type=int, default=2, help="trial processes")
    args = ap.parse_args()
    res = results_io.Results("bench_controllers", variant="quick" if args.quick else None)
    print(f"machine: {results_io.machine()}, load {results_io.load1()}")
    rows = []
    for scene in (("layer",) if args.quick else tuple(SCENES)):
        for law in LAWS:
            row = law_row(scene, law, 5 if args.quick else 30, args.jobs)
            rows.append(row)
            print(f"{scene} {law}: {row['trials']} trials, iterations {row['iterations_median']:.0f}, "
                  f"tolerance {row['tolerance_stops']}, stroke limit {row['stroke_limit_stops']}, miss median "
                  f"{row['miss_median_mm']:.3f} p95 {row['miss_p95_mm']:.3f} mm ({row['run_s']:.0f} s)", flush=True)
    res.table("laws", rows, units={"time_to_tolerance_s_median": "s", "miss_median_mm": "mm", "miss_p95_mm": "mm",
                                   "miss_max_mm": "mm", "loop_wall_s_median": "s", "run_s": "s"})
    res.write()


if __name__ == "__main__":
    main()
