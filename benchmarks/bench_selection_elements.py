"""What a layer's accuracy selection picks with `tissue.mesh.element: auto`, and what it really misses by.

configs/example.yaml at ν 0.45, 0.49 and 0.499 (docs/model.md §9, §21): one calibration per ν with
`element: auto` (`experiments.selection.select`), then for each budget the pick among every candidate
(`auto`) and among p1's alone (what `element: p1` picks from the same calibration). Each pick is built and
solved on the hardest forward case (push10) as `simulate` runs it, and its targets are compared with a
reference: `nodal`, the richest model, Newton, on the size field × 0.25. Per row: the pick, its predicted
error, its real error against the reference (mm), and its solve's time (median of --repeats).

    PYTHONPATH=. python3 benchmarks/bench_selection_elements.py     # about 2 minutes on 2 cores

Writes benchmarks/results/bench_selection_elements.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))

import results_io  # noqa: E402

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
from scissor_cli.config import parse_config  # noqa: E402
from scissor_cli.experiments.build import build_model, scene_of  # noqa: E402
from scissor_cli.experiments.selection import choose, hardest_case, select  # noqa: E402
from scissor_cli.mesh.probe import probe_targets, target_positions  # noqa: E402
from scissor_cli.solvers.equilibrium import solve_equilibrium  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
NUS = (0.45, 0.49, 0.499)
BUDGETS_MM = (1.0, 0.5, 0.3, 0.1)
REFERENCE_LEVEL = 0.25
#: as the selection's calibration of ADMM (`selection._admm_or_unconverged`)
ADMM_MAX_ITER = 5000


def example(nu: float, element: str, accuracy_mm: float | None, scale: float = 1.0):
    data = yaml.safe_load((ROOT / "configs" / "example.yaml").read_text())
    data["material"]["nu"] = nu
    mesh = data["tissue"].setdefault("mesh", {})
    mesh["element"], mesh["scale"] = element, scale * mesh.get("scale", 1.0)
    data["solver"]["accuracy_mm"] = accuracy_mm
    if element == "nodal":
        data["solver"]["kind"] = "newton"  # (the example runs ADMM, which nodal does not)
    return parse_config(yaml.safe_dump(data), "example.yaml")


def targets_of(cfg, strokes: np.ndarray, repeats: int = 1) -> tuple[np.ndarray, float, int]:
    """The targets (T, 2) mm of a config's model at strokes, its solve's median time (s) and its elements."""
    scene, mesh, tissue = build_model(cfg)
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = solve_equilibrium(tissue, strokes, method=cfg.solver.kind, tol=cfg.solver.tolerance,
                                   max_iter=ADMM_MAX_ITER if cfg.solver.kind == "admm" else None)
        times.append(time.perf_counter() - t0)
    rest = np.array([t.rest for t in scene.targets])
    return target_positions(probe_targets(mesh, rest), result.x), float(np.median(times)), mesh.n_elements


def rows_for(nu: float, repeats: int) -> list[dict]:
    cfg = example(nu, "auto", min(BUDGETS_MM))
    t0 = time.perf_counter()
    calibrated = select(cfg, min(BUDGETS_MM))
    calibration_s = time.perf_counter() - t0
    _, strokes = hardest_case(cfg, scene_of(cfg))
    reference_cfg = example(nu, "nodal", None, scale=REFERENCE_LEVEL)
    reference_cfg = reference_cfg.model_copy(update={"material": reference_cfg.material.model_copy(
        update={"model": "neo_hookean_fiber"})})
    reference, _, n_reference = targets_of(reference_cfg, strokes)
    rows = []
    for budget in BUDGETS_MM:
        for among in ("auto", "p1"):
            candidates = [c for c in calibrated.candidates if among == "auto" or c.element == among]
            pick, meets = choose(candidates, budget)
            picked = replace(calibrated, accuracy_mm=budget, pick=pick, meets_budget=meets)
            positions, solve_s, n = targets_of(picked.apply(cfg), strokes, repeats)
            error = float(np.linalg.norm(positions - reference, axis=1).max())
            rows.append({"nu": nu, "budget_mm": budget, "among": among, "element": pick.element,
                         "level": pick.level, "model": pick.model, "solver": pick.solver,
                         "tolerance": pick.tolerance, "n_elements": n, "meets_budget": meets,
                         "predicted_error_mm": pick.predicted_error_mm, "error_mm": error, "solve_s": solve_s,
                         "calibration_s": calibration_s, "reference_elements": n_reference})
            print(f"ν {nu} budget {budget} mm, {among}: {pick.element} {pick.solver} {pick.model} level "
                  f"{pick.level:g} ({n} elements), predicted {pick.predicted_error_mm:.3f} mm, real {error:.3f} mm, "
                  f"{solve_s * 1e3:.0f} ms" + ("" if meets else " (no candidate predicted within the budget)"),
                  flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    res = results_io.Results("bench_selection_elements")
    print(f"machine: {results_io.machine()}, load {results_io.load1()}")
    rows = [row for nu in NUS for row in rows_for(nu, args.repeats)]
    res.table("picks", rows, units={"budget_mm": "mm", "predicted_error_mm": "mm", "error_mm": "mm",
                                    "solve_s": "s", "calibration_s": "s"})
    print(res.write())


if __name__ == "__main__":
    main()
