"""Whole runs with the needle in the slab (docs/model.md §18), timed end to end from nothing; not a test.

Two runs of `scissor simulate --jobs 2`, each into a fresh directory with a fresh cache (so the slab's
ladder, the controller's model and the needle models are all made):

* `default-slab`: configs/example_insertion.yaml with `layer_check: {}` (its slab picked by the default
  accuracy, 0.1 mm), `--truth slab`, the strategies `none` and `loop`, 2 prosthesis trials per target
  (goal: ≤ 10 min on 2 cores);
* `example_3d` (with --full): configs/example_3d.yaml as shipped (30 trials, the budget; goal ≤ 10 min).

Prints each run's wall time, the lines it printed with a time in them (the stages), the needle's miss per
strategy from results.h5 (median / p95 / max), the median trial time, the machine and its load.

    PYTHONPATH=. python benchmarks/bench_needle_3d.py [--full] [--out DIR]
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import results_io
import yaml

ROOT = Path(__file__).resolve().parents[1]


def default_slab_scene(out: Path) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "example_insertion.yaml").read_text())
    data["layer_check"] = {}
    data["insertion"]["strategies"] = ["none", "loop"]
    data["trials"] = {**data.get("trials", {}), "count": 2, "profile": "prosthesis", "truth": "slab"}
    path = out / "default-slab.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def timed_run(name: str, config: Path, out: Path) -> dict:
    run = out / name
    shutil.rmtree(out / ".scissor-cache", ignore_errors=True)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(config), "--jobs", "2", "--out",
                        str(run), "--force"], capture_output=True, text=True, env=results_io.subprocess_env())
    wall = time.perf_counter() - t0
    record = {"run": name, "config": config.name, "exit": r.returncode, "wall_s": wall, "load1": results_io.load1(),
              "stages": [], "misses": [], "trial_s": {}}
    print(f"\n{name}: exit {r.returncode} in {wall / 60:.1f} min (load {os.getloadavg()[0]:.2f})", flush=True)
    text = " ".join(r.stderr.split())
    for line in re.split(r"(?<=\)) (?=[a-z])", text):
        if re.search(r"\d+(\.\d+)? s\b|in \d", line) and len(line) < 400:
            print(f"  {line}")
            record["stages"].append(line)
    if r.returncode != 0:
        print(r.stderr[-2000:])
        return record
    with h5py.File(run / "results.h5") as f:
        for target in f["trials"]:
            g = f[f"trials/{target}"]
            if "miss_mm" not in g or "done" not in g:
                continue
            done = g["done"][()].astype(bool) & (g["stop_reason"].asstr()[()] != "no_plan")  # (zeros: contract.md)
            if not done.any():
                print(f"  {target}: no plan, no insertion")
                continue
            miss = np.atleast_2d(g["miss_mm"][()][done].T).T
            strategies = [s.decode() if isinstance(s, bytes) else str(s)
                          for s in g["miss_mm"].attrs.get("strategies", [])]
            for k, s in enumerate(strategies):
                v = miss[:, k]
                print(f"  {target} {s}: needle miss median {np.median(v):.3f} / p95 {np.percentile(v, 95):.3f} / "
                      f"max {v.max():.3f} mm over {v.size} trials")
                record["misses"].append({"target": target, "strategy": s, "median_mm": np.median(v),
                                         "p95_mm": np.percentile(v, 95), "max_mm": v.max(), "trials": v.size})
            if "trial_time_s" in g:
                print(f"  {target}: median trial {np.median(g['trial_time_s'][()][done]):.1f} s")
                record["trial_s"][target] = np.median(g["trial_time_s"][()][done])
        if "budget" in f:  # the budget's rows, what docs/img/budget_slab.png is drawn from
            from scissor_cli.output.error_budget import results as budget_results  # noqa: PLC0415

            record["budget"] = {"title": str(yaml.safe_load(config.read_text()).get("name", config.stem)),
                                "profile": str(f["budget"].attrs.get("profile", "")),
                                "rows": budget_results.budget_rows(budget_results.read_budget(f))}
    return record


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="also configs/example_3d.yaml as shipped")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-needle-3d")
    args = ap.parse_args()
    res = results_io.Results("bench_needle_3d", "full" if args.full else None)
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.2f}")
    runs = [timed_run("default-slab", default_slab_scene(args.out), args.out)]
    if args.full:
        runs.append(timed_run("example_3d", ROOT / "configs" / "example_3d.yaml", args.out))
    for record in runs:
        if "budget" in record:
            res.data(f"budget_{record['run']}", record.pop("budget"))
    res.table("runs", [{k: v for k, v in rec.items() if k != "misses"} for rec in runs],
              {"wall_s": "s", "trial_s": "s"})
    res.table("misses", [{"run": rec["run"], **m} for rec in runs for m in rec["misses"]],
              {"median_mm": "mm", "p95_mm": "mm", "max_mm": "mm"})
    res.write()


if __name__ == "__main__":
    main()
