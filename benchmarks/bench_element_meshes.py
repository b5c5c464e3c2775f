"""Speed against error with the element and the mesh chosen together (docs/model.md §21); not a test.

The paper's dome (configs/paper_trials_prosthesis_dome.yaml: its fibers, ν 0.45, and the same at ν 0.49, the
real tissue's), pushed and pulled 10 mm by its cup (the trials' strokes stay within this), solved with `p1` and
with `nodal` on meshes of growing `tissue.mesh.grading` (the edge's growth per mm from the lesions, vessels and
cup: 0.3, a layer's default and a body's before `nodal`, then coarser; 0.4 is a body's default), Newton to
1e-8. The reference is `nodal` on grading 0.3 at
`tissue.mesh.scale` 0.7 (every edge × 0.7; docs/performance-elements.md, "Convergence under refinement", gives
its own error under refinement). Per ν, element and grading: the tetrahedra and unknowns, the factor's nonzeros,
one numeric factorisation of the tangent at rest on its analysed pattern (CHOLMOD, `factorize_free`, what every
later Newton step and control move pays; the median of --repeats), the two forward
solves, and the lesions' largest distance from the reference (mm, and % of the reference's move). The timed
peer in the same run is `p1` graded 0.3, what the dome study ran before `nodal` (docs/model.md §21, "The body's
default").

    PYTHONPATH=. python3 benchmarks/bench_element_meshes.py      # about 7 minutes on 2 cores

Writes benchmarks/results/bench_element_meshes.json.
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

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.experiments.build import body_model  # noqa: E402
from scissor_cli.mesh.probe import probe_points, target_positions  # noqa: E402
from scissor_cli.solvers.equilibrium import solve_equilibrium  # noqa: E402
from scissor_cli.solvers.linear import factorize_free  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "paper_trials_prosthesis_dome.yaml"
NUS = (0.45, 0.49)
GRADINGS = (0.3, 0.4, 0.5, 0.7)
ELEMENTS = ("p1", "nodal")
STROKES_MM = (10.0, -10.0)
REFERENCE_SCALE = 0.7


def _config(nu: float, grading: float, element: str):
    cfg = load_config(CONFIG)
    mesh = cfg.tissue.mesh.model_copy(update={"grading": grading, "element": element})
    return cfg.model_copy(update={"tissue": cfg.tissue.model_copy(update={"mesh": mesh}),
                                  "material": cfg.material.model_copy(update={"nu": nu})})


def _moves(nu: float, grading: float, element: str, scale: float, repeats: int) -> dict:
    """One (ν, grading, element, scale): the mesh, one factorisation's cost and the lesions' moves (S, T, 3) mm."""
    scene, mesh, tissue = body_model(_config(nu, grading, element), cache=ROOT / "runs" / ".mesh-cache", scale=scale)
    rest = np.array([t.rest for t in scene.targets]).reshape(len(scene.targets), 3)
    probe = probe_points(mesh.nodes, mesh.tetrahedra, rest)
    K = tissue.stiffness_free(tissue.rest, upper=True)
    slot: dict = {}
    factor = factorize_free(tissue, K, slot)  # the analysis, once per pattern (a run's first solve)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        factorize_free(tissue, K, slot)
        times.append(time.perf_counter() - t0)
    moves, iterations = [], 0
    t0 = time.perf_counter()
    for stroke in STROKES_MM:
        r = solve_equilibrium(tissue, np.full(tissue.n_cups, stroke), method="newton", tol=1e-8)
        moves.append(target_positions(probe, r.x) - rest)
        iterations += int(r.iterations)
    return {"nu": nu, "grading": grading, "element": element, "scale": scale,
            "tetrahedra": int(mesh.n_elements), "unknowns": int(tissue.free_dofs.size),
            "factor_nnz": int(factor.nnz_factor), "factor_s": statistics.median(times),
            "forward_s": time.perf_counter() - t0, "newton_iterations": iterations, "moves_mm": np.array(moves)}


def rows_for(nu: float, repeats: int) -> list[dict]:
    """The reference, then every (element, grading) at scale 1 with its distance from the reference."""
    ref = _moves(nu, GRADINGS[0], "nodal", REFERENCE_SCALE, 1)
    reach = np.linalg.norm(ref["moves_mm"], axis=2)
    print(f"ν {nu} reference: {ref['tetrahedra']} tetrahedra, moves {np.round(reach, 3).tolist()} mm", flush=True)
    rows = []
    for grading in GRADINGS:
        for element in ELEMENTS:
            x = _moves(nu, grading, element, 1.0, repeats)
            off = np.linalg.norm(x.pop("moves_mm") - ref["moves_mm"], axis=2)
            x |= {"error_mm": float(off.max()), "error_pct": float(100 * (off / reach).max())}
            rows.append(x)
            print(f"ν {nu} {element} grading {grading}: {x['tetrahedra']} tetrahedra, {x['unknowns']} unknowns, "
                  f"factor {x['factor_nnz']} nonzeros {x['factor_s']:.2f} s, forward {x['forward_s']:.1f} s, "
                  f"off the reference {x['error_mm']:.3f} mm ({x['error_pct']:.1f} %)", flush=True)
    ref.pop("moves_mm")
    return [ref | {"error_mm": 0.0, "error_pct": 0.0}] + rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3, help="factorisations timed per row (the median)")
    args = ap.parse_args()
    res = results_io.Results("bench_element_meshes")
    rows = [row for nu in NUS for row in rows_for(nu, args.repeats)]
    res.table("meshes", rows, units={"factor_s": "s", "forward_s": "s", "error_mm": "mm", "error_pct": "%"})
    res.data("config", str(CONFIG.relative_to(ROOT)))
    res.data("strokes_mm", list(STROKES_MM))
    res.data("reference_scale", REFERENCE_SCALE)
    print(res.write())


if __name__ == "__main__":
    main()
