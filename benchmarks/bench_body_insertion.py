"""The needle in the body (docs/model.md §20): one insertion per strategy, timed; not a test.

On configs/example_dome.yaml's body (the configured mesh): the needle along −x through T1 at rest from
where that line enters the skin, 50 mm deep (past the lesion) in 0.5 mm steps, with the default needle–tissue
parameters (§12), under `none`, `depth` and `loop` (both cups would move it; the dome has one). Per strategy:
the wall time, steps, the lesion's miss at the end, the last force, active-set passes that did not settle.
Goal (§20): a 50 mm insertion in 0.5 mm steps ≤ 5 s at 30k tetrahedra: `none` again on the dome meshed
finer (SCALE_30K) to that size.

Also, for `loop`'s J in 3-D (the kept factor's answer, `model_state.JACOBIAN_DIRECT_3D`): at every
CHECK_EVERY-th step of an untimed `none` insertion, that J against PCG's converged one (the largest relative
difference where PCG converges), and the capture radius's effect: the same insertion with the layer's default
(half the coarsest edge) for the captured count, the time and the miss.

Speed against error: `none` solved to each of TOLERANCES (every pass and step, `NeedleParams.step_tol`),
its time and how far its lesion and force end from the tightest one's.

And a trial with the needle (goal §20: every strategy ≤ 15 s): `scissor simulate` of example_dome with
`insertion` (every strategy) and TRIALS trials per lesion, one process (`--jobs 1`); each trial's time from
results.h5 (its loop and its three insertions in the drawn true body), and each strategy's miss.

With --element and --grading the whole benchmark runs on that element and mesh grading (`tissue.mesh.element`,
`tissue.mesh.grading`; variant "ELEMENT.grading-G"), and --scale-30k names the mesh scale that gives about 30k
tetrahedra on it; `--element p1 --grading 0.3 --scale-30k 0.85` is the body's default before `nodal`.

    PYTHONPATH=. python benchmarks/bench_body_insertion.py [--depth-mm 50] [--step-mm 0.5] [--repeats 3]
    PYTHONPATH=. python benchmarks/bench_body_insertion.py --element p1 --grading 0.3 --scale-30k 0.85
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

from scissor_cli import runtime

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"
#: the dome's mesh scale that gives about 30k tetrahedra (§20's size) on the default mesh, graded 0.5 (graded 0.4,
#: the default before: 0.74; `p1`'s former default, graded 0.3: 0.85)
SCALE_30K = 0.70
#: steps between two checks of the direct J against the converged one
CHECK_EVERY = 10
#: the step tolerances of the speed-against-error sweep, the tightest the reference
TOLERANCES = (1e-6, 1e-5, 1e-4, 3e-4, 1e-3)
#: trials per lesion of the timed trials with the needle
TRIALS = 2
#: the needle's axis through a lesion: along −x, entering on the +x side (example_dome's `needle.direction`)
AXIS = np.array([-1.0, 0.0, 0.0])


def lesion_path(mesh, lesion, depth_mm: float):
    """The `NeedlePath` through `lesion`'s rest position along AXIS from where that line enters the body's skin,
    depth_mm deep (scissor's modules imported here: the caller has run `runtime.configure`)."""
    from scissor_cli.insertion import NeedlePath
    from scissor_cli.planning.body_lines import skin_entries
    entries, _, _ = skin_entries(mesh.nodes, mesh.boundary_triangles, np.zeros(len(mesh.boundary_triangles), bool),
                                 lesion.rest, AXIS[None])
    return NeedlePath(entries[0], AXIS, depth_mm, lesion.rest, lesion.name)


def trial_times(cfg_data: dict) -> tuple[list[dict], list[str]]:
    """`scissor simulate` of the scene with every strategy and TRIALS trials per lesion, one process: a row per
    trial (its time and each strategy's miss), and the strategies' names."""
    scene = dict(cfg_data, insertion={"strategies": ["none", "depth", "loop"]},
                 trials=dict(cfg_data["trials"], count=TRIALS))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "dome_needle.yaml"
        path.write_text(yaml.safe_dump(scene, sort_keys=False))
        r = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(path), "--jobs", "1", "--out",
                            str(Path(tmp) / "run"), "--quiet"], capture_output=True, text=True, cwd=tmp,
                           env=results_io.subprocess_env())
        if r.returncode != 0:
            raise SystemExit(f"simulate failed ({r.returncode}):\n{r.stderr[-2000:]}")
        rows = []
        with h5py.File(Path(tmp) / "run" / "results.h5", "r") as f:
            for target in f["trials"]:
                g = f["trials"][target]
                strategies = [str(x) for x in g["miss_mm"].attrs["strategies"]]
                for k, (t, miss) in enumerate(zip(g["trial_time_s"][()], g["miss_mm"][()])):
                    rows.append({"target": target, "trial": k, "trial_s": float(t),
                                 "loop_s": float(g["time_s"][k]), **{f"miss_{s}_mm": float(m)
                                                                    for s, m in zip(strategies, miss)}})
    return rows, strategies


def jacobian_check(tissue, probe, differences: list):
    """A `record` hook: at every CHECK_EVERY-th step, J from the kept factor against PCG's converged J (appended
    as (depth mm, relative difference))."""
    from scissor_cli.insertion.model_state import ModelState

    count = [0]

    def record(state, x, strokes):
        count[0] += 1
        if count[0] % CHECK_EVERY or state.solver is None:
            return
        J = {}
        for direct in (True, False):  # the kept factor's answer first: PCG may refresh it (this run is not timed)
            model = ModelState(tissue, tissue, x, x, strokes)
            model.direct = direct
            J[direct] = model.jacobian(state, probe, state.solver, rows=2)[0]
        if not model.direct:  # PCG converged (else it fell back on the factor's answer: nothing to compare)
            differences.append((state.depth_mm, float(np.linalg.norm(J[True] - J[False]) / np.linalg.norm(J[False]))))

    return record


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--depth-mm", type=float, default=50.0)
    ap.add_argument("--step-mm", type=float, default=0.5)
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per strategy (the median is reported)")
    ap.add_argument("--element", choices=("p1", "nodal"), default=None, help="tissue.mesh.element (the config's)")
    ap.add_argument("--grading", type=float, default=None, help="tissue.mesh.grading (the config's)")
    ap.add_argument("--scale-30k", type=float, default=SCALE_30K, help="the mesh scale giving about 30k tetrahedra")
    args = ap.parse_args()
    mesh_options = {k: v for k, v in (("element", args.element), ("grading", args.grading)) if v is not None}
    runtime.configure()
    from scissor_cli.config import load_config
    from scissor_cli.config.body_sections import BodyMeshConfig
    from scissor_cli.config.sections import InsertionConfig
    from scissor_cli.experiments.build import body_model
    from scissor_cli.insertion import InsertionOptions, NeedleParams, run_strategies
    from scissor_cli.insertion.points import needle_points
    from scissor_cli.solvers.equilibrium import solve_equilibrium
    variant = ".".join([args.element or BodyMeshConfig().element]
                       + ([f"grading-{args.grading:g}"] if args.grading is not None else []))
    res = results_io.Results("bench_body_insertion", None if not mesh_options else variant)
    cfg = load_config(CONFIG)
    cfg = cfg.model_copy(update={"tissue": cfg.tissue.model_copy(
        update={"mesh": cfg.tissue.mesh.model_copy(update=mesh_options)})})
    scene, mesh, tissue = body_model(cfg)
    params = NeedleParams.from_config(InsertionConfig(step_mm=args.step_mm), cfg.needle, cfg.tissue.mesh)
    lesion = scene.targets[0]
    strokes = np.zeros(len(scene.cups))
    x0 = solve_equilibrium(tissue, strokes).x
    path = lesion_path(mesh, lesion, args.depth_mm)
    print(f"{cfg.name}: {mesh.n_elements} tetrahedra; {lesion.name} from {np.round(path.entry, 1).tolist()} along "
          f"{AXIS.tolist()}, {args.depth_mm:g} mm in {args.step_mm:g} mm steps", flush=True)
    res.figure("tetrahedra", mesh.n_elements, "1")

    def insert(strategy, p, record=None):
        return run_strategies(tissue, x0, strokes, {strategy: path}, p,
                              {strategy: InsertionOptions(strategy, cfg.controller, keep_displacement=False,
                                                          record=record)})[0]

    rows = []
    coarsest = dataclasses.replace(params, capture_radius_mm=0.5 * cfg.tissue.mesh.max_edge_mm * cfg.tissue.mesh.scale)
    for strategy, p in [("none", params), ("depth", params), ("loop", params), ("none", coarsest)]:
        walls = []
        for _ in range(args.repeats if p is params else 1):
            t0 = time.perf_counter()
            r = insert(strategy, p)
            walls.append(time.perf_counter() - t0)
        wall = float(np.median(walls))
        capture = "local" if p.capture_radius_mm is None else f"{p.capture_radius_mm:g} mm"
        rows.append({"strategy": strategy, "capture": capture, "steps": r.steps, "depth_mm": float(r.depth_mm[-1]),
                     "wall_s": wall, "repeats": len(walls), "captured": int(r.stuck[-1] + r.slipping[-1]),
                     "miss_mm": r.miss_mm, "force_mN": float(r.needle_force_mN[-1]), "unsettled": r.unsettled,
                     "stop": r.stop_reason})
        print(f"  {strategy} (capture {capture}): {r.steps} steps to {r.depth_mm[-1]:.1f} mm in {wall:.1f} s "
              f"(median of {len(walls)}), {rows[-1]['captured']} nodes captured, miss {r.miss_mm:.3f} mm, "
              f"force {r.needle_force_mN[-1]:.0f} mN ({r.stop_reason})", flush=True)
    sweep = []
    for tol in TOLERANCES:
        t0 = time.perf_counter()
        r = insert("none", dataclasses.replace(params, step_tol=tol))
        sweep.append({"step_tol": tol, "wall_s": time.perf_counter() - t0, "target": r.target[-1],
                      "force_mN": float(r.needle_force_mN[-1]), "miss_mm": r.miss_mm})
    reference = sweep[0]
    for row in sweep:
        row["target_off_mm"] = float(np.linalg.norm(row["target"] - reference["target"]))
        row["force_off_mN"] = abs(row["force_mN"] - reference["force_mN"])
    for row in sweep:
        del row["target"]
        print(f"  none solved to {row['step_tol']:.0e}: {row['wall_s']:.1f} s, lesion {row['target_off_mm']:.1e} mm "
              f"from the {TOLERANCES[0]:.0e} solution's, force {row['force_off_mN']:.1e} mN off", flush=True)
    res.table("tolerances", sweep, {"wall_s": "s", "force_mN": "mN", "miss_mm": "mm", "target_off_mm": "mm",
                                    "force_off_mN": "mN"})
    # the goal's size: the same insertion in the same dome meshed finer, to about 30k tetrahedra
    _, mesh_30k, tissue_30k = body_model(cfg, scale=args.scale_30k)
    x0_30k = solve_equilibrium(tissue_30k, strokes).x
    walls = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        r = run_strategies(tissue_30k, x0_30k, strokes, {"none": path}, params,
                           {"none": InsertionOptions("none", cfg.controller, keep_displacement=False)})[0]
        walls.append(time.perf_counter() - t0)
    wall = float(np.median(walls))
    print(f"  none at {mesh_30k.n_elements} tetrahedra (mesh scale {args.scale_30k:g}): {wall:.1f} s (median of "
          f"{len(walls)}), miss {r.miss_mm:.3f} mm", flush=True)
    res.figure("tetrahedra_30k", mesh_30k.n_elements, "1")
    res.figure("none_30k_s", wall, "s")
    res.figure("none_30k_miss_mm", r.miss_mm, "mm")
    differences = []
    insert("none", params, jacobian_check(tissue, needle_points(tissue, lesion.rest).probe, differences))
    worst = max(d for _, d in differences)
    print(f"  loop's J from the kept factor against PCG's: largest relative difference {worst:.2%} over "
          f"{len(differences)} checks", flush=True)
    res.figure("jacobian_direct_difference", worst, "relative")
    res.table("jacobian_checks", [{"depth_mm": z, "difference": d} for z, d in differences],
              {"depth_mm": "mm", "difference": "relative"})
    scene_data = yaml.safe_load(CONFIG.read_text())
    scene_data["tissue"].setdefault("mesh", {}).update(mesh_options)
    trials, strategies = trial_times(scene_data)
    times = [x["trial_s"] for x in trials]
    print(f"  a trial with the needle ({', '.join(strategies)}): median {np.median(times):.1f} s, slowest "
          f"{max(times):.1f} s over {len(times)} trials", flush=True)
    res.figure("trial_median_s", float(np.median(times)), "s")
    res.figure("trial_max_s", float(max(times)), "s")
    res.table("trials", trials, {"trial_s": "s", "loop_s": "s", **{f"miss_{s}_mm": "mm" for s in strategies}})
    res.table("strategies", rows, {"depth_mm": "mm", "wall_s": "s", "miss_mm": "mm", "force_mN": "mN"})
    res.data("config", str(CONFIG.relative_to(ROOT)))
    res.data("default_step_tol", params.step_tol)
    res.data("mesh_options", mesh_options)
    res.data("scale_30k", args.scale_30k)
    res.write()


if __name__ == "__main__":
    main()
