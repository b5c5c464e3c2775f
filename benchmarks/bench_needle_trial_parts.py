"""Where a body trial with the needle spends its time (docs/model.md §20); a measurement, not a test.

configs/example_dome.yaml with `insertion` (every strategy) and --count trials per lesion, run as
`scissor simulate --jobs 1` runs it, in this process, with every insertion's solves timed and charged to what
asked for them:

* the needle's steps: their active-set passes (`insertion.needle`), every strategy;
* the cups' moves under the needle: the plant settled at `loop`'s command with the needle's hold
  (`insertion.model_state.move_held`), each also binned by its size (the largest stroke change);
* the controller's model following the plant's needle (`ModelState.follow`: only for a lesion without a needle
  model) and the held J (`target_response`: the needle models' table).

Within each, the kept factorisations made again (`ChordSolver.refactor`) and the Newton solves that took over
where the chord steps failed. The needle models `loop` steers with (stage `needle models`: each lesion's
nominal `depth` insertion tabulated, once per run), the scene's own insertion (stage `nominal`: every strategy
in the undrawn body) and the trials' are kept apart, and within each the needles (`none` + `depth` share one
until one stops, `loop` goes alone); a share is of its stage's insertions. A trial's whole time (its closed loop
too) is results.h5's `trial_time_s`.

    PYTHONPATH=. python3 benchmarks/bench_needle_trial_parts.py [--count 2]     # about 3 minutes on 2 cores

Writes benchmarks/results/bench_needle_trial_parts.json.
"""

from __future__ import annotations

import argparse
import collections
import statistics
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import results_io
import yaml

from scissor_cli import runtime

runtime.configure()  # before scissor's modules load cvxopt (runtime.match_blas_kernels)
import scissor_cli.experiments.body_closed_loop as body_closed_loop  # noqa: E402
import scissor_cli.experiments.body_insertion as body_insertion  # noqa: E402
import scissor_cli.experiments.body_trials as body_trials  # noqa: E402
import scissor_cli.insertion.model_state as model_state  # noqa: E402
import scissor_cli.insertion.needle as needle  # noqa: E402
import scissor_cli.insertion.run as insertion_run  # noqa: E402
from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.experiments.simulate import Execution, run_simulation  # noqa: E402
from scissor_cli.insertion.chord import ChordSolver  # noqa: E402
from scissor_cli.output.results_sink import RunDirectory  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"
#: the parts of an insertion, by the function that asks for its solves
PARTS = ("needle steps", "cup moves under the needle", "the model follows", "the loop's J")
#: the run's stages with insertions, in the order they run
STAGES = ("needle models", "nominal", "trials")
#: the cup moves' size bins (mm, the largest stroke change; upper bounds)
MOVE_BINS = (0.05, 0.2, 0.45, np.inf)


class Ledger:
    """Time, calls, refactorisations and Newton take-overs per (stage, part), and each cup move's (stage, size,
    time, refactorisations, Newton), filled by wrapping the functions that ask for an insertion's solves."""

    def __init__(self):
        self.parts = collections.defaultdict(lambda: collections.Counter())
        self.moves: list[dict] = []
        self.stage, self.strategies, self.part = "other", "", None

    def charge(self, key: str, amount: float = 1.0) -> None:
        if self.part is not None:
            self.parts[(self.stage, self.strategies, self.part)][key] += amount

    def wrap_while(self, owner, name: str, attribute: str, value) -> None:
        """owner.name sets this ledger's attribute to value(args) while it runs."""
        inner = getattr(owner, name)

        def labelled(*args, **kwargs):
            before = getattr(self, attribute)
            setattr(self, attribute, value(args))
            try:
                return inner(*args, **kwargs)
            finally:
                setattr(self, attribute, before)
        setattr(owner, name, labelled)

    def wrap_part(self, owners, name: str, part: str, on_move: bool = False) -> None:
        inner = getattr(owners[0], name)

        def charged(*args, **kwargs):
            if self.part is not None:  # (a part inside another: the outer one pays)
                return inner(*args, **kwargs)
            self.part = part
            counts = self.parts[(self.stage, self.strategies, part)]
            before = (counts["refactorisations"], counts["newton"])
            t0 = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                wall = time.perf_counter() - t0
                counts["calls"] += 1
                counts["wall_s"] += wall
                if on_move:  # move_held(tissue, state, x, s, command, ...)
                    size = float(np.max(np.abs(np.asarray(args[4]) - np.asarray(args[3]))))
                    self.moves.append({"stage": self.stage, "size_mm": size, "wall_s": wall,
                                       "refactorisations": counts["refactorisations"] - before[0],
                                       "newton": counts["newton"] - before[1]})
                self.part = None
        for owner in owners:
            setattr(owner, name, charged)

    def wrap_counted(self, owners, name: str, key: str) -> None:
        inner = getattr(owners[0], name)

        def counted(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                self.charge(key)
                self.charge(f"{key}_s", time.perf_counter() - t0)
        for owner in owners:
            setattr(owner, name, counted)


def instrument() -> Ledger:
    ledger = Ledger()
    for owner in (body_insertion, body_closed_loop):  # (the caller holds its own name for it)
        ledger.wrap_while(owner, "body_insertion_stage", "stage", lambda args: "nominal")
        ledger.wrap_while(owner, "body_needle_models", "stage", lambda args: "needle models")
    ledger.wrap_while(body_trials.BodyTrialContext, "insert", "stage", lambda args: "trials")
    # _insert_together(tissue, x0, strokes, path, params, options): the strategies on one needle
    ledger.wrap_while(insertion_run, "_insert_together", "strategies", lambda args: " + ".join(args[5]))
    ledger.wrap_part([needle], "_solve_pass", PARTS[0])
    ledger.wrap_part([model_state, insertion_run], "move_held", PARTS[1], on_move=True)
    ledger.wrap_part([model_state.ModelState], "follow", PARTS[2])
    ledger.wrap_part([model_state.ModelState], "target_response", PARTS[3])
    ledger.wrap_counted([ChordSolver], "refactor", "refactorisations")
    ledger.wrap_counted([needle, model_state], "solve_equilibrium", "newton")
    return ledger


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=2, help="trials per lesion")
    args = ap.parse_args()
    res = results_io.Results("bench_needle_trial_parts")
    scene = yaml.safe_load(CONFIG.read_text())
    scene["insertion"] = {"strategies": ["none", "depth", "loop"]}
    scene["trials"] = dict(scene["trials"], count=args.count)
    ledger = instrument()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "dome_needle.yaml"
        path.write_text(yaml.safe_dump(scene, sort_keys=False))
        cfg = load_config(path)
        run_simulation(cfg, RunDirectory(Path(tmp) / "run"), execution=Execution(jobs=1))
        with h5py.File(Path(tmp) / "run" / "results.h5", "r") as f:
            trial_s = [float(t) for name in f["trials"] for t in f["trials"][name]["trial_time_s"][()]]
    wall = time.perf_counter() - t0
    print(f"{cfg.name}: {len(trial_s)} trials, median {statistics.median(trial_s):.1f} s; the run {wall:.0f} s",
          flush=True)
    rows = []
    groups = sorted({key[:2] for key in ledger.parts if key[0] in STAGES}, key=lambda g: (STAGES.index(g[0]), g))
    for stage, strategies in groups:
        total = sum(c["wall_s"] for key, c in ledger.parts.items() if key[0] == stage)
        for part in PARTS:
            c = ledger.parts.get((stage, strategies, part))
            if c is None or not c["calls"]:
                continue
            rows.append({"stage": stage, "strategies": strategies, "part": part, "calls": int(c["calls"]),
                         "wall_s": c["wall_s"],
                         "share": c["wall_s"] / total if total else 0.0,
                         "refactorisations": int(c["refactorisations"]), "refactorisation_s": c["refactorisations_s"],
                         "newton": int(c["newton"]), "newton_s": c["newton_s"]})
            print(f"  {stage:8s} {strategies:13s} {part:28s} {c['wall_s']:6.1f} s ({rows[-1]['share']:.0%}) in "
                  f"{c['calls']:.0f} calls; {c['refactorisations']:.0f} refactorisations "
                  f"{c['refactorisations_s']:.1f} s, {c['newton']:.0f} Newton {c['newton_s']:.1f} s", flush=True)
    moves = []
    for stage in ("nominal", "trials"):
        for low, high in zip((0.0,) + MOVE_BINS[:-1], MOVE_BINS):
            ms = [m for m in ledger.moves if m["stage"] == stage and low < m["size_mm"] <= high]
            moves.append({"stage": stage, "from_mm": low, "to_mm": float(high), "moves": len(ms),
                          "wall_s": sum(m["wall_s"] for m in ms),
                          "refactorisations": sum(m["refactorisations"] for m in ms),
                          "newton": sum(m["newton"] for m in ms)})
    res.table("parts", rows, {"wall_s": "s", "refactorisation_s": "s", "newton_s": "s"})
    res.table("moves", moves, {"from_mm": "mm", "to_mm": "mm", "wall_s": "s"})
    res.data("trial_s", trial_s)
    res.figure("trials", len(trial_s), "1")
    res.figure("trial_median_s", statistics.median(trial_s), "s")
    res.figure("run_s", wall, "s")
    print(f"wrote {res.write()}")


if __name__ == "__main__":
    main()
