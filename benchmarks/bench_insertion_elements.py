"""The needle in the body, speed against error per element and mesh (docs/model.md §20, §21); not a test.

configs/example_dome.yaml's body, the needle along −x through T1 at rest from where that line enters the skin,
50 mm in 0.5 mm steps, strategy `none`, the default needle–tissue parameters (§12), on `p1` and `nodal` over
meshes of growing `tissue.mesh.grading` (and `p1` refined to about 30k tetrahedra, the size of the insertion's
time goal; `nodal` also coarser than a body's default). The reference is `nodal` graded 0.3 with every edge ×
REFERENCE_SCALE; the same on a mesh finer still (× FINER_SCALE) gives the reference's own error. Per row: the
tetrahedra, the insertion's wall time (the median of --repeats), where the lesion ends (its region's mean, as
scissor carries a body's lesion: its drag by the needle) and how far that is from the reference's (mm, and %
of the reference's drag), the same for the lesion's centre point (the needle's line passes through it, where
the displacement has no limit under refinement; docs/model.md §21), the needle's last force and the lesion's
miss; and, on the same tissue, the config's first forward case (push10) from rest, timed as `bench_body.py`
times it (Newton to 1e-8, the median of --repeats), with the lesions' ends against the reference's (the
largest, mm and % of that lesion's move).

What it answers: which element and mesh reach a given accuracy of the drag and of a push fastest; the fair
form of "a 50 mm insertion ≤ 5 s" and "one equilibrium ≤ 1 s" at 30k tetrahedra once the elements differ in
accuracy (docs/model.md §21: a coarser mesh is fair where the element meets the accuracy on it) is the
coarsest row within BOUND_PCT of the reference on both.

    PYTHONPATH=. python3 benchmarks/bench_insertion_elements.py      # about 15 minutes on 2 cores

Writes benchmarks/results/bench_insertion_elements.json.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import results_io  # noqa: E402
from bench_body_insertion import lesion_path  # noqa: E402

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.config.sections import InsertionConfig  # noqa: E402
from scissor_cli.experiments.build import body_model  # noqa: E402
from scissor_cli.insertion import InsertionOptions, NeedleParams, run_strategies  # noqa: E402
from scissor_cli.mesh.probe import target_positions  # noqa: E402
from scissor_cli.solvers.equilibrium import solve_equilibrium  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"
DEPTH_MM, STEP_MM = 50.0, 0.5
REFERENCE_SCALE = 0.7
#: the reference's own mesh error: the same insertion on a mesh finer still
FINER_SCALE = 0.55
#: (element, grading, mesh scale): the rows, the reference first; `nodal` also coarser than a body's default
ROWS = (("nodal", 0.3, REFERENCE_SCALE), ("nodal", 0.3, FINER_SCALE), ("p1", 0.3, 1.0), ("p1", 0.3, 0.85),
        ("nodal", 0.3, 1.0), ("nodal", 0.4, 1.0), ("p1", 0.5, 1.0), ("nodal", 0.5, 1.0), ("p1", 0.7, 1.0),
        ("nodal", 0.7, 1.0), ("nodal", 0.5, 1.4), ("nodal", 0.5, 2.0), ("nodal", 0.7, 1.4), ("nodal", 0.7, 2.0))
#: the accuracy a mesh is held to, % of the reference's drag and of each lesion's move (the bound the element
#: meets against quadratic elements on the same mesh, docs/model.md §21)
BOUND_PCT = 8.0


def insertion(element: str, grading: float, scale: float, repeats: int) -> dict:
    """One `none` insertion on (element, grading, scale): the mesh, its median time and where it leaves T1; and the
    config's first forward case from rest on the same tissue: its median time and where it leaves the lesions."""
    cfg = load_config(CONFIG)
    mesh_cfg = cfg.tissue.mesh.model_copy(update={"element": element, "grading": grading})
    cfg = cfg.model_copy(update={"tissue": cfg.tissue.model_copy(update={"mesh": mesh_cfg})})
    scene, mesh, tissue = body_model(cfg, cache=ROOT / "runs" / ".mesh-cache", scale=scale)
    params = NeedleParams.from_config(InsertionConfig(step_mm=STEP_MM), cfg.needle, cfg.tissue.mesh)
    lesion = scene.targets[0]
    strokes = np.zeros(len(scene.cups))
    x0 = solve_equilibrium(tissue, strokes).x
    path = lesion_path(mesh, lesion, DEPTH_MM)
    centre = tissue.element.probe(tissue.rest, lesion.rest[None])  # the lesion's centre point (the former probe)
    walls, r = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = run_strategies(tissue, x0, strokes, {"none": path}, params,
                           {"none": InsertionOptions("none", cfg.controller, keep_displacement=False)})[0]
        walls.append(time.perf_counter() - t0)
    case = cfg.forward[0]
    push, push_walls = scene.strokes_vector(case.strokes), []
    for _ in range(repeats):
        t0 = time.perf_counter()
        pushed = solve_equilibrium(tissue, push, tol=1e-8)
        push_walls.append(time.perf_counter() - t0)
    probe = tissue.probe(np.array([t.rest for t in scene.targets]))
    return {"element": element, "grading": grading, "scale": scale, "tetrahedra": int(mesh.n_elements),
            "push_case": case.name, "push_s": statistics.median(push_walls),
            "push_ends_mm": target_positions(probe, pushed.x).tolist(),
            "wall_s": statistics.median(walls), "steps": r.steps, "lesion_end_mm": r.target[-1].tolist(),
            "drag_mm": float(np.linalg.norm(r.target[-1] - lesion.rest)),
            "centre_end_mm": target_positions(centre, r.x)[0].tolist(),
            "force_mN": float(r.needle_force_mN[-1]), "miss_mm": r.miss_mm, "stop": r.stop_reason}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2, help="timed insertions per row (the median)")
    args = ap.parse_args()
    res = results_io.Results("bench_insertion_elements")
    rows = []
    lesions_rest = np.array([t.position_mm for t in load_config(CONFIG).targets])
    rest = lesions_rest[0]
    for element, grading, scale in ROWS:
        row = insertion(element, grading, scale, 1 if not rows else args.repeats)
        ref = rows[0] if rows else row
        off = float(np.linalg.norm(np.subtract(row["lesion_end_mm"], ref["lesion_end_mm"])))
        centre_off = float(np.linalg.norm(np.subtract(row["centre_end_mm"], ref["centre_end_mm"])))
        centre_drag = float(np.linalg.norm(np.subtract(ref["centre_end_mm"], rest)))
        row |= {"error_mm": off, "error_pct": 100.0 * off / ref["drag_mm"], "reference": not rows,
                "centre_error_mm": centre_off, "centre_error_pct": 100.0 * centre_off / centre_drag}
        ref_ends = np.array(ref["push_ends_mm"])
        push_off = np.linalg.norm(np.array(row["push_ends_mm"]) - ref_ends, axis=1)
        push_off_pct = 100.0 * push_off / np.linalg.norm(ref_ends - lesions_rest, axis=1)
        row |= {"push_error_mm": float(push_off.max()), "push_error_pct": float(push_off_pct.max())}
        rows.append(row)
        print(f"{element} grading {grading} ×{scale:g}: {row['tetrahedra']} tetrahedra, {row['wall_s']:.1f} s, "
              f"drag {row['drag_mm']:.3f} mm, {off:.3f} mm ({row['error_pct']:.1f} %) off the reference "
              f"(the centre point {row['centre_error_pct']:.1f} %), "
              f"force {row['force_mN']:.0f} mN, miss {row['miss_mm']:.3f} mm ({row['stop']}); {row['push_case']} "
              f"from rest {row['push_s']:.2f} s, the lesions {row['push_error_mm']:.3f} mm "
              f"({row['push_error_pct']:.1f} %) off the reference", flush=True)
    res.table("insertions", rows, units={"wall_s": "s", "drag_mm": "mm", "force_mN": "mN", "miss_mm": "mm",
                                         "error_mm": "mm", "error_pct": "%", "centre_error_mm": "mm",
                                         "centre_error_pct": "%", "push_s": "s", "push_error_mm": "mm",
                                         "push_error_pct": "%"})
    res.data("config", str(CONFIG.relative_to(ROOT)))
    res.data("depth_mm", DEPTH_MM)
    res.data("step_mm", STEP_MM)
    res.data("bound_pct", BOUND_PCT)
    res.write()


if __name__ == "__main__":
    main()
