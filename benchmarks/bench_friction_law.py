"""What the needle's friction law gives (docs/model.md §12): the shipped insertion scenes, and step refinement.

Run once with the package as it is and once with an earlier commit's on PYTHONPATH, each with its own
--label (results/bench_friction_law.<label>.json, the package's commit in its data); docs/performance.md
sets the two results side by side ("Friction with state"). It uses only
what every version of the package has (configs, `scissor simulate`, `run_insertion`).

* `scenes`: `scissor simulate CONFIG --trials 0` on each shipped config with an `insertion:` section
  (configs/example_insertion.yaml, example_full.yaml, example_ultrasound.yaml and, with --slab,
  example_3d.yaml, whose nominal insertion runs in the slab): per target and strategy, from results.h5,
  the miss and depth error at the end, the final needle force and the stuck and slipping counts.
* `steps`: a layer where nodes stick — the example scene (default mesh), f_s 40, f_k 10 mN/mm, F_tip
  100 mN, a needle from the left skin along +x through T1 at rest, 45 mm — inserted in 0.5, 0.25,
  0.125 mm steps (and 0.0625, 0.03125 with --fine): the target's end position, the needle force, the
  stuck count, each step's distance from the next finer one, the wall time.

    PYTHONPATH=. python benchmarks/bench_friction_law.py --label after [--slab] [--fine]
    PYTHONPATH=/path/to/older/checkout python benchmarks/bench_friction_law.py --label before [--slab]
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import results_io
import yaml

ROOT = Path(__file__).resolve().parents[1]
SCENES = ["example_insertion", "example_full", "example_ultrasound"]


def scenes(names: list[str], out: Path) -> list[dict]:
    rows = []
    for name in names:
        run = out / name
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(ROOT / "configs" / f"{name}.yaml"),
                            "--trials", "0", "--jobs", "2", "--out", str(run), "--force", "--quiet"],
                           capture_output=True, text=True, cwd=out)  # (not this checkout's folder: `-m` puts the
        # working directory first on the path, ahead of the PYTHONPATH that picks the package to measure)
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            raise SystemExit(f"{name}: exit {r.returncode}\n{r.stderr[-2000:]}")
        with h5py.File(run / "results.h5", "r") as f:
            for target in f["insertion"]:
                for strategy, g in f["insertion"][target].items():
                    rows.append(dict(scene=name, target=target, strategy=strategy,
                                     miss_mm=float(g.attrs["miss_mm"]), depth_error_mm=float(g.attrs["depth_error_mm"]),
                                     force_mN=float(g["needle_force_mN"][-1]), stuck=int(g["stuck"][-1]),
                                     slipping=int(g["slipping"][-1]), steps=int(g.attrs["steps"])))
        print(f"{name}: {wall:.0f} s", flush=True)
    return rows


def steps(step_sizes: list[float]) -> list[dict]:
    from scissor_cli import runtime
    runtime.configure()
    from scissor_cli.config import load_config
    from scissor_cli.experiments.build import build_model
    from scissor_cli.insertion import InsertionOptions, NeedleParams, NeedlePath, run_insertion

    data = yaml.safe_load((ROOT / "configs" / "example.yaml").read_text())
    data["insertion"] = {"step_mm": 0.5, "friction_static_mN_per_mm": 40.0, "friction_kinetic_mN_per_mm": 10.0,
                         "tip_force_mN": 100.0, "tip_zone_mm": 2.0, "strategies": ["none"]}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sticking.yaml"
        path.write_text(yaml.safe_dump(data))
        cfg = load_config(path)
    tissue = build_model(cfg)[2]
    params = NeedleParams.from_config(cfg.insertion, cfg.needle, cfg.tissue.mesh)
    t1 = next(t for t in cfg.targets if t.name == "T1")
    target = np.asarray(t1.position_mm, float)
    path = NeedlePath(np.array([0.0, target[1]]), np.array([1.0, 0.0]), 45.0, target)
    rows = []
    for step in step_sizes:
        t0 = time.perf_counter()
        r = run_insertion(tissue, tissue.rest.copy(), np.zeros(tissue.n_cups), path,
                          dataclasses.replace(params, step_mm=step), InsertionOptions("none", keep_displacement=False))
        rows.append(dict(step_mm=step, target_end_mm=r.target[-1].tolist(), force_mN=float(r.needle_force_mN[-1]),
                         stuck=int(r.stuck[-1]), slipping=int(r.slipping[-1]),
                         steps_with_stuck=int(np.sum(r.stuck > 0)), unsettled=int(r.unsettled),
                         time_s=time.perf_counter() - t0))
        print(f"step {step:g} mm: target {r.target[-1].round(4)}, force {r.needle_force_mN[-1]:.1f} mN, "
              f"stuck {r.stuck[-1]}, {rows[-1]['time_s']:.2f} s", flush=True)
    for a, b in zip(rows, rows[1:]):
        a["to_half_step_mm"] = float(np.linalg.norm(np.subtract(a["target_end_mm"], b["target_end_mm"])))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", required=True, help="the result's variant: results/bench_friction_law.<label>.json")
    ap.add_argument("--slab", action="store_true", help="configs/example_3d.yaml too (minutes)")
    ap.add_argument("--fine", action="store_true", help="steps of 0.0625 and 0.03125 mm too")
    ap.add_argument("--out", help="where the runs go (default: a temporary folder)")
    args = ap.parse_args()
    import scissor_cli

    res = results_io.Results("bench_friction_law", args.label)
    step_rows = steps([0.5, 0.25, 0.125] + ([0.0625, 0.03125] if args.fine else []))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out) if args.out else Path(tmp)
        scene_rows = scenes(SCENES + (["example_3d"] if args.slab else []), out)
    package = Path(scissor_cli.__file__).parent
    commit = subprocess.run(["git", "-C", str(package), "rev-parse", "HEAD"], capture_output=True, text=True).stdout
    res.data("package", {"path": str(package), "commit": commit.strip()})
    res.table("steps", step_rows, units={"step_mm": "mm", "target_end_mm": "mm", "force_mN": "mN",
                                         "to_half_step_mm": "mm", "time_s": "s"})
    res.table("scenes", scene_rows, units={"miss_mm": "mm", "depth_error_mm": "mm", "force_mN": "mN"})
    res.write()
    print(f"wrote {res.path}")


if __name__ == "__main__":
    main()
