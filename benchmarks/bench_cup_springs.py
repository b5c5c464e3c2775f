"""A cup that holds the skin rigidly against one that holds it through springs (docs/model.md §21, "What it
does not do yet"); a measurement, not a test, and not a model scissor offers.

scissor's cup moves its patch of skin rigidly with the stroke (Dirichlet dofs). The rim of a rigid patch is a
singularity of the continuum (a flat punch's edge): on configs/example_dome.yaml one element there nearly
collapses under push10, and the load continuation from rest takes several substeps for it. This asks what a
compliant grip would change: each patch node tied by a zero-length spring to where the rigid cup would put
it, the springs a bed of stiffness k = E / t per mm² of the node's share of the skin (t: the thickness of a
layer of the tissue's own modulus that would be as stiff), the patch's dofs then free. The bed is the
implicit-Euler term of `solvers.common.Inertia` with Δt = 1 s and the springs' stiffness as its weights:
½ ‖x − x̃‖²_W with x̃ the rigid cup's placement, the same Newton and load continuation (`solve_newton`).

Per hold, push10 from rest on the scene's element (`tissue.mesh.element`), Newton to 1e-8: the wall time
(median of --repeats), Newton iterations, factorisations, load substeps, the smallest J, the patch's mean
push along the cup's axis, and each lesion's move against the rigid cup's.

    PYTHONPATH=. python benchmarks/bench_cup_springs.py [--repeats 2] [--thickness-mm 0.1 0.3 1 3]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import results_io

from scissor_cli import runtime

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"
STROKE_MM = 10.0
TOL = 1e-8


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--thickness-mm", type=float, nargs="+", default=[0.1, 0.3, 1.0, 3.0])
    args = ap.parse_args()
    runtime.configure()
    from scissor_cli.config import load_config
    from scissor_cli.mechanics.body_tissue import build_body, skin_areas, skin_nodes
    from scissor_cli.mechanics.tissue import tissue_from_boundary
    from scissor_cli.mesh.body_inputs import mesh_body
    from scissor_cli.mesh.probe import target_positions
    from scissor_cli.scene.body_scene import build_body_scene
    from scissor_cli.solvers.common import Inertia
    from scissor_cli.solvers.newton import solve_newton

    res = results_io.Results("bench_cup_springs")
    cfg = load_config(CONFIG)
    scene = build_body_scene(cfg)
    if len(scene.cups) != 1:
        raise SystemExit(f"{CONFIG.name}: one cup expected, found {len(scene.cups)}")
    with tempfile.TemporaryDirectory() as tmp:
        mesh = mesh_body(scene, cfg.tissue.mesh, cache=Path(tmp))
    element = cfg.tissue.mesh.element
    rigid = build_body(scene, mesh, element=element)
    cup, patch = scene.cups[0], rigid.cup_nodes[0]
    # the same tissue with the patch free: only the held faces are Dirichlet
    fixed = rigid.fixed_nodes
    held = np.sort((3 * fixed[:, None] + np.arange(3)).ravel()).astype(np.int64)
    gripped = tissue_from_boundary(scene, mesh, rigid.ops, (rigid.element_E_kPa, rigid.fiber, rigid.params), fixed,
                                   [], np.zeros((0, 3)), held, element)
    skin = skin_nodes(scene, mesh, fixed)
    share = np.zeros(mesh.n_nodes)
    share[skin] = skin_areas(mesh, skin)
    share_mm2 = share[patch]  # each patch node's share of the skin (mm²)
    probe = rigid.probe(np.array([t.rest for t in scene.targets]))
    at_rest = target_positions(probe, mesh.nodes)
    axis = np.asarray(cup.axis, float)
    placed = mesh.nodes.copy()
    placed[patch] += STROKE_MM * axis  # where the rigid cup puts its patch
    res.data("element", element)
    res.figure("tetrahedra", mesh.n_elements, "1")
    res.figure("patch_nodes", int(patch.size), "1")
    res.figure("patch_area_mm2", float(share_mm2.sum()), "mm^2")
    print(f"{cfg.name}: {mesh.n_elements} tetrahedra ({element}); cup {cup.name!r}: {patch.size} skin nodes, "
          f"{share_mm2.sum():.1f} mm²; push {STROKE_MM:g} mm from rest, Newton to {TOL:g}", flush=True)

    def solve(tissue, strokes, inertia=None):
        times, r = [], None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            r = solve_newton(tissue, strokes, inertia=inertia, tol=TOL)
            times.append(time.perf_counter() - t0)
        return r, float(np.median(times))

    rows, rigid_moves = [], None
    E_kPa = scene.material.E_kPa
    for thickness in [None, *args.thickness_mm]:
        if thickness is None:
            r, wall_s = solve(rigid, np.array([STROKE_MM]))
            hold, k = "rigid", None
        else:
            k = E_kPa / thickness  # kPa/mm = mN/mm per mm²
            weight = np.zeros(mesh.nodes.size)
            weight.reshape(-1, 3)[patch] = (k * share_mm2)[:, None]
            r, wall_s = solve(gripped, np.zeros(0), Inertia(1.0, placed.ravel(), weight))
            hold = f"springs, t = {thickness:g} mm"
        moves = np.linalg.norm(target_positions(probe, r.x) - at_rest, axis=1)
        rigid_moves = moves if rigid_moves is None else rigid_moves
        push = (r.x[patch] - mesh.nodes[patch]) @ axis
        row = {"hold": hold, "thickness_mm": thickness, "k_mN_per_mm3": k, "wall_s": wall_s,
               "iterations": r.iterations, "factorizations": r.factorizations, "substeps": r.substeps,
               "min_J": float(np.min(rigid.jacobians(r.x))), "patch_push_mm": float(push.mean()),
               "patch_push_min_mm": float(push.min()),
               **{f"move_{t.name}_mm": float(m) for t, m in zip(scene.targets, moves)}}
        rows.append(row)
        print(f"{hold}: {wall_s:.2f} s, {r.iterations} iterations, {r.factorizations} factorisations, "
              f"{row['substeps']} substeps, smallest J {row['min_J']:.3f}, patch push {row['patch_push_mm']:.2f} mm "
              f"(least {row['patch_push_min_mm']:.2f}), lesions move {np.round(moves, 3).tolist()} mm "
              f"({np.round(moves / rigid_moves, 3).tolist()} of the rigid cup's)", flush=True)
    res.table("holds", rows, {"thickness_mm": "mm", "k_mN_per_mm3": "mN/mm^3", "wall_s": "s", "patch_push_mm": "mm",
                              "patch_push_min_mm": "mm", **{f"move_{t.name}_mm": "mm" for t in scene.targets}})
    res.write()


if __name__ == "__main__":
    main()
