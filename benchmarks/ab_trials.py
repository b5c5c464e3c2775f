"""A/B of solver settings on a run's own trials, alternately in one process; not a timed test.

A whole-command A/B (`farm-bench`) of a change that saves a few % of a
trial drowns in the machine's drift (about 10 % over a day on the 2-core
VM, docs/performance.md). This runs the config's pre-trial stages once
(`scissor simulate --jobs 1` into a temporary folder, its trials
recorded as they run), then replays those trials (same config text, same
tasks, same trial indices: the same draws) under each setting in turn,
round after round, each round on a context built anew (`fresh_context`:
the controller model's states are solved again, as a run's worker
solves them), and prints per setting the median CPU time
(process_time) of the round, the counts that do not depend on the load
(gradients, sparse-solve columns, factorisations) and the largest
difference of every insertion miss and every trial's final error from
the first setting's.

A setting is NAME=module.ATTR:value[,module.ATTR:value…], with a module
of `scissor_cli.insertion` by its name (`chord`, `needle`) or any other
by its path below `scissor_cli` (`solvers.newton`), and a Python
literal; the first setting is the reference, e.g.

    PYTHONPATH=. python benchmarks/ab_trials.py configs/example_3d.yaml --truth layer --count 4 \\
        a=chord.CONTRACTION:0.5 b=chord.CONTRACTION:0.85 --rounds 6
    PYTHONPATH=. python benchmarks/ab_trials.py configs/example_dome.yaml --count 2 \\
        on=solvers.newton.HESSIAN_FREE:True off=solvers.newton.HESSIAN_FREE:False

`--truth layer` runs a layer-truth trial as the error budget's rows do;
`--count` trials per target (the budget is off); `--needle` inserts the
needle in each trial with every strategy. Each round's CPU time and wall
time are both kept: a setting of the threads (`runtime._threads`) is
judged by its wall time. Settings touch module
constants only, so the replay is of this code; code changes are compared
across two checkouts, or by a setting that switches them.
"""

from __future__ import annotations

import argparse
import ast
import collections
import importlib
import importlib.util
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from scissor_cli import runtime

runtime.configure()  # before scissor's modules load cvxopt (runtime.match_blas_kernels)
import results_io  # noqa: E402

import scissor_cli.experiments.trials as trials_module  # noqa: E402
import scissor_cli.solvers.linear as linear  # noqa: E402
import scissor_cli.solvers.supernodal as supernodal  # noqa: E402
from scissor_cli.config import load_config, parse_config  # noqa: E402
from scissor_cli.experiments.simulate import Execution, run_simulation  # noqa: E402
from scissor_cli.mechanics.tissue import Tissue  # noqa: E402
from scissor_cli.output.results_sink import RunDirectory  # noqa: E402


def parse_setting(text: str) -> tuple[str, dict]:
    """'name=module.ATTR:value,…' → (name, {(module, ATTR): value})."""
    name, _, body = text.partition("=")
    if not name or not body:
        raise SystemExit(f"a setting is NAME=module.ATTR:value[,…], got {text!r}")
    out = {}
    for item in body.split(","):
        target, _, value = item.partition(":")
        module, _, attr = target.rpartition(".")
        top = "." in module or importlib.util.find_spec(f"scissor_cli.{module}") is not None
        path = f"scissor_cli.{module}" if top else f"scissor_cli.insertion.{module}"
        mod = importlib.import_module(path)
        if not hasattr(mod, attr):
            raise SystemExit(f"{path} has no {attr}")
        out[(mod, attr)] = ast.literal_eval(value)
    return name, out


def record_trials(config: Path, truth: str | None, count: int, needle: bool = False) -> list[tuple]:
    """Run the config's stages with its trials (budget off; with `needle`, every insertion strategy, as
    benchmarks/bench_body_insertion.py's trials) and return each trial's (config text, task, index)."""
    if needle:
        data = yaml.safe_load(config.read_text())
        data["insertion"] = {"strategies": ["none", "depth", "loop"]}
        cfg = parse_config(yaml.safe_dump(data, sort_keys=False), str(config), config.parent)
    else:
        cfg = load_config(config)
    update = {"count": count, "budget": False} | ({"truth": truth} if truth else {})
    cfg = cfg.model_copy(update={"trials": cfg.trials.model_copy(update=update)})
    recorded, run_trial = [], trials_module.run_trial

    def recording(config_yaml, task, k):
        recorded.append((config_yaml, task, k))
        return run_trial(config_yaml, task, k)

    trials_module.run_trial = recording
    try:
        with tempfile.TemporaryDirectory() as tmp:
            run_simulation(cfg, RunDirectory(tmp), execution=Execution(jobs=1))
    finally:
        trials_module.run_trial = run_trial
    return recorded


class Counts:
    """Gradients, sparse-solve columns (CHOLMOD's and the slab's float32 ones) and factorisations (CHOLMOD's, and
    float32's alone: `Factorization.deferred`), counted by wrapping the methods every caller uses."""

    def __init__(self):
        self.n = collections.Counter()
        solve, refactor, gradient = linear.Factorization.solve, linear.Factorization.refactor, Tissue.energy_gradient
        solve32 = supernodal.SupernodalFactor.solve
        counter = self.n

        def counted_solve(factor, b, solve=solve):
            counter["solve columns"] += 1 if np.ndim(b) == 1 else np.shape(b)[1]
            return solve(factor, b)

        def counted_solve32(factor, b):
            return counted_solve(factor, b, solve32)

        def counted_refactor(factor, A, single=False):
            try:
                refactor(factor, A, single)
            finally:  # (a failed one counts too)
                counter["float32 factorisations" if factor.deferred else "factorisations"] += 1
            return factor

        def counted_gradient(tissue, *args, **kwargs):
            counter["gradients"] += 1
            return gradient(tissue, *args, **kwargs)

        linear.Factorization.solve, linear.Factorization.refactor = counted_solve, counted_refactor
        supernodal.SupernodalFactor.solve = counted_solve32
        Tissue.energy_gradient = counted_gradient


def fresh_context(work: list[tuple]) -> None:
    """Build this process's trial context anew, each task's warm start solved (a body's `guess`), off the clock.

    A run's worker solves the controller model's states its trials command; only the commands its earlier trials
    of the target sent (the drives' top-speed approach) are taken over (`control.ModelPaths`). A context kept from
    the round before would take over every model state of the replay, so the rounds would time the true body alone.
    """
    trials_module._CONTEXTS.clear()
    for config_yaml, task, _ in work:
        guess = getattr(trials_module.trial_context(config_yaml), "guess", None)
        if guess is not None:
            guess(task)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("config", type=Path)
    ap.add_argument("settings", nargs="+", help="NAME=module.ATTR:value[,…]; the first is the reference")
    ap.add_argument("--truth", choices=("layer", "slab"), help="the trials' truth (default: the config's)")
    ap.add_argument("--count", type=int, default=2, help="trials per target")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--needle", action="store_true", help="every insertion strategy in each trial")
    args = ap.parse_args()
    settings = dict(parse_setting(s) for s in args.settings)
    stem = args.config.stem + (".needle" if args.needle else "")
    res = results_io.Results("ab_trials", ".".join([stem, *settings]))
    defaults = {key: getattr(*key) for s in settings.values() for key in s}
    t0 = time.perf_counter()
    work = record_trials(args.config, args.truth, args.count, args.needle)
    print(f"{args.config}: {len(work)} trials recorded in {time.perf_counter() - t0:.0f} s "
          f"(truth {args.truth or 'as configured'}); {args.rounds} rounds, settings in turn; load average "
          f"{os.getloadavg()[0]:.2f}")
    counts = Counts()
    cpu, wall = {name: [] for name in settings}, {name: [] for name in settings}
    seen, misses, finals = {}, {}, {}
    for _ in range(args.rounds):
        for name, setting in settings.items():
            for (mod, attr), value in (defaults | setting).items():
                setattr(mod, attr, value)
            fresh_context(work)
            counts.n.clear()
            t, t_wall = time.process_time(), time.perf_counter()
            outcomes = [trials_module.run_trial(*w) for w in work]
            cpu[name].append(time.process_time() - t)
            wall[name].append(time.perf_counter() - t_wall)
            seen[name] = dict(counts.n)
            misses[name] = np.concatenate([o.insertion_miss_mm for o in outcomes] + [np.zeros(0)])
            finals[name] = np.concatenate([np.ravel(o.final_error) for o in outcomes])
            failed = [o.message for o in outcomes if not o.ok]
            if failed:
                raise SystemExit(f"setting {name}: a trial failed: {failed[0]}")
    reference = next(iter(settings))
    rows = []
    for name in settings:
        c, w = np.array(cpu[name]), np.array(wall[name])
        apart = np.max(np.abs(misses[name] - misses[reference]), initial=0.0)
        final_apart = np.max(np.abs(finals[name] - finals[reference]), initial=0.0)
        print(f"{name}: CPU {np.median(c):.2f} s median of {c.size} ({c.min():.2f}–{c.max():.2f}), "
              f"{np.median(c) / np.median(cpu[reference]):.3f}× {reference}; wall {np.median(w):.2f} s "
              f"({w.min():.2f}–{w.max():.2f}), {np.median(w) / np.median(wall[reference]):.3f}×; "
              + ", ".join(f"{k} {v}" for k, v in sorted(seen[name].items()))
              + f"; insertion misses within {apart:.1e} mm, final errors within {final_apart:.1e} mm of {reference}'s")
        rows.append({"setting": name, "values": {f"{mod.__name__}.{attr}": repr(v) for (mod, attr), v in
                                                 settings[name].items()},
                     "cpu_median_s": np.median(c), "cpu_min_s": c.min(), "cpu_max_s": c.max(), "rounds": c.size,
                     "over_reference": np.median(c) / np.median(cpu[reference]), "wall_median_s": np.median(w),
                     "wall_min_s": w.min(), "wall_max_s": w.max(),
                     "wall_over_reference": np.median(w) / np.median(wall[reference]), **seen[name],
                     "misses_apart_mm": apart, "final_errors_apart_mm": final_apart})
    print(f"load average now {os.getloadavg()[0]:.2f}")
    res.table("settings", rows, {"cpu_median_s": "s (CPU)", "cpu_min_s": "s (CPU)", "cpu_max_s": "s (CPU)",
                                 "wall_median_s": "s", "wall_min_s": "s", "wall_max_s": "s",
                                 "misses_apart_mm": "mm",
                                 "final_errors_apart_mm": "mm"})
    res.figure("trials", len(work), "trials")
    res.write()


if __name__ == "__main__":
    main()
