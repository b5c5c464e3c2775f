"""Cook's membrane in 3-D at ν 0.49 (docs/model.md §21): the locking benchmark, per element, under refinement.

The tapered panel of Cook (1974) — corners (0, 0), (48, 44), (48, 60), (0, 44) mm — extruded 10 mm in z,
clamped on its left face (x = 0); its right face (x = 48) is moved 1 mm in y (a shear stroke, held in x
and z). Linear elasticity, E 10 kPa, ν 0.49. The mesh: n × n × n/4 hexahedra mapped onto the panel, six
tetrahedra each, n = 4, 8, 16, 32. The figure is the reaction force on the right face along y (mN): locking
makes an element too stiff, so a locking element's force is too large and falls slowly under refinement.
Per element and level: the tetrahedra, the force, the change from the previous level, the observed order
p = log2(ΔF_k / ΔF_k+1) from three consecutive levels, and the finest level's error against the Richardson
extrapolation of `nodal`'s three finest levels (the reference both elements are measured against).

    PYTHONPATH=. python3 benchmarks/bench_cook.py            # about 3 minutes on 2 cores

Writes benchmarks/results/bench_cook.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import results_io  # noqa: E402

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.experiments.build import scene_of  # noqa: E402
from scissor_cli.mechanics import fem  # noqa: E402
from scissor_cli.mechanics.tissue import scene_material, tissue_from_boundary  # noqa: E402
from scissor_cli.solvers.equilibrium import solve_equilibrium  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LEVELS = (4, 8, 16, 32)
ELEMENTS = ("p1", "nodal")
NU = 0.49
THICKNESS_MM = 10.0
STROKE_MM = 1.0
#: the six tetrahedra of a hexahedron (its corners numbered by the bits x + 2y + 4z), all sharing the 0–7
#: diagonal, so neighbouring hexahedra's faces split the same way
HEX_TETS = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])


def cook_mesh(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (N, 3) mm and positively oriented tetrahedra (M, 4) of the panel with n × n × max(1, n/4) cells."""
    nz = max(1, n // 4)
    s, t, u = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), np.linspace(0, 1, nz + 1),
                          indexing="ij")
    x = 48.0 * s
    y = 44.0 * s + t * (44.0 + (60.0 - 44.0) * s - 44.0 * s)  # bottom edge 0 → 44, top edge 44 → 60
    nodes = np.column_stack([x.ravel(), y.ravel(), THICKNESS_MM * u.ravel()])
    index = np.arange(nodes.shape[0]).reshape(n + 1, n + 1, nz + 1)
    i, j, k = np.meshgrid(np.arange(n), np.arange(n), np.arange(nz), indexing="ij")
    corners = np.stack([index[i + (b & 1), j + ((b >> 1) & 1), k + ((b >> 2) & 1)].ravel() for b in range(8)], axis=1)
    tets = corners[:, HEX_TETS].reshape(-1, 4)
    e = nodes[tets]
    volume = np.einsum("ij,ij->i", np.cross(e[:, 1] - e[:, 0], e[:, 2] - e[:, 0]), e[:, 3] - e[:, 0])
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]
    return nodes, tets


def cook_tissue(n: int, element: str):
    """The panel as a `Tissue`: the left face held, the right face one 'cup' moving along y."""
    cfg = load_config(ROOT / "configs" / "example.yaml")
    cfg = cfg.model_copy(update={"material": cfg.material.model_copy(update={"nu": NU, "model": "linear"})})
    scene = scene_of(cfg)
    nodes, tets = cook_mesh(n)
    mesh = SimpleNamespace(nodes=nodes, triangles=tets, tetrahedra=tets, n_nodes=len(nodes), n_elements=len(tets))
    ops = fem.simplex_operators(nodes, tets)
    material = scene_material(scene, np.full(len(tets), -1, np.int64), "linear")
    fixed = np.flatnonzero(nodes[:, 0] < 1e-9)
    right = np.flatnonzero(nodes[:, 0] > 48.0 - 1e-9)
    held = np.concatenate([fixed, right])
    dirichlet = np.sort(np.concatenate([3 * held, 3 * held + 1, 3 * held + 2]))
    return tissue_from_boundary(scene, mesh, ops, material, fixed, [right], np.array([[0.0, 1.0, 0.0]]),
                                dirichlet, element), right


def level_rows() -> list[dict]:
    rows = []
    for n in LEVELS:
        for element in ELEMENTS:
            tissue, right = cook_tissue(n, element)
            t0 = time.perf_counter()
            r = solve_equilibrium(tissue, np.array([STROKE_MM]), method="newton", tol=1e-10)
            _, grad = tissue.energy_gradient(r.x)
            force = float(np.sum(grad.reshape(-1, 3)[right, 1]))
            rows.append({"element": element, "n": n, "tetrahedra": int(tissue.mesh.n_elements),
                         "force_mN": force, "solve_s": time.perf_counter() - t0,
                         "newton_iterations": int(r.iterations)})
            print(f"{element} n={n}: {tissue.mesh.n_elements} tetrahedra, reaction {force:.4f} mN "
                  f"({rows[-1]['solve_s']:.1f} s)", flush=True)
    return rows


def orders(rows: list[dict]) -> list[dict]:
    series = {e: np.array([r["force_mN"] for r in rows if r["element"] == e]) for e in ELEMENTS}
    f = series["nodal"]
    p_ref = np.log2((f[-3] - f[-2]) / (f[-2] - f[-1]))
    reference = f[-1] + (f[-1] - f[-2]) / (2.0 ** p_ref - 1.0)
    out = []
    for element, f in series.items():
        d = np.diff(f)
        p = [float(np.log2(d[k] / d[k + 1])) if d[k + 1] != 0 and d[k] / d[k + 1] > 0 else float("nan")
             for k in range(len(d) - 1)]
        out.append({"element": element, "forces_mN": f.tolist(), "changes_mN": d.tolist(), "orders": p,
                    "reference_mN": float(reference),
                    "errors_pct": (100.0 * (f - reference) / reference).tolist()})
        print(f"{element}: forces {np.round(f, 4).tolist()} mN, orders {np.round(p, 2).tolist()}, errors against "
              f"{reference:.4f} mN: {np.round(out[-1]['errors_pct'], 2).tolist()} %", flush=True)
    return out


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    res = results_io.Results("bench_cook")
    print(f"machine: {results_io.machine()}, load {results_io.load1()}")
    rows = level_rows()
    res.table("levels", rows, units={"force_mN": "mN", "solve_s": "s"})
    res.table("orders", orders(rows), units={"forces_mN": "mN", "changes_mN": "mN", "reference_mN": "mN",
                                             "errors_pct": "%"})
    print(res.write())


if __name__ == "__main__":
    main()
