"""Slab-truth trials on a Dask LocalCluster of 1, 2, 4 single-thread workers: time and bit-identity (not a test).

    python benchmarks/bench_dask_slab.py [CONFIG] [--trials N] [--workers 1 2 4] [--out DIR]

Default CONFIG: configs/paper_trials_prosthesis_slab.yaml with `trials.truth: slab`, N trials of its
first target (default 8), no insertion. A `layer_check.accuracy_mm` is resolved once here (the
chosen grading written into the config the runs share), so each run times its trials, not the ladder.
Every run is `scissor simulate --executor dask --scheduler <the cluster>`; the first also solves the
nominal slab's start, which the others read from the cache beside the runs (DIR/.scissor-cache).
Beside them, the local pool with `--jobs 2` as the peer. Prints, with the machine's load: workers,
the trial stage's wall time (the run's "trials done in"), the speed-up against one worker, and
whether every trial's final error equals the one-worker run's bit for bit.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt (the workers inherit its OPENBLAS_CORETYPE)
import results_io  # noqa: E402

from scissor_cli.config import load_config, resolved_yaml  # noqa: E402
from scissor_cli.experiments.layer_check_stage import slab_resolution_stage  # noqa: E402
from scissor_cli.experiments.run_cache import CACHE_DIR  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def scene_for(config: Path, trials: int, out: Path) -> Path:
    data = yaml.safe_load(config.read_text())
    data.pop("insertion", None)
    data["targets"] = data["targets"][:1]
    data["trials"] = {**data.get("trials", {}), "truth": "slab", "count": trials}
    path = out / "scene.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    cfg = load_config(path)
    if cfg.layer_check is not None and cfg.layer_check.accuracy_mm is not None:
        cfg, choice = slab_resolution_stage(cfg, out / CACHE_DIR)
        path.write_text(resolved_yaml(cfg))
        print(f"slab grading: {choice.explain()}", flush=True)
    return path


def run(scene: Path, out: Path, extra: list[str]) -> tuple[float, dict]:
    r = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(scene), "--out", str(out), "--force",
                        *extra], capture_output=True, text=True, env=results_io.subprocess_env())
    if r.returncode != 0:
        sys.exit(f"{out.name}: exit {r.returncode}\n{r.stderr[-2000:]}")
    seconds = float(re.search(r"trials done in ([0-9.]+) s", r.stdout + r.stderr).group(1))
    with h5py.File(out / "results.h5") as f:
        finals = {t: f[f"trials/{t}/final_error"][()] for t in f["trials"] if "final_error" in f[f"trials/{t}"]}
    return seconds, finals


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "paper_trials_prosthesis_slab.yaml"))
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench-dask-slab"))
    args = ap.parse_args()
    stem = Path(args.config).stem
    res = results_io.Results("bench_dask_slab", ".".join(p for p in (
        None if stem == "paper_trials_prosthesis_slab" else stem, None if args.trials == 8 else f"trials{args.trials}",
        None if args.workers == [1, 2, 4] else "workers" + "-".join(map(str, args.workers))) if p) or None)
    from dask.distributed import LocalCluster  # noqa: PLC0415 - the cluster extra: pip install -e '.[cluster]'

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.2f}; {args.config}, {args.trials} slab-truth trials", flush=True)
    scene = scene_for(Path(args.config), args.trials, out)
    rows, reference = [], None
    for n in args.workers:
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
            seconds, finals = run(scene, out / f"dask-{n}", ["--executor", "dask", "--scheduler",
                                                             cluster.scheduler_address])
        reference = finals if reference is None else reference
        same = all(np.array_equal(reference[t], finals[t]) for t in reference)
        rows.append((f"Dask, {n} worker(s)", seconds, same, results_io.load1()))
        print(f"  {rows[-1][0]}: trials {seconds:.1f} s, identical {same}, load {os.getloadavg()[0]:.2f}", flush=True)
    seconds, finals = run(scene, out / "local-2", ["--jobs", "2"])
    rows.append(("local pool, --jobs 2", seconds, all(np.array_equal(reference[t], finals[t]) for t in reference),
                 results_io.load1()))
    base = rows[0][1]
    print("\n| executor | trial stage | speed-up against 1 worker | final errors identical |\n|---|---|---|---|")
    for name, s, same, _ in rows:
        print(f"| {name} | {s:.1f} s | {base / s:.2f}× | {'yes' if same else 'NO'} |")
    res.table("executors", [{"executor": name, "trials_s": s, "speedup": base / s, "identical": bool(same),
                             "load1": load} for name, s, same, load in rows],
              {"trials_s": "s (the run's trial stage)", "speedup": "against 1 worker"})
    res.figure("trials", args.trials, "slab-truth trials")
    res.write()


if __name__ == "__main__":
    main()
