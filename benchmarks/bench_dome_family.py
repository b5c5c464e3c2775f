"""How the paper's dome study depends on what the paper leaves open (docs/model.md §19, "The paper's experiment").

The paper gives the prosthesis's stiffness and shape (a flat hemisphere) but not its radius, its height, the
targets' height or the cup's patch. configs/paper_trials_prosthesis_dome.yaml assumes one value of each; here
each assumption is changed alone, both ways, and every set-up is run — a family of set-ups, each reported, none
tuned to the paper's numbers. The cup stays on the skin at the targets' height, on the +y side (so the paper's
layer, the section through the targets, still holds it). Each set-up runs `scissor simulate --jobs 2` with
--trials per target (default 10) and the controller's model the body and the paper's layer (holding the side
opposite the cup); a row gives the maxima of |x|, |y| (the paper's 0.7 / 1.7 mm) and |z| over the targets
that have a plan.

    PYTHONPATH=. python3 benchmarks/bench_dome_family.py [--trials 10] [--models body,layer]
"""

from __future__ import annotations

import argparse
import copy

import numpy as np
import results_io
import yaml
from bench_dome_study import PAPER_MAX_MM, ROOT, simulate_scene

BASELINE = ROOT / "configs" / "paper_trials_prosthesis_dome.yaml"
#: (assumption, value): each changed alone from the baseline; None is the baseline itself
SETUPS = [(None, None), ("radius_mm", 50.0), ("radius_mm", 70.0), ("height_mm", 25.0), ("height_mm", 45.0),
          ("target_height_mm", 10.0), ("target_height_mm", 20.0), ("cup_radius_mm", 3.0), ("cup_radius_mm", 8.0)]


def setup(base: dict, assumption: str | None, value: float | None, model: str, trials: int) -> dict:
    """The baseline scene with one assumption changed, the cup moved onto the skin at the targets' height."""
    s = copy.deepcopy(base)
    t = s["tissue"]
    if assumption in ("radius_mm", "height_mm"):
        t[assumption] = value
    if assumption == "target_height_mm":
        for target in s["targets"]:
            target["position_mm"][2] = value
            if target.get("desired_mm"):
                target["desired_mm"][2] = value
    if assumption == "cup_radius_mm":
        s["cups"][0]["radius_mm"] = value
    z = float(s["targets"][0]["position_mm"][2])
    s["cups"][0]["contact_mm"] = [0.0, round(t["radius_mm"] * float(np.sqrt(1.0 - (z / t["height_mm"]) ** 2)), 3), z]
    s["controller"]["model"] = model
    s["trials"]["count"] = trials
    return s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10, help="trials per target (default 10)")
    ap.add_argument("--models", default="body,layer", help="the controller's models, a,b")
    args = ap.parse_args()
    base = yaml.safe_load(BASELINE.read_text())
    res = results_io.Results("bench_dome_family")
    rows = []
    for assumption, value in SETUPS:
        for model in args.models.split(","):
            scene = setup(base, assumption, value, model, args.trials)
            targets, wall, cpu, _ = simulate_scene(scene, BASELINE.name)
            run = [x for x in targets if x["trials"]]
            row = {"assumption": assumption or "baseline", "value": value, "model": model,
                   "planned": len(run), "targets": len(targets), "trials": sum(x["trials"] for x in run),
                   "max_x_mm": max((x["max_x_mm"] for x in run), default=None),
                   "max_y_mm": max((x["max_y_mm"] for x in run), default=None),
                   "max_z_mm": max((x["max_z_mm"] for x in run), default=None),
                   "miss_p95_mm": max((x["miss_p95_mm"] for x in run), default=None),
                   "at_stroke_limit": sum(x["at_stroke_limit"] for x in run), "wall_s": wall, "cpu_s": cpu,
                   "iterations_median": float(np.median([x["iterations_median"] for x in run])) if run else None}
            rows.append(row)
            print(f"{row['assumption']} {value if value is not None else ''} ({model}): {row['planned']}/"
                  f"{row['targets']} planned, max |x| {row['max_x_mm']}, |y| {row['max_y_mm']}, |z| "
                  f"{row['max_z_mm']} mm, {row['at_stroke_limit']} at the stroke limit, {wall:.0f} s", flush=True)
    res.table("setups", rows, units={k: "mm" for k in ("value", "max_x_mm", "max_y_mm", "max_z_mm", "miss_p95_mm")}
              | {"wall_s": "s", "cpu_s": "s"})
    res.data("paper_max_mm", PAPER_MAX_MM)
    res.data("baseline", str(BASELINE.relative_to(ROOT)))
    res.data("trials_per_target", args.trials)
    res.write()


if __name__ == "__main__":
    main()
