"""The needle in nearly incompressible tissue (docs/model.md §12, "The chord step's arithmetic"); not a test.

configs/example_dome.yaml's body at ν 0.45 (the paper's silicone), 0.49 (breast tissue) and 0.499 (the hard
case), the needle along −x through T1 at rest from where that line enters the skin, 50 mm in 0.5 mm steps,
strategy `none`, the default needle–tissue parameters. Each ν three ways, in this process, in turn:

* `shipped`: as scissor runs it;
* `no float64 copy`: where float32 cannot carry the factor, its solves through cvxopt's CHOLMOD (as before
  `Factorization.double`);
* `neither`: besides, a fresh factorisation's step that does not contract goes to Newton from the pass's start
  (as before `ChordSolver._damped`).

Per row: the wall time (median of --repeats), the factorisations the needle's chord solver made, the passes
Newton took over, whether its solves went to float64, and how far the lesion ends from the shipped run's (the
same equilibria to the solver's tolerance).

    PYTHONPATH=. python3 benchmarks/bench_needle_incompressible.py [--repeats 3]   # about 15 minutes on 2 cores

Writes benchmarks/results/bench_needle_incompressible.json.
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
import scissor_cli.insertion.needle as needle  # noqa: E402
from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.config.sections import InsertionConfig  # noqa: E402
from scissor_cli.experiments.build import body_model  # noqa: E402
from scissor_cli.insertion import InsertionOptions, NeedleParams, run_strategies  # noqa: E402
from scissor_cli.insertion.chord import ChordSolver  # noqa: E402
from scissor_cli.solvers.equilibrium import solve_equilibrium  # noqa: E402
from scissor_cli.solvers.linear import Factorization  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"
DEPTH_MM, STEP_MM = 50.0, 0.5
NUS = (0.45, 0.49, 0.499)
#: (name, float64 copy, damping): the shipped solver first (the others are held to its lesion)
VARIANTS = (("shipped", True, True), ("no float64 copy", False, True), ("neither", False, False))


class Counts:
    """The needle's chord factorisations, Newton take-overs and float64 switches, by wrapping what makes them."""

    def __init__(self):
        self.factorisations = self.newton = 0
        self.solvers: list[ChordSolver] = []
        refactor, solve, init = ChordSolver.refactor, needle.solve_equilibrium, ChordSolver.__init__

        def counted_refactor(solver, x):
            self.factorisations += 1
            return refactor(solver, x)

        def counted_solve(*args, **kwargs):
            self.newton += 1
            return solve(*args, **kwargs)

        def kept(solver, *args, **kwargs):
            init(solver, *args, **kwargs)
            self.solvers.append(solver)

        ChordSolver.refactor, needle.solve_equilibrium, ChordSolver.__init__ = counted_refactor, counted_solve, kept

    def reset(self) -> None:
        self.factorisations = self.newton = 0
        self.solvers = []


def variant(copy: bool, damping: bool) -> tuple:
    """Switch the float64 copy and the damping on or off; returns what restores them."""
    double, damped = Factorization.double, ChordSolver._damped
    if not copy:
        Factorization.double = lambda self: None
    if not damping:
        ChordSolver._damped = lambda self, *args: None
    return double, damped


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    res = results_io.Results("bench_needle_incompressible")
    counts = Counts()
    rows = []
    for nu in NUS:
        cfg = load_config(CONFIG)
        cfg = cfg.model_copy(update={"material": cfg.material.model_copy(update={"nu": nu})})
        scene, mesh, tissue = body_model(cfg, cache=ROOT / "runs" / ".mesh-cache")
        params = NeedleParams.from_config(InsertionConfig(step_mm=STEP_MM), cfg.needle, cfg.tissue.mesh)
        strokes = np.zeros(len(scene.cups))
        x0 = solve_equilibrium(tissue, strokes).x
        path = lesion_path(mesh, scene.targets[0], DEPTH_MM)
        walls: dict[str, list] = {name: [] for name, _, _ in VARIANTS}
        last: dict[str, tuple] = {}
        for _ in range(args.repeats):  # the variants in turn, so the machine's drift falls on each alike
            for name, copy, damping in VARIANTS:
                restore = variant(copy, damping)
                try:
                    counts.reset()
                    t0 = time.perf_counter()
                    r = run_strategies(tissue, x0, strokes, {"none": path}, params,
                                       {"none": InsertionOptions("none", cfg.controller, keep_displacement=False)})[0]
                    walls[name].append(time.perf_counter() - t0)
                finally:
                    Factorization.double, ChordSolver._damped = restore
                last[name] = (r, counts.factorisations, counts.newton,
                              any(not s.single_precision for s in counts.solvers))
        shipped_end = last[VARIANTS[0][0]][0].target[-1]
        for name, _, _ in VARIANTS:
            r, factorisations, newton, double = last[name]
            rows.append({"nu": nu, "variant": name, "tetrahedra": int(mesh.n_elements),
                         "wall_s": statistics.median(walls[name]), "steps": r.steps, "stop": r.stop_reason,
                         "factorisations": factorisations, "newton": newton, "float64": double,
                         "lesion_off_mm": float(np.linalg.norm(r.target[-1] - shipped_end))})
            print(f"ν {nu}, {name}: {rows[-1]['wall_s']:.1f} s, {r.steps} steps, {factorisations} factorisations, "
                  f"{newton} Newton, float64 {double}, lesion {rows[-1]['lesion_off_mm']:.1e} mm off the shipped "
                  f"run's", flush=True)
    res.table("runs", rows, {"wall_s": "s", "lesion_off_mm": "mm"})
    print(f"wrote {res.write()}")


if __name__ == "__main__":
    main()
