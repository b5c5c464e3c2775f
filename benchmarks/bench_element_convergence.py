"""Convergence under refinement, per element (docs/model.md §21): the observed order on the body.

The dome (configs/example_dome.yaml) with its fibers at ν 0.49 and an 8 mm push, meshed at `tissue.mesh.scale`
2, 1.4, 1 and 0.7, solved with `p1` and with `nodal` (Newton to 1e-8). Per element and level: the tetrahedra,
the lesions' positions, the change from the previous level (the largest over the lesions, mm), the observed
order of convergence from three consecutive levels,

    p = log(d_k / d_{k+1}) / log(h_k / h_{k+1}),    h = the mesh scale (every edge's target length × scale),

and the Richardson estimate of the finest level's error, d / ((h_k / h_{k+1})^p − 1), from the finest three
levels. The mesh is graded around the lesions and vessels and its coarsest edges are capped, so the coarse
levels differ less than their scales say (N grows by less than scale⁻³): the order of the finest three levels
is the one in the asymptotic range, the others are reported as measured.

    PYTHONPATH=. python3 benchmarks/bench_element_convergence.py     # about 5 minutes on 2 cores
    PYTHONPATH=. python3 benchmarks/bench_element_convergence.py --grading 0.5
    PYTHONPATH=. python3 benchmarks/bench_element_convergence.py --grading 0.5 --share 0.4

On `tissue.mesh.grading` GRADING (a layer's default, and a body's before `nodal`: the finest the study compares);
writes benchmarks/results/bench_element_convergence.json. With --grading G the same ladder on that grading, variant
"grading-G": whether a coarser mesh still meets the refinement bound (scale 1 → 0.7 moves the lesions ≤ 0.05 mm).
With --share A only `nodal`, its α (`nodal.ELEMENT_SHARE`, the share of the deviatoric energy kept per element) A,
variant "grading-G.share-A": whether a stiffer share, cheaper in the insertion, still meets that bound there.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import results_io  # noqa: E402

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.experiments.build import body_model  # noqa: E402
from scissor_cli.mechanics.body_tissue import build_body  # noqa: E402
from scissor_cli.mesh.probe import probe_points, target_positions  # noqa: E402
from scissor_cli.solvers.equilibrium import solve_equilibrium  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCALES = (2.0, 1.4, 1.0, 0.7)
#: the ladder's grading without --grading
GRADING = 0.3
ELEMENTS = ("p1", "nodal")
NU = 0.49
STROKE_MM = 8.0


def level_rows(grading: float, share: float | None = None) -> list[dict]:
    """One row per (element, scale): tetrahedra, the lesions' final positions (T, 3) mm, the solve's time; the mesh
    graded `grading`; with `share`, `nodal` alone with that α."""
    cfg = load_config(ROOT / "configs" / "example_dome.yaml")
    cfg = cfg.model_copy(update={"material": cfg.material.model_copy(update={"nu": NU})})
    cfg = cfg.model_copy(update={"tissue": cfg.tissue.model_copy(
        update={"mesh": cfg.tissue.mesh.model_copy(update={"grading": grading})})})
    rows = []
    for scale in SCALES:
        scene, mesh, _ = body_model(cfg, cache=ROOT / "runs" / ".mesh-cache", scale=scale)
        rest = np.array([t.rest for t in scene.targets]).reshape(len(scene.targets), 3)
        probe = probe_points(mesh.nodes, mesh.tetrahedra, rest)
        for element in ELEMENTS if share is None else ("nodal",):
            tissue = build_body(scene, mesh, element=element)
            if share is not None:
                tissue = replace(tissue, element=tissue.element.with_share(share), factor_cache={})
            t0 = time.perf_counter()
            r = solve_equilibrium(tissue, np.full(tissue.n_cups, STROKE_MM), method="newton", tol=1e-8)
            rows.append({"element": element, "scale": scale, "tetrahedra": int(mesh.n_elements),
                         "h": scale, "forward_s": time.perf_counter() - t0,
                         "newton_iterations": int(r.iterations), "lesions_mm": target_positions(probe, r.x).tolist(),
                         "moves_mm": np.linalg.norm(target_positions(probe, r.x) - rest, axis=1).tolist()})
            print(f"{element} scale {scale}: {mesh.n_elements} tetrahedra, moves "
                  f"{np.round(rows[-1]['moves_mm'], 3).tolist()} mm, {rows[-1]['forward_s']:.1f} s", flush=True)
    return rows


def orders(rows: list[dict]) -> list[dict]:
    """Per element: the change between levels, the observed orders and the finest level's Richardson error."""
    out = []
    for element in dict.fromkeys(r["element"] for r in rows):
        levels = [r for r in rows if r["element"] == element]
        x = [np.asarray(r["lesions_mm"]) for r in levels]
        h = [r["h"] for r in levels]
        d = [float(np.linalg.norm(x[k + 1] - x[k], axis=1).max()) for k in range(len(x) - 1)]
        p = [float(np.log(d[k] / d[k + 1]) / np.log(h[k + 1] / h[k + 2])) if d[k + 1] > 0 else float("nan")
             for k in range(len(d) - 1)]
        ratio = h[-2] / h[-1]
        finest_error = d[-1] / (ratio ** p[-1] - 1.0) if np.isfinite(p[-1]) and p[-1] > 0 else float("nan")
        out.append({"element": element, "changes_mm": d, "orders": p, "finest_error_mm": float(finest_error),
                    "scales": [r["scale"] for r in levels], "tetrahedra": [r["tetrahedra"] for r in levels]})
        print(f"{element}: changes {np.round(d, 4).tolist()} mm, observed orders {np.round(p, 2).tolist()}, "
              f"finest level's error (Richardson) {finest_error:.4f} mm", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grading", type=float, default=GRADING, help="tissue.mesh.grading")
    ap.add_argument("--share", type=float, default=None, help="nodal's α (nodal.ELEMENT_SHARE): nodal alone")
    args = ap.parse_args()
    variant = ".".join(([] if args.grading == GRADING else [f"grading-{args.grading:g}"])
                       + ([] if args.share is None else [f"share-{args.share:g}"]))
    res = results_io.Results("bench_element_convergence", variant or None)
    print(f"machine: {results_io.machine()}, load {results_io.load1()}")
    rows = level_rows(args.grading, args.share)
    res.table("levels", rows, units={"forward_s": "s", "lesions_mm": "mm", "moves_mm": "mm"})
    res.table("orders", orders(rows), units={"changes_mm": "mm", "finest_error_mm": "mm"})
    res.figure("grading", args.grading, "1")
    if args.share is not None:
        res.figure("share", args.share, "1")
    print(res.write())


if __name__ == "__main__":
    main()
