"""What moves downstream when the element stops locking (docs/model.md §21): the same runs on `p1` and `nodal`.

Each scene is run by `scissor simulate` (through the Python API) with `tissue.mesh.element` p1 and then nodal,
Newton for both (ADMM refuses `nodal`), no trials; from each results.h5:

* configs/example_full.yaml: the layer check, per forward case, how much the 2-D layer overstates the targets'
  in-plane motion against the 3-D slab (the slab takes the layer's element), and each target's planned strokes;
* configs/example_dome.yaml: each lesion's move under the forward case push10, and the planned strokes;
* configs/example_insertion.yaml: each strategy's nominal insertion, its miss and the target's drag along the
  needle (the largest along-axis move during the insertion).

    PYTHONPATH=. python3 benchmarks/bench_element_downstream.py      # about 15 minutes on 2 cores

Writes benchmarks/results/bench_element_downstream.json.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

import scissor_cli.api as scissor  # noqa: E402
from scissor_cli.output.layer_check import layer_check_rows  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCENES = ("example_full", "example_dome", "example_insertion")
ELEMENTS = ("p1", "nodal")


def _run(scene: str, element: str, out: Path) -> float:
    """`simulate` of the scene on `element` with Newton and no trials into `out`; its wall time (s)."""
    cfg = scissor.load_config(ROOT / "configs" / f"{scene}.yaml")
    mesh = cfg.tissue.mesh.model_copy(update={"element": element})
    cfg = cfg.model_copy(update={"tissue": cfg.tissue.model_copy(update={"mesh": mesh}),
                                 "solver": cfg.solver.model_copy(update={"kind": "newton"}),
                                 "trials": cfg.trials.model_copy(update={"count": 0, "budget": False})})
    t0 = time.perf_counter()
    scissor.simulate(cfg, out, jobs=2)
    return time.perf_counter() - t0


def _rows(scene: str, element: str, f: h5py.File, run_s: float) -> list[dict]:
    rows = []
    base = {"scene": scene, "element": element, "run_s": run_s}
    for r in layer_check_rows(scene, f):
        rows.append(base | {"what": f"layer check {r['case']}", "value": r["layer_check_in_plane_diff_pct"],
                            "unit": "%"})
    if scene == "example_dome" and "forward/push10" in f:
        for name, ds in f["forward/push10/targets"].items():
            rest = np.asarray(f[f"targets/{name}"].attrs["rest"], float)
            rows.append(base | {"what": f"{name} moved by push10", "value": float(np.linalg.norm(ds[()] - rest)),
                                "unit": "mm"})
    for name, g in f.get("plan", {}).items():
        if g.attrs.get("feasible", True) and "strokes" in g.attrs:
            strokes = np.atleast_1d(np.asarray(g.attrs["strokes"], float))
            rows.append(base | {"what": f"{name} planned strokes", "value": float(np.abs(strokes).max()),
                                "unit": "mm"})
    for target, g in f.get("insertion", {}).items():
        for strategy, s in g.items():
            if isinstance(s, h5py.Group) and "miss_mm" in s.attrs:
                along = np.asarray(s["target"][()], float)
                n = np.asarray(s.attrs["direction"], float)[:along.shape[1]]
                drag = float(np.abs((along - along[0]) @ (n / np.linalg.norm(n))).max())
                rows.append(base | {"what": f"{target} `{strategy}` miss", "value": float(s.attrs["miss_mm"]),
                                    "unit": "mm"})
                rows.append(base | {"what": f"{target} `{strategy}` drag along the needle", "value": drag,
                                    "unit": "mm"})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    args = ap.parse_args()
    res = results_io.Results("bench_element_downstream",
                             variant=None if args.scenes == list(SCENES) else "-".join(args.scenes))
    print(f"machine: {results_io.machine()}, load {results_io.load1()}")
    rows = []
    for scene in args.scenes:
        for element in ELEMENTS:
            with tempfile.TemporaryDirectory() as out:
                run_s = _run(scene, element, Path(out))
                with h5py.File(Path(out) / "results.h5", "r") as f:
                    new = _rows(scene, element, f, run_s)
            rows += new
            print(f"{scene} {element} ({run_s:.0f} s): "
                  + "; ".join(f"{x['what']} {x['value']:.3f} {x['unit']}" for x in new), flush=True)
    res.table("downstream", rows, units={"run_s": "s"})
    print(res.write())


if __name__ == "__main__":
    main()
