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


def timed_run(name: str, config: Path, out: Path) -> None:
    run = out / name
    shutil.rmtree(out / ".scissor-cache", ignore_errors=True)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(config), "--jobs", "2", "--out",
                        str(run), "--force"], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    print(f"\n{name}: exit {r.returncode} in {wall / 60:.1f} min (load {os.getloadavg()[0]:.2f})", flush=True)
    text = " ".join(r.stderr.split())
    for line in re.split(r"(?<=\)) (?=[a-z])", text):
        if re.search(r"\d+(\.\d+)? s\b|in \d", line) and len(line) < 400:
            print(f"  {line}")
    if r.returncode != 0:
        print(r.stderr[-2000:])
        return
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
            strategies = [s.decode() if isinstance(s, bytes) else str(s) for s in g["miss_mm"].attrs.get("strategies", [])]
            for k, s in enumerate(strategies):
                v = miss[:, k]
                print(f"  {target} {s}: needle miss median {np.median(v):.3f} / p95 {np.percentile(v, 95):.3f} / "
                      f"max {v.max():.3f} mm over {v.size} trials")
            if "trial_time_s" in g:
                print(f"  {target}: median trial {np.median(g['trial_time_s'][()][done]):.1f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="also configs/example_3d.yaml as shipped")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-needle-3d")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.2f}")
    timed_run("default-slab", default_slab_scene(args.out), args.out)
    if args.full:
        timed_run("example_3d", ROOT / "configs" / "example_3d.yaml", args.out)


if __name__ == "__main__":
    main()
