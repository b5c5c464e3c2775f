"""The paper's prosthesis study with slab truth on each element (docs/model.md §13, §21): what moves; not a test.

`scissor simulate configs/paper_trials_prosthesis_slab.yaml --jobs 2` from an empty folder and cache with
`tissue.mesh.element` p1 (the layer's default) and then nodal — the layer the controller steers by and the slab
that is the trials' truth, with the slab its `layer_check.accuracy_mm` picks on that element — with Newton for
both (ADMM refuses `nodal`) and --trials per target (default 10). Per element and target: the maxima of |x|
(across the push) and |y| (along it) of the final error beside the paper's Fig. 14, the miss across the needle
(median, p95), the trials stopped at the cup's stroke limit and the median trial; per element the slab picked
and the wall and CPU time.

    PYTHONPATH=. python3 benchmarks/bench_element_slab_study.py [--trials 10]
"""

from __future__ import annotations

import argparse

import results_io
import yaml
from bench_dome_study import PAPER_MAX_MM, ROOT, simulate_scene

CONFIG = ROOT / "configs" / "paper_trials_prosthesis_slab.yaml"
ELEMENTS = ("p1", "nodal")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10, help="trials per target")
    args = ap.parse_args()
    res = results_io.Results("bench_element_slab_study", None if args.trials == 10 else f"trials-{args.trials}")
    rows, runs = [], []
    for element in ELEMENTS:
        scene = yaml.safe_load(CONFIG.read_text())
        scene["tissue"].setdefault("mesh", {})["element"] = element
        scene["trials"]["count"] = args.trials
        scene["solver"]["kind"] = "newton"  # (ADMM refuses `nodal`: both elements on the same solver)
        targets, wall, cpu, slab = simulate_scene(scene, CONFIG.name)
        rows += [{"element": element} | row for row in targets]
        runs.append({"element": element, "wall_s": wall, "cpu_s": cpu} | slab)
        for row in targets:
            print(f"{element} {row['target']}: max |x| {row['max_x_mm']:.2f}, |y| {row['max_y_mm']:.2f} mm; miss "
                  f"median {row['miss_median_mm']:.2f}, p95 {row['miss_p95_mm']:.2f} mm; {row['at_stroke_limit']} "
                  f"at the stroke limit; a trial {row['trial_s_median']:.1f} s", flush=True)
        print(f"{element}: slab {slab['slab_tetrahedra']} tetrahedra; {wall / 60:.1f} min wall, {cpu:.0f} CPU-s",
              flush=True)
    res.table("targets", rows, units={k: "mm" for k in ("max_x_mm", "max_y_mm", "miss_median_mm", "miss_p95_mm")}
              | {"trial_s_median": "s"})
    res.table("runs", runs, units={"wall_s": "s", "cpu_s": "s"})
    res.data("paper_max_mm", PAPER_MAX_MM)
    res.data("config", str(CONFIG.relative_to(ROOT)))
    res.data("trials_per_target", args.trials)
    print(res.write())


if __name__ == "__main__":
    main()
