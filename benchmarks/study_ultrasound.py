"""Camera against ultrasound (docs/model.md §17, docs/performance.md "Ultrasound in the loop"); a study, not a test.

Runs `scissor simulate --jobs 2` for each pair (camera, ultrasound) of:

* the paper's prosthesis scene, layer truth, with the error budget
  (configs/paper_trials_prosthesis.yaml, configs/paper_trials_prosthesis_ultrasound.yaml);
* the same against the slab (…_slab.yaml, …_slab_ultrasound.yaml);
* configs/example_ultrasound.yaml (slab truth, the needle, the surrogate) and its camera twin (the same file
  without `imaging`), without the budget unless --budget;

30 trials per target unless --trials. Then `scissor report` over all of them (summary.md with the sensor
column, sensors.md: manipulation miss, needle miss and the sensor's error per run and target, budget.md).
Prints each run's wall time and trial time, and per pair the ultrasound's over the camera's (the goal: a
slab-truth study with ultrasound ≤ 2× the camera's).

    PYTHONPATH=. python benchmarks/study_ultrasound.py [--trials 30] [--only paper-layer paper-slab example]
        [--budget] [--out runs/study-ultrasound]
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

import results_io
import yaml

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"


def pairs(out: Path, budget: bool) -> dict[str, tuple[Path, Path, list[str]]]:
    """{study: (camera config, ultrasound config, extra options)}; the example's pair with its budget only if
    `budget`."""
    example = yaml.safe_load((CONFIGS / "example_ultrasound.yaml").read_text())
    example["trials"]["budget"] = budget  # (the shipped file asks for it: its rows rerun every slab trial)
    ultrasound_twin = out / "example_ultrasound.yaml"
    ultrasound_twin.write_text(yaml.safe_dump(example, sort_keys=False))
    example.pop("imaging")
    example["name"] = "paper-push-camera"
    camera_twin = out / "example_camera.yaml"
    camera_twin.write_text(yaml.safe_dump(example, sort_keys=False))
    return {
        "paper-layer": (CONFIGS / "paper_trials_prosthesis.yaml", CONFIGS / "paper_trials_prosthesis_ultrasound.yaml",
                        ["--budget"]),
        "paper-slab": (CONFIGS / "paper_trials_prosthesis_slab.yaml",
                       CONFIGS / "paper_trials_prosthesis_slab_ultrasound.yaml", []),
        "example": (camera_twin, ultrasound_twin, []),
    }


def run(config: Path, out: Path, trials: int, extra: list[str]) -> tuple[float, float]:
    """(wall time s, the trials' time s from the run's own message)."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(config), "--jobs", "2", "--trials",
                        str(trials), "--out", str(out), "--force", *extra], capture_output=True, text=True,
                       env=results_io.subprocess_env())
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        print(r.stderr[-3000:])
        raise SystemExit(f"{config.name}: exit {r.returncode}")
    found = re.search(r"trials done in ([\d.]+) s", " ".join(r.stderr.split()))
    return wall, float(found.group(1)) if found else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=30)
    ap.add_argument("--only", nargs="+", default=None)
    ap.add_argument("--budget", action="store_true", help="the example's pair with its budget too")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "study-ultrasound")
    args = ap.parse_args()
    res = results_io.Results("study_ultrasound", ".".join(p for p in (
        None if args.trials == 30 else f"trials{args.trials}", "only-" + "-".join(args.only) if args.only else None,
        "budget" if args.budget else None) if p) or None)
    timings = []
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.2f}", flush=True)
    dirs = []
    for name, (camera, ultrasound, extra) in pairs(args.out, args.budget).items():
        if args.only and name not in args.only:
            continue
        times = {}
        for sensor, config in (("camera", camera), ("ultrasound", ultrasound)):
            out = args.out / f"{name}-{sensor}"
            times[sensor] = run(config, out, args.trials, extra)
            dirs.append(str(out))
            print(f"{name} {sensor}: {times[sensor][0] / 60:.1f} min in all, trials {times[sensor][1]:.0f} s "
                  f"(load {os.getloadavg()[0]:.2f})", flush=True)
            timings.append({"study": name, "sensor": sensor, "config": config.name, "wall_s": times[sensor][0],
                            "trials_s": times[sensor][1], "load1": results_io.load1(), "run": out.name})
        print(f"{name}: ultrasound / camera = {times['ultrasound'][0] / times['camera'][0]:.2f} in all, "
              f"{times['ultrasound'][1] / times['camera'][1]:.2f} for the trials", flush=True)
    r = subprocess.run([sys.executable, "-m", "scissor_cli", "report", *dirs, "--out", str(args.out / "report")],
                       capture_output=True, text=True)
    print(r.stdout[-6000:])
    record(res, dirs, timings)
    res.write()


def record(res: results_io.Results, dirs: list[str], timings: list[dict]) -> None:
    """Each run's times, the report's summary and sensor rows, and each budget's rows."""
    import h5py  # noqa: PLC0415

    sys.path.insert(0, str(ROOT))
    from scissor_cli.output.error_budget import results as budget_results  # noqa: PLC0415
    from scissor_cli.output.imaging.report import sensor_rows  # noqa: PLC0415
    from scissor_cli.output.report import load_run, summary_rows  # noqa: PLC0415

    res.table("runs", timings, {"wall_s": "s", "trials_s": "s"})
    res.table("summary", summary_rows([load_run(Path(d), True) for d in dirs]),
              {k: "mm" for k in ("median_x", "max_x", "p95_x", "median_y", "max_y", "p95_y", "miss_median",
                                 "miss_p95", "miss_max")})
    res.table("sensors", [dict(row, run=Path(d).name) for d in dirs for row in sensor_rows(Path(d).name,
                                                                                         Path(d) / "results.h5")])
    budgets = []
    for d in dirs:
        with h5py.File(Path(d) / "results.h5", "r") as f:
            rows = budget_results.budget_rows(budget_results.read_budget(f))
            budgets += [dict(row, run=Path(d).name) for row in rows]
    res.table("budget", budgets, {k: "mm" for k in budgets[0] if k.endswith("_mm")} if budgets else {})


if __name__ == "__main__":
    main()
