"""Elements that lock and one that does not (docs/model.md §21): error against quadratic elements, and cost.

For the 2-D example (configs/example.yaml) and the dome (configs/example_dome.yaml), on each scene's own mesh
with its own held and cup nodes, linear elasticity under a 1 mm push of the first cup, at ν 0.45, 0.49 and
0.499: each lesion's displacement with `p1` and with `nodal` against scikit-fem's P2 on the same mesh
(benchmarks/quadratic_reference.py) and against the mixed u–p Taylor–Hood solve there (P2 with a P1
pressure: quadratic displacements alone lock too as ν → 1/2), the same on the dome with a second cup (both
pushed), and the cost of
one tangent: assembly of K_ff, its upper triangle's
nonzeros, its factorisation (CHOLMOD, the solvers' `factorize_free`), and a whole nonlinear forward solve
(the scene's material at ν 0.45, Newton to 1e-8: the layer's push10, the dome's 8 mm push), and beside them
what quadratic elements on the same mesh would cost, alone and mixed (unknowns, nonzeros, the same
factorisation of the displacement block; the mixed solve's pressure iterations besides). Then the dome
with its fibers at ν 0.49 and an 8 mm push at mesh scale 1 and 0.7: how far the lesions move under refinement.
Last, the sweep that chose α (`nodal.ELEMENT_SHARE`): the dome with one cup and with two at each ν, against P2
and against Taylor–Hood, for each share in SHARES.
Times are medians of `--repeats` runs in this process, p1 and nodal side by side.

    PYTHONPATH=. python3 benchmarks/bench_elements.py             # about 15 minutes on 2 cores
    PYTHONPATH=. python3 benchmarks/bench_elements.py --quick     # the layer only (variant "quick")

Writes benchmarks/results/bench_elements.json (or bench_elements.quick.json).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parent))

import quadratic_reference  # noqa: E402
import results_io  # noqa: E402

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.experiments.build import body_model, build_model  # noqa: E402
from scissor_cli.mechanics.body_tissue import build_body  # noqa: E402
from scissor_cli.mechanics.nodal import ELEMENT_SHARE  # noqa: E402
from scissor_cli.mechanics.tissue import build_tissue  # noqa: E402
from scissor_cli.mesh.probe import probe_points, target_positions  # noqa: E402
from scissor_cli.solvers.equilibrium import solve_equilibrium  # noqa: E402
from scissor_cli.solvers.linear import Factorization, factorize_free  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
NUS = (0.45, 0.49, 0.499)
ELEMENTS = ("p1", "nodal")


def _median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


#: the second cup of the dome's two-cup variant: on the skin opposite the vessel, pushing along +x
SECOND_CUP = {"name": "cup2", "contact_mm": [-57.5, 0.0, 10.0], "axis": [1.0, 0.0, 0.0], "radius_mm": 5.0,
              "stroke_mm": [-15.0, 15.0], "speed_mm_per_s": 5.0}


def _config(scene_name: str, nu: float, model: str):
    """A shipped scene (`example_dome.yaml+cup2`: the dome with SECOND_CUP) at ν with a material model."""
    name, _, variant = scene_name.partition("+")
    cfg = load_config(ROOT / "configs" / name)
    cfg = cfg.model_copy(update={"material": cfg.material.model_copy(update={"nu": nu, "model": model})})
    if variant == "cup2":
        cups = list(cfg.cups) + [type(cfg.cups[0]).model_validate(SECOND_CUP)]
        cfg = cfg.model_copy(update={"cups": cups})
    return cfg


def _tissues(scene_name: str, nu: float, model: str, scale: float = 1.0):
    """{element: Tissue} of a shipped scene at ν with a material model, on one mesh."""
    cfg = _config(scene_name, nu, model)
    if scene_name.startswith("example_dome.yaml"):
        scene, mesh, _ = body_model(cfg, cache=ROOT / "runs" / ".mesh-cache", scale=scale)
        return {e: build_body(scene, mesh, element=e) for e in ELEMENTS}
    scene, mesh, _ = build_model(cfg)
    return {e: build_tissue(scene, mesh, element=e) for e in ELEMENTS}


def _targets(tissue) -> np.ndarray:
    return np.array([t.rest for t in tissue.scene.targets]).reshape(len(tissue.scene.targets), -1)


#: (scene, ν) → (the scene's `nodal` tissue at ν, `_references`' answer): the α sweep and the mixed cost row
#: reuse the accuracy table's tissues and solves
_SOLVED: dict = {}


def _references(tissue, nu: float, strokes: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, object, float]:
    """(P2's displacements (K, d) at the points, the Taylor–Hood solve there, P2's time in s) of the tissue's
    mesh, held nodes and cup strokes, linear elasticity at ν."""
    moved = tissue.apply_strokes(tissue.rest, strokes) - tissue.rest
    args = (*quadratic_reference.mesh_and_held(tissue), moved, tissue.element_E_kPa, nu, points)
    t0 = time.perf_counter()
    _, p2 = quadratic_reference.solve_p2(*args)
    p2_s = time.perf_counter() - t0
    return p2, quadratic_reference.solve_mixed(*args), p2_s


def _off_pct(u: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """|u − ref| / |ref| per point (K,), in %."""
    return 100 * np.linalg.norm(u - ref, axis=1) / np.linalg.norm(ref, axis=1)


def accuracy_rows(scene_name: str) -> list[dict]:
    """Per ν and target: |u − u_ref| / |u_ref| of p1 and nodal against P2 and against Taylor–Hood (and P2's own
    against Taylor–Hood), 1 mm push of every cup, linear elasticity."""
    rows = []
    for nu in NUS:
        tissues = _tissues(scene_name, nu, "linear")
        any_t = tissues["p1"]
        points = _targets(any_t)
        strokes = np.ones(any_t.n_cups)
        ref, mixed, p2_s = _references(any_t, nu, strokes, points)
        _SOLVED[scene_name, nu] = tissues["nodal"], (ref, mixed, p2_s)
        th = mixed.at_points
        probe = probe_points(any_t.mesh.nodes, any_t.ops.triangles, points)
        moves = {e: target_positions(probe, solve_equilibrium(t, strokes, method="newton").x) - points
                 for e, t in tissues.items()}
        for k, name in enumerate(t.name for t in any_t.scene.targets):
            row = {"scene": scene_name, "nu": nu, "target": name, "p2_move_mm": float(np.linalg.norm(ref[k])),
                   "p2_s": p2_s, "th_move_mm": float(np.linalg.norm(th[k])),
                   "th_iterations": mixed.iterations, "p2_off_th_pct": float(_off_pct(ref, th)[k])}
            for element, u in moves.items():
                row[f"{element}_error_pct"] = float(_off_pct(u, ref)[k])
                row[f"{element}_off_th_pct"] = float(_off_pct(u, th)[k])
            rows.append(row)
            print(f"{scene_name} ν {nu} {name}: p1 {row['p1_error_pct']:.1f} %, nodal {row['nodal_error_pct']:.1f} %"
                  f" off P2 (P2 move {row['p2_move_mm']:.4f} mm); off Taylor–Hood p1 {row['p1_off_th_pct']:.1f} %, "
                  f"nodal {row['nodal_off_th_pct']:.1f} %, P2 {row['p2_off_th_pct']:.1f} %", flush=True)
    return rows


def cost_rows(scene_name: str, stroke_mm: float, repeats: int) -> list[dict]:
    """Per element: assembly, nonzeros, factorisation and a nonlinear forward solve, at the scene's material."""
    cfg = load_config(ROOT / "configs" / scene_name)
    tissues = _tissues(scene_name, 0.45, cfg.material.model)
    rows = []
    for element, tissue in tissues.items():
        strokes = np.zeros(tissue.n_cups)
        strokes[0] = stroke_mm
        assemble_s, K = _median_time(lambda t=tissue: t.stiffness_free(t.rest, upper=True), repeats)
        factor_s, _ = _median_time(lambda t=tissue, K=K: factorize_free(t, K, {}), repeats)
        solve_s, r = _median_time(lambda t=tissue, s=strokes: solve_equilibrium(t, s, method="newton", tol=1e-8),
                                  repeats)
        rows.append({"scene": scene_name, "element": element, "unknowns": int(tissue.free_dofs.size),
                     "K_upper_nnz": int(K.nnz), "assemble_ms": 1e3 * assemble_s, "factor_ms": 1e3 * factor_s,
                     "forward_s": solve_s, "newton_iterations": int(r.iterations), "stroke_mm": stroke_mm})
        print(f"{scene_name} {element}: nnz {K.nnz}, assemble {1e3 * assemble_s:.1f} ms, "
              f"factor {1e3 * factor_s:.1f} ms, forward {solve_s:.2f} s ({r.iterations} it)", flush=True)
    return rows + [p2_cost_row(scene_name, tissues["p1"], repeats), mixed_cost_row(scene_name, tissues["p1"], repeats)]


def p2_cost_row(scene_name: str, tissue, repeats: int) -> dict:
    """Quadratic elements' side of the cost table on the same mesh and held nodes: the unknowns, K_ff's upper
    nonzeros, scikit-fem's assembly of the linear-elastic K (scissor has no nonlinear P2 to time) and the same
    CHOLMOD factorisation as the others (nested dissection by node, `linear.Factorization`)."""
    system = quadratic_reference.p2_system(*quadratic_reference.mesh_and_held(tissue),
                                           np.zeros_like(tissue.rest), tissue.element_E_kPa, 0.45)
    assemble_s, K = _median_time(system.assemble, repeats)
    free = np.setdiff1d(np.arange(K.shape[0]), system.held_dofs)
    K_upper = sp.triu(K.tocsr()[free][:, free], format="csr")
    K_upper.sort_indices()

    def factor():
        return Factorization(K_upper, definite=True, upper=True, ordering="nested_dissection",
                             groups=system.node_of_dof[free])

    factor_s, _ = _median_time(factor, repeats)
    print(f"{scene_name} p2: {free.size} unknowns, nnz {K_upper.nnz}, assemble {1e3 * assemble_s:.1f} ms, "
          f"factor {1e3 * factor_s:.1f} ms", flush=True)
    return {"scene": scene_name, "element": "p2", "unknowns": int(free.size), "K_upper_nnz": int(K_upper.nnz),
            "assemble_ms": 1e3 * assemble_s, "factor_ms": 1e3 * factor_s, "forward_s": None,
            "newton_iterations": None, "stroke_mm": None}


def mixed_cost_row(scene_name: str, tissue, repeats: int) -> dict:
    """Taylor–Hood's side of the cost table (`p2_cost_row`'s, for P2 displacements with a P1 pressure): the
    unknowns (both fields), the nonzeros of the saddle-point matrix's upper triangle, scikit-fem's assembly of its
    blocks, the same CHOLMOD factorisation of the displacement block, and the pressure's CG iterations on the
    Schur complement (each a solve with that factor) under a 1 mm push."""
    args = quadratic_reference.mesh_and_held(tissue)
    system = quadratic_reference.mixed_system(*args, np.zeros_like(tissue.rest), tissue.element_E_kPa, 0.45)
    assemble_s, (A, B, C, _) = _median_time(system.assemble, repeats)
    free = system.free
    A_upper = sp.triu(A[free][:, free], format="csr")
    A_upper.sort_indices()
    nnz = A_upper.nnz + B[:, free].nnz + sp.triu(C).nnz

    def factor():
        return Factorization(A_upper, definite=True, upper=True, ordering="nested_dissection",
                             groups=system.p2.node_of_dof[free])

    factor_s, _ = _median_time(factor, repeats)
    mixed = _SOLVED[scene_name, 0.45][1][1]  # the accuracy table's solve at ν 0.45: the same mesh, E and push
    print(f"{scene_name} Taylor–Hood: {free.size} + {B.shape[0]} unknowns, nnz {nnz}, assemble "
          f"{1e3 * assemble_s:.1f} ms, factor {1e3 * factor_s:.1f} ms, {mixed.iterations} pressure iterations",
          flush=True)
    return {"scene": scene_name, "element": "p2/p1", "unknowns": int(free.size + B.shape[0]), "K_upper_nnz": int(nnz),
            "assemble_ms": 1e3 * assemble_s, "factor_ms": 1e3 * factor_s, "forward_s": None,
            "newton_iterations": None, "stroke_mm": None, "pressure_iterations": mixed.iterations}


#: the shares α of the element's own deviatoric energy the sweep tries (nodal.ELEMENT_SHARE is the built one)
SHARES = (0.0, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, 0.65, 0.8, 1.0)


def share_rows(scene_name: str) -> list[dict]:
    """The scene (a dome), linear elasticity at each ν, a 1 mm push of every cup: the worst target's error against
    P2 and against Taylor–Hood for every α in SHARES, and how much further than Taylor–Hood's it moves (+: further).
    The references are the accuracy table's (`accuracy_rows` first)."""
    rows = []
    for nu in NUS:
        tissue, (ref, mixed, _) = _SOLVED[scene_name, nu]
        points = _targets(tissue)
        strokes = np.ones(tissue.n_cups)
        th = mixed.at_points
        probe = probe_points(tissue.mesh.nodes, tissue.ops.triangles, points)
        for share in SHARES:
            t = replace(tissue, element=tissue.element.with_share(share), factor_cache={})
            u = target_positions(probe, solve_equilibrium(t, strokes, method="newton").x) - points
            err, off_th = _off_pct(u, ref), _off_pct(u, th)
            worst = int(np.argmax(off_th))
            further = 100 * (np.linalg.norm(u[worst]) / np.linalg.norm(th[worst]) - 1)
            rows.append({"scene": scene_name, "share": share, "nu": nu, "max_error_pct": float(err.max()),
                         "max_off_th_pct": float(off_th.max()), "further_than_th_pct": float(further)})
            print(f"{scene_name} ν {nu} share α {share}: worst target {err.max():.1f} % off P2, "
                  f"{off_th.max():.1f} % off Taylor–Hood ({further:+.1f} % of its move)", flush=True)
    return rows


def refinement_rows(repeats: int) -> list[dict]:
    """The dome with its fibers at ν 0.49, an 8 mm push: how far the lesions move from mesh scale 1 to 0.7."""
    rows = []
    ends = {}
    for scale in (1.0, 0.7):
        for element, tissue in _tissues("example_dome.yaml", 0.49, "neo_hookean_fiber", scale).items():
            strokes = np.full(tissue.n_cups, 8.0)
            probe = probe_points(tissue.mesh.nodes, tissue.ops.triangles, _targets(tissue))
            solve_s, r = _median_time(lambda t=tissue, s=strokes: solve_equilibrium(t, s, method="newton", tol=1e-8),
                                      repeats)
            ends[element, scale] = target_positions(probe, r.x)
            rows.append({"element": element, "scale": scale, "tetrahedra": int(tissue.mesh.n_elements),
                         "forward_s": solve_s, "newton_iterations": int(r.iterations)})
            print(f"refinement {element} scale {scale}: {tissue.mesh.n_elements} tetrahedra, {solve_s:.1f} s",
                  flush=True)
    for row in rows:
        if row["scale"] == 0.7:
            e = row["element"]
            row["lesion_shift_mm"] = float(np.linalg.norm(ends[e, 0.7] - ends[e, 1.0], axis=1).max())
            print(f"refinement {e}: lesions move {row['lesion_shift_mm']:.3f} mm from scale 1 to 0.7", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the 2-D example only")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    res = results_io.Results("bench_elements", variant="quick" if args.quick else None)
    scenes = [("example.yaml", 10.0)] + ([] if args.quick else [("example_dome.yaml", 8.0)])
    accuracy, cost = [], []
    for name, stroke in scenes:
        accuracy += accuracy_rows(name)
        cost += cost_rows(name, stroke, args.repeats)
    if not args.quick:
        accuracy += accuracy_rows("example_dome.yaml+cup2")
        res.table("refinement", refinement_rows(1), units={"forward_s": "s", "lesion_shift_mm": "mm"})
        shares = share_rows("example_dome.yaml") + share_rows("example_dome.yaml+cup2")
        res.table("share", shares, units={"max_error_pct": "%", "max_off_th_pct": "%", "further_than_th_pct": "%"})
        res.data("element_share", ELEMENT_SHARE)
    res.table("accuracy", accuracy, units={"p2_move_mm": "mm", "p2_s": "s", "p1_error_pct": "%",
                                           "nodal_error_pct": "%", "th_move_mm": "mm", "p2_off_th_pct": "%",
                                           "p1_off_th_pct": "%", "nodal_off_th_pct": "%"})
    res.table("cost", cost, units={"assemble_ms": "ms", "factor_ms": "ms", "forward_s": "s", "stroke_mm": "mm"})
    print(res.write())


if __name__ == "__main__":
    main()
