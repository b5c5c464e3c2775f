"""Speed of the needle insertion in 3-D: the slab (docs/model.md §14; docs/performance.md, "Needle in the slab (§14)")
or a body (§20; docs/performance-elements.md, "Where an insertion step goes").

Not a timed test.

The scene's `layer_check` slab (default: configs/example_full.yaml's,
≈ 129k tetrahedra). For the first target with a plan, from the nominal
slab's equilibrium at the plan's strokes, along the plan's entry and
direction lifted to the layer's height (strategy `none`):

* the whole insertion (default 50 mm in 0.5 mm steps; the slab's goal ≤ 30 s), the
  median of the repeats, and one step's median;
* the factorisations, active-set passes and chord steps per step, the
  captured nodes at the end and the final miss (the evidence that holds
  when the machine is busy);
* a step against its floor (docs/model.md §18): one energy gradient plus
  one solve on the kept factor per chord step (each timed alone, median of
  20), plus each refactorisation; the rest is the step's own bookkeeping
  (capture, shares, the hold's Schur complement, the active-set rule);
* on a body (below), the same insertion once more on the float32 factor
  refactored at the start of every step (the exact tangent there): how
  many of the chord steps the kept factor's age costs, and what refreshing
  it would.

With --loop, the `loop` strategy instead (exact sensor, the scene's
controller gains, steering on the target's `NeedleModel` tabulated first
as the needle-model stage does; with --run DIR, the config, plan and needle
model that run used, read from DIR/results.h5: its nominal `loop`
replayed; CONFIG is then not read),
once as `scissor simulate` runs it and
once with each cup move starting from the cups' nodes placed alone (the
old start, the peer in the same run): each run's time, and its steps with
and without a cup move — their count, time and refactorisations
(docs/model.md §18, "Insertion control").

The slab is the one `scissor simulate` would use: with `layer_check.accuracy_mm`
(0.1 mm by default) the ladder's pick (cached beside runs/); --configured
benches the configured slab.

A body's config (e.g. configs/example_dome.yaml) benches its body instead,
at rest, the needle through its first lesion from the skin as
bench_body_insertion.py inserts it (`lesion_path`; §12's needle–tissue
defaults): the same measurements, the same step against its floor, on the
body's element; variant: the config's stem.

    PYTHONPATH=. python benchmarks/bench_insertion3d.py [CONFIG.yaml] [--depth MM] [--repeats K] [--configured]
        [--loop [--run DIR]]
    PYTHONPATH=. python benchmarks/bench_insertion3d.py configs/example_dome.yaml

The machine has 2 cores and other work may share them: the numbers are
wall-clock medians, printed with the load average and the CPU time.
"""

from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
from bench_body_insertion import lesion_path  # the body's needle path (this directory is on sys.path)
from bench_insertion import (  # the layer's benchmark's load line and plan
    _load,
    first_plan,
)

from scissor_cli import runtime

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli.config import load_config, parse_config  # noqa: E402
from scissor_cli.config.body_sections import BodyConfig  # noqa: E402
from scissor_cli.config.sections import InsertionConfig  # noqa: E402
from scissor_cli.experiments.build import body_model, build_model  # noqa: E402
from scissor_cli.experiments.layer_check_stage import slab_resolution_stage  # noqa: E402
from scissor_cli.experiments.run_cache import CACHE_DIR  # noqa: E402
from scissor_cli.insertion import InsertionOptions, NeedleParams, NeedlePath, miss_and_depth_error, run_insertion  # noqa: E402
from scissor_cli.insertion import run as insertion_run  # noqa: E402
from scissor_cli.insertion.capture import free_nodes  # noqa: E402
from scissor_cli.insertion.chord import ChordSolver  # noqa: E402
from scissor_cli.insertion.model_table import tabulate  # noqa: E402
from scissor_cli.insertion.needle import NeedleState, advance  # noqa: E402
from scissor_cli.insertion.steering import NeedleModel  # noqa: E402
from scissor_cli.layer3d.check import slab_spec  # noqa: E402
from scissor_cli.layer3d.slab import build_slab, slab_probe  # noqa: E402
from scissor_cli.layer3d.truth import SLAB_TRUTH_TOL  # noqa: E402
from scissor_cli.mechanics.tissue import Tissue  # noqa: E402
from scissor_cli.mesh.probe import target_positions  # noqa: E402
from scissor_cli.solvers.equilibrium import solve_equilibrium  # noqa: E402
from scissor_cli.solvers.linear import Factorization, factorize_free  # noqa: E402
from scissor_cli.solvers.newton import solve_newton  # noqa: E402
from scissor_cli.solvers.supernodal import SupernodalFactor  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


#: the kept factor's precisions compared (`ChordSolver.single_precision`)
PRECISIONS = {"float32": True, "float64": False}
#: the row of the float32 run whose kept factor is refactored at the start of every step (the exact tangent there)
FRESH = "float32, refactored at every step"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "example_full.yaml"))
    ap.add_argument("--depth", type=float, default=50.0, help="insertion depth (mm)")
    ap.add_argument("--step", type=float, default=0.5, help="step (mm)")
    ap.add_argument("--repeats", type=int, default=3, help="repeats of the insertion")
    ap.add_argument("--configured", action="store_true", help="the configured slab, not accuracy_mm's pick")
    ap.add_argument("--loop", action="store_true", help="the loop strategy, against the cup moves' old start")
    ap.add_argument("--run", type=Path, help="with --loop: the plan and needle model of this run directory")
    args = ap.parse_args()
    stem = Path(args.config).stem
    res = results_io.Results("bench_insertion3d", ".".join(p for p in (
        None if stem == "example_full" or args.run else stem, None if args.depth == 50.0 else f"depth{args.depth:g}",
        None if args.step == 0.5 else f"step{args.step:g}", None if args.repeats == 3 else f"repeats{args.repeats}",
        "configured" if args.configured else None, "loop" if args.loop else None,
        f"run-{args.run.name}" if args.run else None) if p) or None)
    cfg = load_config(args.config) if args.run is None else _run_config(args.run)
    if isinstance(cfg, BodyConfig):
        if args.loop or args.configured:
            raise SystemExit(f"{args.config}: --loop and --configured are the slab's")
        case = _body_case(cfg, args)
    else:
        case = _slab_case(cfg, args)
    slab, x0, entry, axis, probe, params = case.tissue, case.x0, case.entry, case.axis, case.probe, case.params
    print(f"load average {_load()}")
    res.data("scene", {**case.scene, "nodes": slab.mesh.n_nodes, "tetrahedra": slab.mesh.n_elements,
                       "free_dofs": int(slab.free_dofs.size), "depth_mm": args.depth, "step_mm": args.step,
                       "repeats": args.repeats})
    if args.loop:
        res.table("loop", _loop_runs(cfg, slab, x0, case.plan, case.target, params, entry, axis, case.table),
                  {"wall_s": "s", "miss_mm": "mm", "moved_s": "s", "unmoved_s": "s"})
        res.write()
        return
    runs = {precision: {"totals": [], "times": [], "cpu": [], "counts": []} for precision in PRECISIONS}
    for _ in range(args.repeats):
        for precision, single in PRECISIONS.items():  # alternately: peers under the same load
            _insert(runs[precision], precision, slab, case, params, args, single)
    # on a body, what the kept factor's age costs: the same insertion on the exact tangent at every step's start
    extra = {}
    if case.scene["kind"] == "body":
        extra[FRESH] = {"totals": [], "times": [], "cpu": [], "counts": []}
        _insert(extra[FRESH], FRESH, slab, case, params, args, True, refresh=True)
    kernels = _kernel_times(slab, x0)
    res.table("precisions", [_report(args, precision, r, probe, entry, axis, kernels) for precision, r in
                             [*runs.items(), *extra.items()]],
              {"step_median_ms": "ms", "step_mean_ms": "ms", "insertion_s": "s", "insertion_cpu_s": "s",
               "force_mN": "mN", "miss_mm": "mm", "depth_error_mm": "mm", "gradient_ms": "ms", "solve_ms": "ms",
               "refactorisation_ms": "ms", "floor_ms": "ms", "per_step": "factorisations, passes, chord steps"})
    a, b = (runs[p]["x"] for p in PRECISIONS)
    res.figure("float32_float64_nodes_apart_mm", np.abs(a - b).max(), "mm")
    res.figure("float32_over_float64", np.median(runs['float32']['totals']) / np.median(runs['float64']['totals']),
               "ratio of the whole insertion's time")
    print(f"float32 against float64 factor: the nodes' final positions differ by at most {np.abs(a - b).max():.2e} mm; "
          f"whole insertion "
          f"{np.median(runs['float32']['totals']) / np.median(runs['float64']['totals']):.2f}× the time")
    print(f"load average {_load()}")
    res.write()


def _insert(r: dict, label: str, tissue: Tissue, case, params, args, single: bool, refresh: bool = False) -> None:
    """One `none` insertion from case.x0 along case.entry, case.axis, appended to r (its steps' times and counts,
    the run's wall and CPU times, the in-situ timings, the final state). refresh: the chord solver refactors at the
    start of every step after the first (counted as that step's)."""
    state, x = NeedleState(case.entry, case.axis), case.x0.copy()
    state.solver = ChordSolver(tissue, single_precision=single)
    cand = free_nodes(tissue)
    step_times = []
    c0 = time.process_time()
    with _in_situ() as spent:
        while state.depth_mm < args.depth - 1e-9:
            t0 = time.perf_counter()
            fresh = refresh and state.solver.factored
            if fresh:
                state.solver.refactor(x)
            out = advance(tissue, state, x, case.strokes, min(args.step, args.depth - state.depth_mm), params, cand)
            step_times.append(time.perf_counter() - t0)
            r["counts"].append((out.factorizations + fresh, out.passes, out.iterations))
            x = out.x
    r.setdefault("in_situ", []).append(spent)
    r["cpu"].append(time.process_time() - c0)
    r["times"] += step_times
    r["totals"].append(sum(step_times))
    r["x"], r["state"], r["out"] = x, state, out
    r["factor"] = "float32" if single else "float64"  # (its kernel times: `_kernel_times`)
    print(f"  one run, {label}: {r['totals'][-1]:.1f} s, {len(step_times)} steps, load {_load()}", flush=True)


def _slab_case(cfg, args) -> SimpleNamespace:
    """The scene's `layer_check` slab (accuracy_mm's pick unless --configured) at the first plan's strokes, the
    needle along that plan lifted to the layer's height (with --run, the run's plan and needle model)."""
    if cfg.layer_check is not None and cfg.layer_check.accuracy_mm is not None and not args.configured:
        cfg = slab_resolution_stage(cfg, ROOT / "runs" / CACHE_DIR)[0]
    if cfg.insertion is None or cfg.layer_check is None:
        raise SystemExit(f"{args.config}: needs an insertion and a layer_check section")
    scene, mesh, tissue = build_model(cfg)
    t0 = time.perf_counter()
    slab = build_slab(scene, mesh, slab_spec(cfg.layer_check, cfg.tissue.mesh), model=tissue.params.model)
    build_s = time.perf_counter() - t0
    params = NeedleParams.from_config(cfg.insertion, cfg.needle, cfg.tissue.mesh)
    table = None
    if args.run is not None:
        plan, target, table = _from_run(args.run, scene)
    else:
        plan, target = first_plan(tissue, scene, cfg.needle)
    t0 = time.perf_counter()
    x0 = solve_newton(slab, plan.strokes, tol=SLAB_TRUTH_TOL).x
    settle_s = time.perf_counter() - t0
    z = slab.mesh.levels_mm[slab.mesh.layer_level]
    print(f"{cfg.name}: slab {slab.mesh.n_nodes} nodes, {slab.mesh.n_elements} tetrahedra, "
          f"{slab.free_dofs.size} free dofs (built in {build_s:.1f} s, nominal equilibrium {settle_s:.1f} s); "
          f"target {target.name}, {plan.side} entry; f_s {params.friction_static_mN_per_mm:g}, "
          f"f_k {params.friction_kinetic_mN_per_mm:g} mN/mm, F_tip {params.tip_force_mN:g} mN, "
          f"capture radius {params.capture_radius_mm:g} mm")
    return SimpleNamespace(
        tissue=slab, x0=x0, strokes=plan.strokes, entry=np.append(plan.entry, z), axis=np.append(plan.direction, 0.0),
        probe=slab_probe(slab, target.rest[None]), params=params, plan=plan, target=target, table=table,
        scene={"kind": "slab", "config": cfg.name, "build_s": build_s, "nominal_equilibrium_s": settle_s,
               "target": target.name, "entry": plan.side, "element": slab.element.name})


def _body_case(cfg, args) -> SimpleNamespace:
    """A 3-D body at rest (docs/model.md §19), the needle through its first lesion as bench_body_insertion.py
    inserts it (`lesion_path`), §12's needle–tissue defaults; the lesion is its region's mean."""
    scene, mesh, tissue = body_model(cfg)
    params = NeedleParams.from_config(InsertionConfig(step_mm=args.step), cfg.needle, cfg.tissue.mesh)
    lesion, strokes = scene.targets[0], np.zeros(len(scene.cups))
    t0 = time.perf_counter()
    x0 = solve_equilibrium(tissue, strokes).x
    settle_s = time.perf_counter() - t0
    path = lesion_path(mesh, lesion, args.depth)
    lesion_probe = tissue.probe(lesion.rest[None])
    print(f"{cfg.name}: body {mesh.n_nodes} nodes, {mesh.n_elements} tetrahedra (`{tissue.element.name}`), "
          f"{tissue.free_dofs.size} free dofs; lesion {lesion.name} along {path.direction.tolist()} from the skin")
    return SimpleNamespace(
        tissue=tissue, x0=x0, strokes=strokes, entry=path.entry, axis=path.direction,
        probe=SimpleNamespace(positions=lambda x: target_positions(lesion_probe, x)), params=params,
        scene={"kind": "body", "config": cfg.name, "nominal_equilibrium_s": settle_s, "target": lesion.name,
               "entry": "skin", "element": tissue.element.name})


def _report(args, precision, r, probe, entry, axis, kernels) -> dict:
    """One precision's insertion: a step's time, the whole, the counts, the miss, and the step against its floor."""
    t = np.array(r["times"]) * 1e3
    f, p, k = np.array(r["counts"]).T
    state, out, totals = r["state"], r["out"], r["totals"]
    miss, depth_error = miss_and_depth_error(probe.positions(r["x"])[0], entry, axis, state.depth_mm)
    print(f"{precision} — one step ({args.step:g} mm): median {np.median(t):.0f} ms (min {t.min():.0f}, "
          f"max {t.max():.0f})")
    print(f"  {args.depth:g} mm in {args.step:g} mm steps: {np.median(totals):.1f} s, median of {len(totals)} "
          f"(min {min(totals):.1f}; the slab's goal ≤ 30 s); CPU time {np.median(r['cpu']):.1f} s")
    print(f"  per step: {f.mean():.2f} factorisations ({f.sum() // len(totals)} per run), {p.mean():.1f} active-set "
          f"passes, {k.mean():.1f} chord steps; at the end {state.captured.size} captured "
          f"({int(state.stuck.sum())} stuck), needle force {out.force_mN:.1f} mN, miss {miss:.3f} mm, "
          f"depth error {depth_error:+.3f} mm; the solver in float32 at the end: {state.solver.single_precision}")
    grad_s, solves, factor_s = kernels
    kind = r["factor"]
    solve_s = solves[kind]
    floor = (k.mean() * (grad_s + solve_s) + f.mean() * factor_s[kind]) * 1e3
    print(f"  floor of a step: {k.mean():.1f} chord steps × (gradient {grad_s * 1e3:.1f} ms + kept-factor solve "
          f"{solve_s * 1e3:.1f} ms, each timed alone) + {f.mean():.2f} refactorisations × "
          f"{factor_s[kind] * 1e3:.0f} ms = {floor:.0f} ms; measured {np.mean(t):.0f} ms (mean)")
    spent = r["in_situ"][-1]  # the last run's
    steps = len(t) // len(totals)
    grad_calls, grad_time = spent["gradient"]
    solve_calls, solve_time = spent["solve"]
    rest = totals[-1] - grad_time - solve_time
    print(f"  in the last run, timed where they ran: {grad_calls} gradients {grad_time:.2f} s "
          f"({grad_time / max(grad_calls, 1) * 1e3:.1f} ms each), {solve_calls} kept-factor solve columns "
          f"{solve_time:.2f} s ({solve_time / max(solve_calls, 1) * 1e3:.1f} ms each, the captured nodes' "
          f"responses among them), the rest {rest:.2f} s ({rest / steps * 1e3:.0f} ms a step: capture, shares, the "
          f"hold's Schur complement, the active-set rule, refactorisations)")
    return {"precision": precision, "runs": len(totals), "step_median_ms": np.median(t), "step_mean_ms": np.mean(t),
            "insertion_s": np.median(totals), "insertion_cpu_s": np.median(r["cpu"]),
            "factorisations_per_step": f.mean(), "passes_per_step": p.mean(), "chord_steps_per_step": k.mean(),
            "captured": int(state.captured.size), "stuck": int(state.stuck.sum()), "force_mN": out.force_mN,
            "miss_mm": miss, "depth_error_mm": depth_error, "gradient_ms": grad_s * 1e3, "solve_ms": solve_s * 1e3,
            "refactorisation_ms": factor_s[kind] * 1e3, "floor_ms": floor}


@contextlib.contextmanager
def _in_situ():
    """Time every energy gradient and kept-factor solve (per column) while the block runs: {name: [calls, s]}."""
    spent = {"gradient": [0, 0.0], "solve": [0, 0.0]}
    timed = [(Tissue, "energy_gradient", "gradient"), (SupernodalFactor, "solve", "solve"),
             (Factorization, "solve", "solve")]
    originals = [(cls, name, getattr(cls, name)) for cls, name, _ in timed]

    def wrap(fn, key):
        def timed_call(self, b, *args, **kwargs):
            t0 = time.perf_counter()
            out = fn(self, b, *args, **kwargs)
            spent[key][1] += time.perf_counter() - t0
            spent[key][0] += 1 if key == "gradient" or np.ndim(b) == 1 else np.shape(b)[1]
            return out
        return timed_call

    for (cls, name, key), (_, _, fn) in zip(timed, originals):
        setattr(cls, name, wrap(fn, key))
    try:
        yield spent
    finally:
        for cls, name, fn in originals:
            setattr(cls, name, fn)


def _run_config(run: Path):
    """The config a run resolved (its chosen cups, its slab pinned), from DIR/results.h5."""
    with h5py.File(run / "results.h5", "r") as f:
        return parse_config(str(f.attrs["config_yaml"]), str(run / "results.h5"))


def _from_run(run: Path, scene):
    """The first feasible plan of a run (as a `SimpleNamespace` with strokes, entry, direction, depth_mm, side), its
    target and the NeedleModel the run steered with."""
    with h5py.File(run / "results.h5", "r") as f:
        for target in scene.targets:
            a = f[f"plan/{target.name}"].attrs
            if not a["feasible"]:
                continue
            g = f[f"controller_model/needle/{target.name}"]
            table = NeedleModel(g["depth_mm"][()], g["target"][()], g["jacobian"][()],
                                float(g.attrs["entry_height_mm"]), float(g.attrs["steered_height_mm"]))
            plan = SimpleNamespace(strokes=np.asarray(a["strokes"], float), entry=np.asarray(a["entry"], float),
                                   direction=np.asarray(a["direction"], float), depth_mm=float(a["depth_mm"]),
                                   side=str(a["side"]))
            return plan, target, table
    raise SystemExit(f"{run}: no feasible plan with a needle model")


def _loop_runs(cfg, slab, x0, plan, target, params, entry, axis, table=None) -> list[dict]:
    """`loop` on the target's NeedleModel, with the cup moves' start as shipped and with the cups' nodes placed
    alone."""
    if table is None:
        t0 = time.perf_counter()
        height = float(slab_probe(slab, target.rest[None]).positions(x0)[0, 2])  # aimed as the needle-model stage
        path = NeedlePath(np.append(entry[:2], height), axis, float(plan.depth_mm), target.rest, target.name)
        table = tabulate(slab, x0, plan.strokes, path, params, cfg.controller)
        print(f"needle model: {len(table.depth_mm)} steps in {time.perf_counter() - t0:.1f} s")
    aimed = NeedlePath(np.append(entry[:2], table.height_for("loop")), axis, float(plan.depth_mm), target.rest,
                       target.name)
    shipped = insertion_run.moved_start
    out = []
    for name, start in (("held response (shipped)", shipped),
                        ("cups' nodes placed alone",
                         lambda tissue, state, x, command: tissue.apply_strokes(x, command))):
        insertion_run.moved_start = start
        rows = []

        def record(state, x, s, rows=rows):
            rows.append((time.perf_counter(), s.copy(), state.solver.factorizations))

        try:
            t0 = time.perf_counter()
            rows.append((t0, np.asarray(plan.strokes, float), 0))
            r = run_insertion(slab, x0, plan.strokes, aimed, params,
                              InsertionOptions("loop", cfg.controller, needle_model=table, keep_displacement=False,
                                               record=record))
            wall = time.perf_counter() - t0
        finally:
            insertion_run.moved_start = shipped
        t = np.diff([row[0] for row in rows])
        moved = np.array([not np.array_equal(a[1], b[1]) for a, b in zip(rows, rows[1:])])
        factored = np.diff([row[2] for row in rows])
        print(f"loop, cup moves from the {name}: {wall:.1f} s, {r.steps} steps, miss {r.miss_mm:.3f} mm "
              f"({r.stop_reason}); load {_load()}")
        for label, m in (("with a cup move", moved), ("without", ~moved)):
            print(f"  steps {label}: {int(m.sum())}, {t[m].sum():.1f} s "
                  f"({1e3 * np.median(t[m]) if m.any() else 0:.0f} ms "
                  f"median), {int(factored[m].sum())} refactorisations of the kept factor")
        out.append({"start": name, "wall_s": wall, "steps": r.steps, "miss_mm": r.miss_mm, "stop": str(r.stop_reason),
                    "moved_steps": int(moved.sum()), "moved_s": t[moved].sum(),
                    "moved_refactorisations": int(factored[moved].sum()), "unmoved_steps": int((~moved).sum()),
                    "unmoved_s": t[~moved].sum(), "unmoved_refactorisations": int(factored[~moved].sum())})
    return out


def _kernel_times(slab, x) -> tuple[float, dict, dict]:
    """Medians (s) at x (N3, 3): one energy gradient; per precision one solve on the kept factor and one
    refactorisation (float32: CHOLMOD's factor copied out, `Factorization.single`)."""
    K = slab.stiffness_free(x, upper=True)
    slot: dict = {}
    factor = factorize_free(slab, K, slot)
    g = np.random.default_rng(0).standard_normal(slab.free_dofs.size)
    times = {"grad": [], "float64": [], "float32": [], "factor64": [], "factor32": []}
    for _ in range(20):
        t0 = time.perf_counter()
        slab.energy_gradient(x)
        times["grad"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        factor.solve(g)
        times["float64"].append(time.perf_counter() - t0)
    for _ in range(5):
        t0 = time.perf_counter()
        factorize_free(slab, K, slot)
        times["factor64"].append(time.perf_counter() - t0)
    for _ in range(5):
        t0 = time.perf_counter()
        single = factorize_free(slab, K, slot).single()
        times["factor32"].append(time.perf_counter() - t0)
    single.solve(g)  # compiled on the first call
    for _ in range(20):
        slab.energy_gradient(x)  # each solve after a gradient, as in a chord step (and as float64's above)
        t0 = time.perf_counter()
        single.solve(g)
        times["float32"].append(time.perf_counter() - t0)
    med = {k: float(np.median(v)) for k, v in times.items()}
    return (med["grad"], {"float64": med["float64"], "float32": med["float32"]},
            {"float64": med["factor64"], "float32": med["factor32"]})


if __name__ == "__main__":
    main()
