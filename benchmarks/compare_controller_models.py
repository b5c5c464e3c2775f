"""The controller models against the slab truth (docs/performance.md, "Controller models"): runs and report.

Writes one variant of a scene per (controller.model, jacobian_update) — the
scene with `trials.truth: slab` and without its insertion section (with
`--needle`, with it: the report then holds each model's needle miss per
strategy beside the manipulation's, insertion_summary.md) — runs
`scissor simulate VARIANT --trials N --jobs J` for each and `scissor report`
over them (the summary table has the controller, stroke-limit stops, time
per iteration, the model's build time and error). `--reachable` makes the
variant of docs/performance.md: T2 alone, desired y 21.0 mm.

    python benchmarks/compare_controller_models.py [CONFIG] [--trials 6] [--jobs 2] [--reachable]
        [--only layer-none surrogate-none ...] [--localisation MM] [--accuracy-mm MM] [--stop-frames N]
        [--needle] [--profile ideal|prosthesis|ex_vivo] [--out DIR]

Default CONFIG: configs/example_full.yaml; the paper's scene is
configs/paper_trials_prosthesis_slab.yaml (its slab grading is chosen by
accuracy in each variant's run, about 4 min each). `--localisation 0` takes
the profile's localisation error out (what is left is the loop's own); `--accuracy-mm 0.1` lets a config
that pins its slab (example_full.yaml) run on the slab its ladder picks. The `slab` rows steer with the
nominal slab itself (the reference: one slab solve per control iteration). A slab-truth trial takes about
3 s on the paper scene's picked slab (a minute on a pinned 128k one); a surrogate is trained once and cached in
DIR/.scissor-cache.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
MODELS = [("layer", "none"), ("layer", "broyden"), ("calibrated", "none"), ("calibrated", "broyden"),
          ("surrogate", "none"), ("surrogate", "broyden"), ("slab", "none"), ("slab", "broyden")]


def variant(scene: dict, model: str, update: str, args) -> dict:
    data = dict(scene)
    if args.accuracy_mm is not None:
        data["layer_check"] = {**data.get("layer_check", {}), "accuracy_mm": args.accuracy_mm}
    if not args.needle:
        data.pop("insertion", None)
    data["trials"] = {**data.get("trials", {}), "truth": "slab", "budget": False}
    if args.profile is not None:
        data["trials"]["profile"] = args.profile
    localisation_mm, stop_frames = args.localisation, args.stop_frames
    if localisation_mm is not None:
        data["trials"]["localisation_error_mm"] = localisation_mm
    data["controller"] = {**data.get("controller", {}), "model": model, "jacobian_update": update}
    if stop_frames is not None:
        data["controller"]["stop_frames"] = stop_frames
    if args.reachable:
        data["targets"] = [dict(t, desired_mm=[58.0, 21.0]) for t in data["targets"] if t["name"] == "T2"]
    return data


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "example_full.yaml"))
    ap.add_argument("--trials", type=int, default=6)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--reachable", action="store_true", help="T2 alone with a desired point the slab can reach")
    ap.add_argument("--only", nargs="+", metavar="MODEL-UPDATE", help="a subset of the variants, e.g. surrogate-none")
    ap.add_argument("--localisation", type=float, default=None, help="override trials.localisation_error_mm (mm)")
    ap.add_argument("--accuracy-mm", type=float, default=None,
                    help="set layer_check.accuracy_mm: the slab the ladder picks instead of the one the config pins")
    ap.add_argument("--stop-frames", type=int, default=None,
                    help="set controller.stop_frames: stop on the mean of this many camera frames")
    ap.add_argument("--needle", action="store_true", help="keep the scene's insertion: the needle miss per model")
    ap.add_argument("--profile", default=None, help="override trials.profile")
    ap.add_argument("--out", default=str(ROOT / "runs" / "controller-models"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = yaml.safe_load(Path(args.config).read_text())
    runs = []
    for model, update in MODELS:
        name = f"{model}-{update}"
        if args.only and name not in args.only:
            continue
        path = out / f"{name}.yaml"
        path.write_text(yaml.safe_dump(variant(scene, model, update, args), sort_keys=False))
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(path), "--trials", str(args.trials),
                            "--jobs", str(args.jobs), "--out", str(out / name), "--force"])
        print(f"{name}: exit {r.returncode} in {time.perf_counter() - t0:.0f} s", flush=True)
        if r.returncode == 0:
            runs.append(str(out / name))
    subprocess.run([sys.executable, "-m", "scissor_cli", "report", *runs, "--out", str(out / "report")], check=False)


if __name__ == "__main__":
    main()
