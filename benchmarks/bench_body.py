"""The breast in 3-D (docs/model.md §19): a body's mesh, one equilibrium, and a forward run, timed; not a test.

On configs/example_dome.yaml (the paper's bench as a dome: radius 60, height 35 mm, two lesions, a vessel,
a cyst, one cup on the skin):

* the mesh at the configured size field, from nothing and from the cache (goal: ≤ 5 s at ~30k
  tetrahedra), its size and smallest dihedral angle;
* one equilibrium on the scene's element (`tissue.mesh.element`, as `simulate` builds it): the forward
  case push10 from rest (the tangent predictor and load steps), and one control-loop move, 10 → 11 mm
  warm started from the 10 mm equilibrium (goal: ≤ 1 s at 30k), each the median of --repeats;
* the cups-to-lesions Jacobian at rest;
* `scissor simulate configs/example_dome.yaml --trials 0` end to end from an empty folder and cache
  (goal: ≤ 30 s).

    PYTHONPATH=. python benchmarks/bench_body.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import results_io

from scissor_cli import runtime

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    runtime.configure()
    from scissor_cli.config import load_config
    from scissor_cli.mechanics.body_tissue import build_body
    from scissor_cli.mesh.body_inputs import mesh_body
    from scissor_cli.mesh.probe import probe_points
    from scissor_cli.scene.body_scene import build_body_scene
    from scissor_cli.solvers.equilibrium import solve_equilibrium
    from scissor_cli.solvers.jacobian import cup_target_jacobian

    res = results_io.Results("bench_body")
    cfg = load_config(CONFIG)
    scene = build_body_scene(cfg)
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp)
        t0 = time.perf_counter()
        mesh = mesh_body(scene, cfg.tissue.mesh, cache=cache)
        mesh_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        mesh_body(scene, cfg.tissue.mesh, cache=cache)
        cached_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    element = cfg.tissue.mesh.element  # the scene's own (its default when the config names none), as simulate
    tissue = build_body(scene, mesh, element=element)
    build_s = time.perf_counter() - t0
    res.data("element", element)
    print(f"{cfg.name}: {mesh.n_elements} tetrahedra ({element}), {mesh.n_nodes} nodes, smallest dihedral "
          f"{mesh.min_dihedral_deg:.1f}°; mesh {mesh_s:.2f} s (cached {1e3 * cached_s:.1f} ms), tissue {build_s:.2f} s",
          flush=True)
    res.figure("tetrahedra", mesh.n_elements, "1")
    res.figure("nodes", mesh.n_nodes, "1")
    res.figure("min_dihedral_deg", mesh.min_dihedral_deg, "deg")
    res.figure("mesh_s", mesh_s, "s")
    res.figure("mesh_cached_s", cached_s, "s")
    res.figure("tissue_s", build_s, "s")

    push = np.array([10.0])
    rest_times, move_times = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        at10 = solve_equilibrium(tissue, push, tol=1e-8)
        rest_times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        at11 = solve_equilibrium(tissue, push + 1.0, start=at10.x, start_strokes=push, tol=1e-8)
        move_times.append(time.perf_counter() - t0)
    print(f"push10 from rest: {np.median(rest_times):.2f} s median ({at10.iterations} Newton iterations, "
          f"{at10.message}); 10 -> 11 mm warm: {np.median(move_times):.2f} s ({at11.iterations} iterations)",
          flush=True)
    res.figure("from_rest_s", float(np.median(rest_times)), "s")
    res.figure("from_rest_iterations", at10.iterations, "1")
    res.figure("move_s", float(np.median(move_times)), "s")
    res.figure("move_iterations", at11.iterations, "1")

    probe = probe_points(mesh.nodes, mesh.tetrahedra, np.array([t.rest for t in scene.targets]))
    t0 = time.perf_counter()
    cup_target_jacobian(tissue, tissue.rest, probe)
    res.figure("jacobian_s", time.perf_counter() - t0, "s")

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        shutil.rmtree(Path(tmp) / ".scissor-cache", ignore_errors=True)
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(CONFIG), "--trials", "0", "--out",
                            str(out), "--quiet"], capture_output=True, text=True, cwd=tmp)
        run_s = time.perf_counter() - t0
        if r.returncode != 0:
            raise SystemExit(f"simulate failed ({r.returncode}):\n{r.stderr[-2000:]}")
    print(f"scissor simulate {CONFIG.name} --trials 0 from nothing: {run_s:.1f} s", flush=True)
    res.figure("forward_run_s", run_s, "s")
    res.write()


if __name__ == "__main__":
    main()
