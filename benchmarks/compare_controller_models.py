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
that pins its slab (`accuracy_mm: null`) run on the slab its ladder picks. The `slab` rows steer with the
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

import results_io
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
    stem = Path(args.config).stem
    res = results_io.Results("compare_controller_models", ".".join(p for p in (
        None if stem == "example_full" else stem, None if args.trials == 6 else f"trials{args.trials}",
        "reachable" if args.reachable else None, "only-" + "-".join(args.only) if args.only else None,
        None if args.localisation is None else f"localisation{args.localisation:g}",
        None if args.accuracy_mm is None else f"accuracy{args.accuracy_mm:g}",
        None if args.stop_frames is None else f"stop{args.stop_frames}", "needle" if args.needle else None,
        None if args.profile is None else args.profile) if p) or None)
    walls = {}
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
                            "--jobs", str(args.jobs), "--out", str(out / name), "--force"],
                           env=results_io.subprocess_env())
        print(f"{name}: exit {r.returncode} in {time.perf_counter() - t0:.0f} s", flush=True)
        walls[name] = {"variant": name, "exit": r.returncode, "wall_s": time.perf_counter() - t0,
                       "load1": results_io.load1()}
        if r.returncode == 0:
            runs.append(str(out / name))
    subprocess.run([sys.executable, "-m", "scissor_cli", "report", *runs, "--out", str(out / "report")], check=False,
                   env=results_io.subprocess_env())
    record(res, runs, list(walls.values()))
    res.write()


def record(res: results_io.Results, runs: list[str], walls: list[dict]) -> None:
    """The report's summary rows (per run and target), the runs' wall times and, per model kind, the target paths
    that `controller_models.png` draws (what docs/img/controller_models_*.png are drawn from)."""
    import h5py  # noqa: PLC0415

    sys.path.insert(0, str(ROOT))
    from scissor_cli.output.controller_model import read_paths  # noqa: PLC0415
    from scissor_cli.output.report import load_run, summary_rows  # noqa: PLC0415

    res.table("runs", walls, {"wall_s": "s"})
    rows = summary_rows([load_run(Path(r), True) for r in runs])
    res.table("summary", rows, {"time_per_iteration_s": "s", "model_build_s": "s", "time_s_mean": "s",
                                "corridor_clear_pct": "%", **{k: "mm" for k in (
                                    "mean_x", "median_x", "max_x", "p95_x", "mean_y", "median_y", "max_y", "p95_y",
                                    "miss_median", "miss_p95", "miss_max", "along_median_abs", "model_error_mm",
                                    "plan_model_error_mm")}})
    paths, scene = {}, ""
    for r in runs:
        with h5py.File(Path(r) / "results.h5", "r") as f:
            p = read_paths(f)
            scene = str(f.attrs.get("config_yaml", ""))
        if p is not None and p.kind not in paths:
            paths[p.kind] = {"kind": p.kind, "cup_names": list(p.cup_names), "target_names": list(p.target_names),
                             "strokes": p.strokes, "model": p.model, "layer": p.layer, "slab_strokes": p.slab_strokes,
                             "slab": p.slab, "rest": p.rest}
    title = next((line.split(":", 1)[1].strip() for line in scene.splitlines() if line.startswith("name:")), "scene")
    res.data("model_paths", {"title": title, "paths": list(paths.values())})


if __name__ == "__main__":
    main()
