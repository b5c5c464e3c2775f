"""How tightly a body trial's truth must settle (docs/performance.md, "The body's truth tolerance"): not a test.

A trial's true body is what the camera reads, to its noise (σ ≈ 0.15 mm on the paper's bench). This replays
a loop's top-speed travel on the first trial's perturbed truth of the paper dome's T2 (the trial's E field,
ν, η and fiber turn: `BodyTrialContext.target_run`): from rest, MOVES moves of STEP_MM on the cup, each
settled by the loop's tracker (`TrackedEquilibrium.move_to`, no tangent) at each relative residual in TOLS.
Per element and tolerance: the largest distance of the lesion from its 1e-10 settle over the moves, the
settle's median time, the factorisations and Newton iterations. `experiments.body_trials.BODY_TRUTH_TOL`
is chosen from this table. About a minute and a half on 2 cores.

    PYTHONPATH=. python3 benchmarks/bench_body_truth_tol.py
"""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli.control.plant import true_tissue  # noqa: E402
from scissor_cli.experiments.body_trials import BodyTrialContext  # noqa: E402
from scissor_cli.experiments.trial_types import TargetTask  # noqa: E402
from scissor_cli.mesh.probe import target_positions  # noqa: E402
from scissor_cli.solvers.tracking import TrackedEquilibrium  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "paper_trials_prosthesis_dome.yaml"
TOLS = (1e-10, 1e-8, 1e-7, 1e-6, 1e-5)
TARGET, MOVES, STEP_MM = "T2", 16, -0.45  # T2 is pulled: the loop travels towards the pull limit
ELEMENTS = ("p1", "nodal")


def replay(ctx: BodyTrialContext, task: TargetTask, tol: float) -> dict:
    """The travel settled at tol: lesion positions (MOVES, 3) mm, settle times (s), the tracker's counts."""
    run, _ = ctx.target_run(task, 0)
    truth = true_tissue(ctx.tissue, run.truth)
    probe = truth.probe(np.asarray(task.rest, float)[None])
    eq = TrackedEquilibrium(truth, tol)
    lesion, times = [], []
    for k in range(1, MOVES + 1):
        t0 = time.perf_counter()
        eq.move_to(np.array([k * STEP_MM]), tangent=False)
        times.append(time.perf_counter() - t0)
        lesion.append(target_positions(probe, eq.x)[0])
    return {"lesion": np.array(lesion), "times": times, **eq.stats}


def main() -> None:
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.2f}")
    res = results_io.Results("bench_body_truth_tol")
    scene = yaml.safe_load(CONFIG.read_text())
    rows = []
    for element in ELEMENTS:
        scene["tissue"]["mesh"]["element"] = element
        ctx = BodyTrialContext(yaml.safe_dump(scene))
        k = [t.name for t in ctx.scene.targets].index(TARGET)
        target = ctx.cfg.targets[k]
        task = TargetTask(k, TARGET, np.asarray(target.position_mm, float), np.asarray(target.desired_mm, float),
                          np.zeros(ctx.tissue.n_cups), "", np.array([1.0, 0.0, 0.0]))
        reference = None
        for tol in TOLS:
            r = replay(ctx, task, tol)
            reference = r["lesion"] if reference is None else reference
            row = {"element": element, "tol": tol, "unknowns": int(ctx.tissue.free_dofs.size),
                   "lesion_off_mm": float(np.max(np.linalg.norm(r["lesion"] - reference, axis=1))),
                   "settle_median_s": statistics.median(r["times"]), "replay_s": float(sum(r["times"])),
                   "factorisations": int(r["refactors"]), "newton_iterations": int(r["newton_iterations"])}
            rows.append(row)
            print(f"{element} tol {tol:g}: lesion within {row['lesion_off_mm']:.2e} mm of the 1e-10 settle, settle "
                  f"median {row['settle_median_s']:.3f} s, replay {row['replay_s']:.1f} s, "
                  f"{row['factorisations']} factorisations, {row['newton_iterations']} Newton iterations", flush=True)
    res.table("tolerances", rows, units={"lesion_off_mm": "mm", "settle_median_s": "s", "replay_s": "s"})
    res.data("replay", {"config": CONFIG.name, "target": TARGET, "moves": MOVES, "step_mm": STEP_MM, "trial": 0})
    res.write()


if __name__ == "__main__":
    main()
