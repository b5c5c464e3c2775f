"""Regenerate docs/performance.md's tables and docs/img's images from the benchmarks' results (issue 54).

    python3 benchmarks/docs.py                 # every generated table, then every image
    python3 benchmarks/docs.py --tables-only   # the tables (reads benchmarks/results/*.json; seconds)
    python3 benchmarks/docs.py --images-only   # the images (runs scissor on shipped configs: minutes)
    python3 benchmarks/docs.py --result-images # only the images drawn from result files (seconds)
    python3 benchmarks/docs.py --check         # exit 1 when a committed table differs from what this would write,
                                               # or docs/img's file names differ from the images it writes
    python3 benchmarks/docs.py --list          # every file it writes

Tables. A doc (docs/*.md, README.md) holds

    <!-- generated: NAME -->
    ...
    <!-- end generated -->

and NAME is a renderer below (`@renderer("NAME", "result", ...)`), which reads the result files
benchmarks/results/<result>.json that the benchmarks write (benchmarks/results_io.py) and returns the Markdown
between the markers: the table and a line naming its source (file, command, date, machine, load). A result
file that is missing renders as a sentence naming the command that writes it, never as a number.

Images. Each file of docs/img comes from one source in IMAGES: either drawn by scissor's own figure function
from a result file's data (the benchmarks that take too long to run here: the controller models' target paths,
the slab-truth budget), or copied from a `scissor simulate` / `scissor report` run of a shipped config in a
temporary folder (`--images-only` runs them; their figures are also saved as benchmarks/results/docs_scenes.json,
which the tables of those scenes read). `--check` never runs a simulation: it compares the tables as text and the
images by name only (a PNG differs between machines).
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import results_io

from scissor_cli.config.body_sections import BodyMeshConfig

ROOT = results_io.ROOT
DOCS = ROOT / "docs"
IMG = DOCS / "img"
RESULTS = results_io.RESULTS_DIR
#: the docs scanned for generated blocks
DOC_FILES = [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]
BEGIN = re.compile(r"<!-- generated: ([a-z0-9_]+) -->\n")
END = "<!-- end generated -->"

# ---------------------------------------------------------------------------------------------------- helpers


def load(name: str) -> dict | None:
    """benchmarks/results/<name>.json; NAME may list alternatives, 'a|b': the first that exists."""
    for one in name.split("|"):
        path = RESULTS / f"{one}.json"
        if path.is_file():
            return json.loads(path.read_text())
    return None


class Missing(Exception):
    """A result file a renderer needs is not there (the benchmark has not been run)."""

    def __init__(self, name: str):
        super().__init__(name)
        self.name = name


def need(name: str) -> dict:
    r = load(name)
    if r is None:
        raise Missing(name.split("|")[0])
    return r


#: the command that writes each result file (what a missing one's sentence names)
COMMANDS = {
    "bench_forward": "python3 benchmarks/bench_forward.py",
    "bench_hard_cases": "python3 benchmarks/bench_hard_cases.py",
    "bench_elements": "python3 benchmarks/bench_elements.py",
    "bench_element_meshes": "python3 benchmarks/bench_element_meshes.py",
    "bench_insertion_elements": "python3 benchmarks/bench_insertion_elements.py",
    "bench_dome_study.p1.grading-0.3": "python3 benchmarks/bench_dome_study.py --element p1 --grading 0.3",
    "bench_dome_study.example.p1.grading-0.3":
        "python3 benchmarks/bench_dome_study.py --example --element p1 --grading 0.3",
    "bench_body_insertion.p1.grading-0.3":
        "python3 benchmarks/bench_body_insertion.py --element p1 --grading 0.3 --scale-30k 0.85",
    "bench_control": "python3 benchmarks/bench_control.py",
    "bench_control.table": "python3 benchmarks/bench_control.py --table",
    "bench_control.models": "python3 benchmarks/bench_control.py configs/example_full.yaml --models",
    "bench_workspace": "python3 benchmarks/bench_workspace.py",
    "bench_solvers": "python3 benchmarks/bench_solvers.py",
    "bench_trials": "python3 benchmarks/bench_trials.py",
    "bench_insertion": "python3 benchmarks/bench_insertion.py",
    "bench_insertion3d": "python3 benchmarks/bench_insertion3d.py",
    "bench_insertion3d.example_dome": "python3 benchmarks/bench_insertion3d.py configs/example_dome.yaml",
    "bench_needle_3d": "python3 benchmarks/bench_needle_3d.py",
    "bench_needle_3d.full": "python3 benchmarks/bench_needle_3d.py --full",
    "bench_slab": "python3 benchmarks/bench_slab.py",
    "bench_slab.quick": "python3 benchmarks/bench_slab.py --quick",
    "bench_slab.no-peer": "python3 benchmarks/bench_slab.py --no-peer",
    "bench_slab_ladder": "python3 benchmarks/bench_slab_ladder.py",
    "bench_slab_truth.trial": "python3 benchmarks/bench_slab_truth.py --trial",
    "bench_dask_slab": "python3 benchmarks/bench_dask_slab.py",
    "bench_ultrasound": "python3 benchmarks/bench_ultrasound.py",
    "bench_ultrasound_loop": "python3 benchmarks/bench_ultrasound_loop.py",
    "study_ultrasound": "python3 benchmarks/study_ultrasound.py",
    "compare_controller_models.accuracy0.1": "python3 benchmarks/compare_controller_models.py --accuracy-mm 0.1",
    "compare_controller_models.paper_trials_prosthesis_slab":
        "python3 benchmarks/compare_controller_models.py configs/paper_trials_prosthesis_slab.yaml",
    "docs_scenes": "python3 benchmarks/docs.py --images-only",
    "bench_dome_study.example": "python3 benchmarks/bench_dome_study.py --example --repeats 3",
    "bench_dome_study.nodal": "python3 benchmarks/bench_dome_study.py --element nodal",
    "bench_body_grips": "python3 benchmarks/bench_body_grips.py",
    "bench_dome_study.layer": "python3 benchmarks/bench_dome_study.py --model layer",
    "bench_dome_study.layer.bottom-left-right":
        "python3 benchmarks/bench_dome_study.py --model layer --section-fixed bottom,left,right",
    "bench_dome_study.layer.left-right":
        "python3 benchmarks/bench_dome_study.py --model layer --section-fixed left,right",
    "friction_law_before": "python3 benchmarks/bench_friction_law.py --label before (on the earlier law's checkout)",
    "friction_law_after": "python3 benchmarks/bench_friction_law.py --label after",
}


def command(name: str) -> str:
    return COMMANDS.get(name, f"python3 benchmarks/{name.split('.')[0]}.py")


def missing_text(name: str) -> str:
    return (f"*Not measured yet: `PYTHONPATH=. {command(name)}` writes `benchmarks/results/{name}.json`; "
            f"then `python3 benchmarks/docs.py --tables-only`.*")


def num(v, digits: int = 2) -> str:
    """A number with `digits` significant digits at most, plain notation where it reads well; '–' for None."""
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return f"{v:,}".replace(",", " ") if abs(v) >= 10_000 else str(v)
    v = float(v)
    if v == 0:
        return "0"
    if abs(v) < 1e-3 or abs(v) >= 1e6:
        return f"{v:.{max(digits - 1, 0)}e}"
    text = f"{v:.{digits}g}"
    if "e" in text:  # e.g. 1.2e+02 at 2 digits: write it out
        text = f"{v:.0f}"
    return text


def fixed(v, decimals: int = 2) -> str:
    return "–" if v is None else f"{float(v):.{decimals}f}"


def off_reference(x: dict) -> str:
    """A row's distance from its reference: `error_mm` and `error_pct`, as 'd mm (p %)'."""
    return f"{fixed(x['error_mm'], 3)} mm ({fixed(x['error_pct'], 1)} %)"


def wall_minutes(r: dict) -> str:
    """A result's `wall_s` figure in minutes (the median of its runs when it ran several)."""
    repeats = r["figures"]["wall_s"].get("repeats", 1)
    return f"{fixed(fig(r, 'wall_s') / 60, 1)} min" + (f" (median of {repeats} runs)" if repeats > 1 else "")


def slowest_trial_s(r: dict) -> float:
    """A dome study's slowest target's median trial (s)."""
    return max(x["trial_s_median"] for x in rows_of(r, "targets"))


def insertion_30k(r: dict, note: str = "") -> str:
    """bench_body_insertion's 50 mm insertion at about 30k tetrahedra: its time and size."""
    return f"{fixed(fig(r, 'none_30k_s'), 1)} s ({num(fig(r, 'tetrahedra_30k'))} tetrahedra{note})"


def as_accurate(r: dict, drag_pct: float | None = None, push_pct: float | None = None,
                besides: str | None = None) -> dict:
    """bench_insertion_elements' coarsest row (fewest tetrahedra) whose drag and push stay within drag_pct and
    push_pct of the reference (both the result's bound by default), of an element other than `besides`: where a
    goal set at 30k tetrahedra is fairly measured (model.md §21: a coarser mesh is fair where the element meets the
    accuracy on it). ValueError when no row does."""
    bound = r["data"]["bound_pct"]
    drag_pct, push_pct = bound if drag_pct is None else drag_pct, bound if push_pct is None else push_pct
    within = [x for x in rows_of(r, "insertions") if not x["reference"] and x["element"] != besides
              and x["error_pct"] <= drag_pct and x["push_error_pct"] <= push_pct]
    if not within:
        raise ValueError(f"no mesh within {drag_pct:g} % and {push_pct:g} %")
    return min(within, key=lambda x: x["tetrahedra"])


def as_accurate_mesh(r: dict, x: dict) -> str:
    """A bench_insertion_elements row's mesh and its errors, for a goal measured on it (`as_accurate`)."""
    scale = f" ×{x['scale']:g}" if x["scale"] != 1.0 else ""
    return (f"{num(x['tetrahedra'])} tetrahedra, `{x['element']}` graded {fixed(x['grading'], 1)}{scale}: the "
            f"needle's drag {fixed(x['error_pct'], 1)} % and {x['push_case']}'s lesions "
            f"{fixed(x['push_error_pct'], 1)} % off the refined reference, ≤ {r['data']['bound_pct']:g} %")


def table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def source(*results: dict) -> str:
    """The line under a table: which file, command, when, on what, under which load."""
    parts = []
    for r in results:
        name = r["benchmark"] + (f".{r['variant']}" if r.get("variant") else "")
        c = r["commit"]
        commit = (c.get("head") or "?")[:7] + (" + changes" if c.get("dirty") else "")
        m = r["machine"]
        speed = (f", speed index {num(r['speed_index_ms_before'], 3)} → {num(r['speed_index_ms_after'], 3)} ms"
                 if "speed_index_ms_after" in r else "")  # (results written before it was recorded have none)
        parts.append(f"`benchmarks/results/{name}.json`: `{r['command']}`, {r['date'][:16].replace('T', ' ')} UTC, "
                     f"{m['cpu']} ({m['cores']} cores), load {r['load1_before']:.2f} → {r['load1_after']:.2f}"
                     f"{speed}, {num(r.get('wall_s'), 3)} s, commit {commit}")
    return "Source: " + "; ".join(parts) + "."


def fig(r: dict, key: str):
    f = r["figures"].get(key)
    return None if f is None else f["value"]


def rows_of(r: dict, key: str) -> list[dict]:
    return r["tables"].get(key, {}).get("rows", [])


RENDERERS: dict[str, tuple] = {}
#: the ultrasound study: the whole one, else the paper scene's two pairs (`--only paper-layer paper-slab`)
STUDY = "study_ultrasound|study_ultrasound.only-paper-layer-paper-slab"


def renderer(name: str, *results: str):
    """Register fn(*result dicts) -> Markdown as the renderer NAME reading the named result files."""
    def wrap(fn):
        RENDERERS[name] = (fn, results)
        return fn
    return wrap


def render(name: str) -> str:
    fn, results = RENDERERS[name]
    try:
        return fn(*[need(r) for r in results]).strip("\n")
    except Missing as exc:
        return missing_text(exc.name)


# ---------------------------------------------------------------------------------------------------- renderers


@renderer("provenance")
def _provenance() -> str:
    """The machines the result files were measured on: one row per CPU, cores and versions, with the files' dates
    and loads; each table's own source line names its file's."""
    groups: dict[tuple, list[dict]] = {}
    other = []
    for path in sorted(RESULTS.glob("*.json")):
        r = json.loads(path.read_text())
        if not {"benchmark", "commit", "machine", "load1_before", "load1_after"} <= set(r):
            other.append(f"`{path.name}`")  # written by a script that does not use results_io
            continue
        key = (r["machine"]["cpu"], r["machine"]["cores"], r["machine"].get("system", ""),
               r["versions"].get("python"), r["versions"].get("numpy"))
        groups.setdefault(key, []).append(r)
    if not groups:
        return "*No result files yet: run the benchmarks (each script's docstring says how long it takes).*"
    rows = []
    for (cpu, cores, system, python, numpy_), rs in groups.items():
        dates = sorted(r["date"][:16].replace("T", " ") for r in rs)
        loads = [x for r in rs for x in (r["load1_before"], r["load1_after"])]
        dirty = sum(1 for r in rs if r["commit"].get("dirty"))
        speeds = [r[k] for r in rs for k in ("speed_index_ms_before", "speed_index_ms_after") if k in r]
        speed = f"{num(min(speeds), 3)}–{num(max(speeds), 3)} ({len(speeds) // 2} of {len(rs)})" if speeds else "–"
        rows.append([f"{cpu}, {cores} cores, {system}", f"{python} / {numpy_}", len(rs),
                     f"{dates[0]} – {dates[-1]}", f"{min(loads):.2f}–{max(loads):.2f}",
                     speed, f"{dirty} of {len(rs)}" if dirty else "none"])
    note = "" if not other else (f" Not written through `results_io` (no machine or load recorded): "
                                 f"{', '.join(other)}.")
    return table(["machine", "python / numpy", "result files", "dates (UTC)", "load (1 min) at start and end",
                  "speed index (ms, lower is faster; files with it)", "with uncommitted changes"], rows) + "\n\n" + (
        "Each table's source line gives its file's command, date, load and speed index before and after, wall time "
        "and commit."
        + note)


def _goal_rows() -> list[list]:
    """(goal, now, met, result file) for every speed goal whose benchmark has a result."""
    out = []

    def at_most(key: str, bound: float, digits: int, unit: str):
        """A goal on one figure of the result: (the figure with its unit, figure <= bound)."""
        return lambda r: (f"{fixed(fig(r, key), digits)}{unit}", fig(r, key) <= bound)

    def at_least(key: str, bound: float, digits: int, unit: str):
        return lambda r: (f"{fixed(fig(r, key), digits)}{unit}", fig(r, key) >= bound)

    def add(goal: str, name: str, fn):
        r = load(name)
        if r is None:
            out.append([goal, "not measured yet", "–", f"`{name.split('|')[0]}`"])
            return
        try:
            now, met = fn(r)
        except (KeyError, IndexError, TypeError, ValueError, StopIteration):
            now, met = "not in the result", None
        which = r["benchmark"] + (f".{r['variant']}" if r.get("variant") else "")
        out.append([goal, now, "–" if met is None else ("yes" if met else "**no**"), f"`{which}`"])

    def control(scene):
        def fn(r):
            row = next(x for x in rows_of(r, "corrective_iteration") if x["scene"] == scene)
            return f"{fixed(row['iteration_ms'], 1)} ms", row["iteration_ms"] <= 10
        return fn

    add("corrective control iteration, truth ≠ model, 1 cup ≤ 10 ms", "bench_control.table", control("example"))
    add("the same, 2 cups ≤ 10 ms", "bench_control.table", control("two_cups"))
    add("manipulation-point search ≤ 0.5 s", "bench_control.table",
        lambda r: (f"{num(fig(r, 'grip_search_ms'), 2)} ms ({fig(r, 'grip_candidates')} candidates)",
                   fig(r, "grip_search_ms") <= 500))

    def newton_push10(r):
        row = next(x for x in rows_of(r, "solves") if x["case"] == "push10" and x["solver"] == "newton")
        return f"{fixed(row['ms'], 0)} ms", row["ms"] <= 100

    def admm_per_element(r):
        v = max(x["us_per_element_iteration"] for x in rows_of(r, "solves") if x["mode"] == "settled")
        return f"≤ {fixed(v, 2)} µs", v <= 5

    add("Newton on `push10` ≤ 0.1 s", "bench_forward", newton_push10)
    add("an ADMM iteration ≤ 5 µs per element", "bench_forward", admm_per_element)
    add("one insertion step (0.5 mm) ≤ 10 ms", "bench_insertion",
        at_most("step_median_ms", 10, 1, " ms"))
    add("50 mm insertion in 0.5 mm steps ≤ 1 s", "bench_insertion",
        at_most("insertion_s", 1, 2, " s"))
    add("2-D Newton ≥ 10× scikit-fem at 16k elements", "bench_solvers",
        at_least("peer_over_best_16k", 10, 1, "×"))
    add("time ∝ elements^p, p ≤ 1.3 (Newton)", "bench_solvers",
        lambda r: (fixed(next(x["exponent"] for x in rows_of(r, "growth") if x["solver"] == "newton"), 2),
                   next(x["exponent"] for x in rows_of(r, "growth") if x["solver"] == "newton") <= 1.3))

    def slab_ratio(r):
        row = min(rows_of(r, "sizes"), key=lambda x: abs(x["tets"] - 50_000))
        return f"{fixed(row['peer_over_scissor'], 1)}× ({num(row['tets'])} tetrahedra)", row["peer_over_scissor"] >= 5

    def slab_100k(r):
        row = min(rows_of(r, "sizes"), key=lambda x: abs(x["tets"] - 100_000))
        return f"{fixed(row['scissor_s'], 1)} s ({num(row['tets'])} tetrahedra)", row["scissor_s"] <= 10

    add("3-D Newton ≥ 5× scikit-fem at ~50k tetrahedra", "bench_slab.quick", slab_ratio)
    add("3-D Newton ≤ 10 s at 100k tetrahedra", "bench_slab.no-peer", slab_100k)
    add("one slab-truth settle ≤ 0.3 s (median of a replayed loop)", "bench_slab_truth.trial",
        at_most("settle_median_s", 0.3, 2, " s"))
    add("one slab-truth trial ≤ 10 s", "bench_slab_truth.trial",
        at_most("trial_s", 10, 1, " s"))

    def dask(r):
        rows = rows_of(r, "executors")
        dask_rows = [x for x in rows if x["executor"].startswith("Dask")]
        falls = dask_rows[1]["trials_s"] < dask_rows[0]["trials_s"]
        same = all(x["identical"] for x in rows)
        return (" / ".join(fixed(x["trials_s"], 1) for x in dask_rows) + " s, " +
                ("bit-identical" if same else "NOT identical")), falls and same

    add("slab-truth trials on Dask (1 / 2 / 4 workers): time falls, results bit-identical", "bench_dask_slab", dask)

    def insertion3d(r):
        row = next(x for x in rows_of(r, "precisions") if x["precision"] == "float32")
        return f"{fixed(row['insertion_s'], 1)} s ({num(r['data']['scene']['tetrahedra'])} tetrahedra)", \
            row["insertion_s"] <= 30

    add("50 mm insertion in 0.5 mm steps in the slab ≤ 30 s", "bench_insertion3d", insertion3d)

    def surrogate(r):
        row = next(x for x in rows_of(r, "models") if x["model"] == "surrogate")
        return (f"{fixed(row['build_s'], 1)} s" + (" (cached)" if row["cached"] else "")
                + f" ({num(r['data']['scene']['tetrahedra'])} tetrahedra)", row["build_s"] <= 60)

    add("the surrogate trained ≤ 60 s, 2 cores", "bench_control.models", surrogate)
    add("the controller's side of an iteration ≤ 10 ms (layer, calibrated, surrogate)", "bench_control.models",
        lambda r: (" / ".join(f"{fixed(x['iteration_ms'], 2)}" for x in rows_of(r, "models") if x["model"] != "slab")
                   + " ms", all(x["iteration_ms"] <= 10 for x in rows_of(r, "models") if x["model"] != "slab")))
    add("the slab's ladder ≤ 60 s on the paper scenes, `--jobs 2`", "bench_slab_ladder",
        lambda r: (", ".join(f"{x['config'].removesuffix('.yaml')} {fixed(x['wall_s'], 1)} s"
                             for x in rows_of(r, "ladders")), all(x["wall_s"] <= 60 for x in rows_of(r, "ladders"))))
    add("a 4 × 30 layer study ≤ 60 s", "bench_trials",
        lambda r: (" / ".join(f"{x['profile']} {fixed(x['wall_s'], 1)} s" for x in rows_of(r, "studies")),
                   all(x["wall_s"] <= 60 for x in rows_of(r, "studies"))))
    add("the workspace, 10⁶ samples ≤ 5 s", "bench_workspace",
        at_most("median_s", 5, 2, " s"))

    def needle_run(run, goal_s):
        def fn(r):
            row = next(x for x in rows_of(r, "runs") if x["run"] == run)
            return f"{fixed(row['wall_s'] / 60, 1)} min", row["exit"] == 0 and row["wall_s"] <= goal_s
        return fn

    add("`layer_check: {}`, slab truth, the needle, 2 trials per target: `simulate --jobs 2` ≤ 10 min",
        "bench_needle_3d", needle_run("default-slab", 600))
    add("`configs/example_3d.yaml` end to end ≤ 10 min", "bench_needle_3d.full", needle_run("example_3d", 600))

    def us(measurement, goal_ms):
        def fn(r):
            row = next(x for x in rows_of(r, "timings") if x["measurement"].startswith(measurement))
            return f"{fixed(row['median_ms'], 2)} ms", row["median_ms"] <= goal_ms
        return fn

    add("one ultrasound frame (L11-5v, 70 mm, in the plane) ≤ 20 ms", "bench_ultrasound", us("fast frame, in-plane",
                                                                                             20))
    add("the same with a ±1 mm elevation band ≤ 20 ms", "bench_ultrasound", us("fast frame, elevation", 20))
    add("its tracking ≤ 5 ms", "bench_ultrasound", us("tracking one frame", 5))

    def study(r):
        runs = {(x["study"], x["sensor"]): x for x in rows_of(r, "runs")}
        ratio = runs[("paper-slab", "ultrasound")]["trials_s"] / runs[("paper-slab", "camera")]["trials_s"]
        return f"{fixed(ratio, 2)}× (trials)", ratio <= 2

    add("a 4 × 30 slab-truth study with ultrasound ≤ 2× the camera's", STUDY, study)

    def body_mesh(r):
        row = min(rows_of(r, "example"), key=lambda x: abs(x["tetrahedra"] - 30_000))
        return (f"{fixed(row['mesh_s_median'], 2)} s ({num(row['tetrahedra'])} tetrahedra)",
                row["mesh_s_median"] <= 5)

    add("the 3-D body's mesh ≤ 5 s at ~30k tetrahedra", "bench_body_mesh", body_mesh)
    add("one equilibrium of the 3-D body ≤ 1 s at ~30k tetrahedra (from rest)", "bench_body",
        lambda r: (f"{fixed(fig(r, 'from_rest_s'), 3)} s ({num(fig(r, 'tetrahedra'))} tetrahedra, "
                   f"`{r['data']['element']}`; a warm control move {fixed(fig(r, 'move_s'), 2)} s)",
                   fig(r, "from_rest_s") <= 1))
    add("`configs/example_dome.yaml`, `simulate --trials 0` from nothing ≤ 30 s", "bench_body",
        at_most("forward_run_s", 30, 1, " s"))
    def body_insertion(r):
        return insertion_30k(r, ", `none`"), fig(r, "none_30k_s") <= 5

    add("a 50 mm insertion in the body in 0.5 mm steps ≤ 5 s at 30k tetrahedra", "bench_body_insertion",
        body_insertion)
    def as_accurate_goals(r):  # the two goals set at 30k tetrahedra, on the coarsest mesh as accurate
        x = as_accurate(r)
        return (f"{fixed(x['push_s'], 2)} s / {fixed(x['wall_s'], 1)} s ({as_accurate_mesh(r, x)})",
                x["push_s"] <= 1 and x["wall_s"] <= 5)

    add("one equilibrium from rest ≤ 1 s / a 50 mm insertion ≤ 5 s, both on the coarsest mesh as accurate instead "
        "of at 30k tetrahedra (model.md §21)", "bench_insertion_elements", as_accurate_goals)
    add("a trial in the body with the needle, every strategy ≤ 15 s (median)", "bench_body_insertion",
        lambda r: (f"{fixed(fig(r, 'trial_median_s'), 1)} s (slowest {fixed(fig(r, 'trial_max_s'), 1)} s)",
                   fig(r, "trial_median_s") <= 15))
    add("the paper's dome study (4 × 30) from nothing ≤ 10 min, 2 cores", "bench_dome_study",
        lambda r: (wall_minutes(r), fig(r, "wall_s") <= 600))
    def slowest_trial(r) -> tuple[str, bool]:  # a dome study's slowest target's median trial, ≤ 10 s
        return f"{fixed(slowest_trial_s(r), 1)} s", slowest_trial_s(r) <= 10

    add("a dome trial ≤ 10 s (the slowest target's median)", "bench_dome_study", slowest_trial)
    add("`configs/example_dome.yaml` end to end ≤ 2 min", "bench_dome_study.example",
        lambda r: (wall_minutes(r), fig(r, "wall_s") <= 120))
    add("the grip search over the body's skin ≤ 2 s", "bench_body_grips",
        lambda r: (f"{fixed(max(x['search_s'] for x in rows_of(r, 'grips')), 2)} s (the slowest of 1, 2, 3 cups)",
                   max(x["search_s"] for x in rows_of(r, "grips")) <= 2))
    add("an environment step of the layer: ≥ 200 per second", "bench_gym", at_least("layer_steps_per_s", 200, 0, "/s"))
    add("an environment step of the body's surrogate: ≥ 1 000 per second", "bench_gym",
        at_least("surrogate_steps_per_s", 1000, 0, "/s"))
    add("an environment step of the body: ≥ 5 per second", "bench_gym", at_least("body_steps_per_s", 5, 1, "/s"))
    add("an environment's reset after the first ≤ 1 s (the slowest plant)", "bench_gym",
        lambda r: (f"{fixed(max(fig(r, k + '_reset_s') for k in ('layer', 'surrogate', 'body')), 2)} s",
                   max(fig(r, k + "_reset_s") for k in ("layer", "surrogate", "body")) <= 1))
    add("an MPC step with 3 cups and H = 10 ≤ 10 ms (median)", "bench_mpc", at_most("c3_median_ms", 10, 2, " ms"))
    return out


@renderer("outside_controllers", "bench_controllers", "bench_gym", "bench_mpc")
def _outside_controllers(laws, gym, mpc) -> str:
    rows = [[x["scene"], f"`{x['law']}`", num(x["trials"]), fixed(x["iterations_median"], 0),
             "–" if x["time_to_tolerance_s_median"] is None else fixed(x["time_to_tolerance_s_median"], 1),
             f"{fixed(x['miss_median_mm'], 3)} / {fixed(x['miss_p95_mm'], 3)} / {fixed(x['miss_max_mm'], 3)}",
             num(x["stroke_limit_stops"]), fixed(1000 * x["loop_wall_s_median"], 0)]
            for x in rows_of(laws, "laws")]
    envs = [[x["environment"], x["config"].replace("configs/", ""), fixed(x["steps_per_s"], 0),
             fixed(x["first_reset_s"], 2), fixed(x["reset_s"], 3)] for x in rows_of(gym, "environments")]
    steps = [[num(x["cups"]), fixed(x["first_ms"], 2), fixed(x["median_ms"], 2), fixed(x["p90_ms"], 2),
              fixed(x["stroke_step_median_ms"], 3)] for x in rows_of(mpc, "mpc_step")]
    return (table(["truth", "law", "trials", "iterations (median)", "robot time to tolerance (s, median)",
                   "true miss median / p95 / max (mm)", "stroke-limit stops", "loop wall (ms, median)"], rows)
            + "\n\nThe paper's prosthesis scene, 4 targets × 30 trials each way, the same seed and draws: `layer` "
              "is `configs/paper_trials_prosthesis.yaml`, `body` its study on the dome "
              "(`configs/paper_trials_prosthesis_dome.yaml`). " + source(laws)
            + "\n\n" + table(["environment", "scene", "steps per second", "first reset (s)",
                              "later reset (s, median)"], envs)
            + "\n\nRandom actions with the profile's draws; the first reset builds the model (the surrogate's "
              "includes its training). " + source(gym)
            + "\n\n" + table(["cups", "MPC step, first call (ms)", "median (ms)", "p90 (ms)",
                              "the PID's stroke step, median (ms)"], steps)
            + "\n\nH = 10 frames, different problems per call (OSQP set-up, solve and the exact active-set "
              "polish). " + source(mpc))


@renderer("goals")
def _goals() -> str:
    return table(["goal", "now", "met", "result file"], _goal_rows()) + "\n\n" + (
        "Each row's file in `benchmarks/results/` has the command, date, machine and load "
        "([How these were measured](#how-these-were-measured)).")


@renderer("forward", "bench_forward")
def _forward(r) -> str:
    rows = rows_of(r, "solves")
    out = []
    for case in dict.fromkeys(x["case"] for x in rows):
        def get(solver, mode, case=case):
            return next((x for x in rows if x["case"] == case and x["solver"] == solver and x["mode"] == mode), None)
        n = get("newton", "cold")
        a, aa = get("admm", "settled"), get("admm+AA(5)", "settled")
        ac = get("admm", "cold")
        w = get("admm", "warm+0.05")
        out.append([case, f"{n['iterations']} it, {fixed(n['ms'], 0)} ms",
                    f"{a['iterations']} it, {fixed(a['ms'], 0)} ms ({fixed(a['us_per_element_iteration'], 2)} "
                    "µs/element/it)",
                    f"{aa['iterations']} it, {fixed(aa['ms'], 0)} ms",
                    f"{ac['iterations']} it, {fixed(ac['ms'], 0)} ms",
                    f"{w['iterations']} it (from scratch {w['iterations_from_scratch']})", num(a["error_rel"], 2)])
    s = r["data"]["scene"]
    return (table(["case", "Newton (tol 1e-10)", f"ADMM settled (tol {num(s['admm_tol'])})", "ADMM + Anderson(5) "
                                                                                             "settled",
                   "ADMM cold (with its weight boosts)", "ADMM warm, 0.05 mm on", "ADMM vs Newton (rel. L2)"], out)
            + f"\n\nThe scene: {num(s['elements'])} triangles, {num(s['nodes'])} nodes, model `{s['model']}`; "
              f"median of {s['repeats']} repeats.\n\n" + source(r))


@renderer("hard_cases", "bench_hard_cases")
def _hard_cases(r) -> str:
    rows = rows_of(r, "solves")
    out = []
    for case in dict.fromkeys(x["case"] for x in rows):
        cells = [case.replace("_", " "), num(rows[[x["case"] for x in rows].index(case)]["elements"])]
        for solver in ("newton", "admm", "admm+anderson"):
            xs = [x for x in rows if x["case"] == case and x["solver"] == solver]
            its = " / ".join("–" if x["iterations"] is None else str(x["iterations"]) for x in xs)
            ts = " / ".join("–" if x["time_s"] is None else fixed(x["time_s"], 2) for x in xs)
            ok = "" if all(x["converged"] for x in xs) else " (not all converged)"
            cells.append(f"{its} it, {ts} s{ok}")
        out.append(cells)
    return (table(["case (configs/hard/)", "elements", "Newton", "ADMM", "ADMM + Anderson"], out)
            + "\n\nEach cell: the config's forward cases in its order, separated by /; iterations and wall time of "
              "one solve.\n\n" + source(r))


@renderer("elements", "bench_elements")
def _elements(r) -> str:
    acc = rows_of(r, "accuracy")
    keys = list(dict.fromkeys((x["scene"], x["nu"]) for x in acc))

    def cells(scene, nu, column):
        return " / ".join(fixed(x[column], 1) for x in acc if (x["scene"], x["nu"]) == (scene, nu))

    columns = ("p1_error_pct", "nodal_error_pct", "p2_off_th_pct", "p1_off_th_pct", "nodal_off_th_pct")
    accuracy = [[scene.replace(".yaml", ""), fixed(nu, 3)] + [cells(scene, nu, c) for c in columns]
                for scene, nu in keys]
    names = {"p2/p1": "`p2/p1` (Taylor–Hood)"}
    cost = [[x["scene"].replace(".yaml", ""), names.get(x["element"], f"`{x['element']}`"), num(x["unknowns"]),
             num(x["K_upper_nnz"]), fixed(x["assemble_ms"], 1), fixed(x["factor_ms"], 1),
             "—" if x["forward_s"] is None else f"{fixed(x['forward_s'], 2)} ({x['newton_iterations']} it)"]
            for x in rows_of(r, "cost")]
    pressure = "; ".join(f"{x['scene'].replace('.yaml', '')} {x['pressure_iterations']}"
                         for x in rows_of(r, "cost") if x["element"] == "p2/p1")
    shift = {x["element"]: x for x in rows_of(r, "refinement") if "lesion_shift_mm" in x}
    coarse = {x["element"]: x for x in rows_of(r, "refinement") if "lesion_shift_mm" not in x}
    refinement = "; ".join(f"`{e}` {fixed(x['lesion_shift_mm'], 3)} mm ({num(coarse[e]['tetrahedra'])} → "
                           f"{num(x['tetrahedra'])} tetrahedra, {fixed(x['forward_s'], 1)} s at the finer)"
                           for e, x in shift.items())
    share_table, built = _shares(r)
    return (table(["scene", "ν", "`p1` off P2 (%)", "`nodal` off P2 (%)", "P2 off Taylor–Hood (%)",
                   "`p1` off Taylor–Hood (%)", "`nodal` off Taylor–Hood (%)"], accuracy)
            + "\n\nLinear elasticity, every cup pushed 1 mm (`+cup2`: the dome with a second cup, both pushed), "
              "each scene's own mesh, per target; the references are scikit-fem's quadratic elements on the same "
              "mesh and nodes: P2 (displacements alone) and Taylor–Hood (P2 with a continuous P1 pressure, the "
              "mixed u–p form, which does not lock as ν → 1/2; `benchmarks/quadratic_reference.py`).\n\n"
            + table(["scene", "element", "unknowns", "K_ff nonzeros (upper)", "assembly (ms)", "factorisation (ms)",
                     "forward solve (s)"], cost)
            + "\n\nOne tangent at rest and one nonlinear forward solve (the scene's material at ν 0.45, Newton to "
              "1e-8: the layer's 10 mm push, the dome's 8 mm); medians of the repeats. `p2`, `p2/p1`: the "
              "quadratic elements of the references on the same mesh (6-node triangles, 10-node tetrahedra), "
              "linear elasticity: scikit-fem's assembly (a vectorised Python assembler, not comparable with the "
              "compiled kernels) and the same CHOLMOD factorisation of the displacement block; scissor has no "
              "nonlinear quadratic solve to time. Taylor–Hood's unknowns and nonzeros count its pressure too, and "
              f"its pressure takes conjugate-gradient iterations on the Schur complement, each a solve with that "
              f"factor ({pressure} under the 1 mm push). Under refinement, the dome "
              f"with its fibers at ν 0.49 pushed 8 mm: its lesions move from mesh scale 1 to 0.7 by {refinement}."
            + "\n\n" + share_table
            + "\n\nThe share α of the element's own deviatoric energy (`nodal.ELEMENT_SHARE`, built: "
              f"{built}; 1 is the averaged nodal volume alone), the dome with one cup and with two, linear "
              "elasticity, every cup pushed 1 mm: the worst target's error against each reference, and (in "
              "brackets) how much further than Taylor–Hood's that target moves. P2 locks at the larger ν, so it "
              "favours a stiffer share than the mixed reference does.\n\n" + source(r))


def _shares(r) -> tuple[str, str]:
    """The α sweep of bench_elements as a table (one row a share, the worst over its scenes at each ν) and the
    built share."""
    rows = rows_of(r, "share")
    nus = sorted({x["nu"] for x in rows})
    out = []
    for share in sorted({x["share"] for x in rows}):
        cells = [fixed(share, 2)]
        for column in ("max_off_th_pct", "max_error_pct"):
            for nu in nus:
                worst = max((x for x in rows if x["share"] == share and x["nu"] == nu), key=lambda x: x[column])
                extra = f" ({worst['further_than_th_pct']:+.1f})" if column == "max_off_th_pct" else ""
                cells.append(fixed(worst[column], 1) + extra)
        out.append(cells)
    built = r["data"].get("element_share")
    header = (["α"] + [f"off Taylor–Hood, ν {fixed(nu, 3)} (%)" for nu in nus]
              + [f"off P2, ν {fixed(nu, 3)} (%)" for nu in nus])
    return table(header, out), "–" if built is None else fixed(built, 2)


#: a body's default `tissue.mesh.grading` (the config's default, so the prose follows it)
BODY_GRADING = BodyMeshConfig().grading
#: the coarser gradings `bench_element_convergence.py --grading G` was run on (rows where their files exist)
CONVERGENCE_GRADINGS = (0.4, 0.5, 0.7)
#: (grading, α) of its `--grading G --share A` runs: `nodal` with a stiffer share than its default
CONVERGENCE_SHARES = ((0.5, 0.4),)


@renderer("element_convergence", "bench_element_convergence")
def _element_convergence(r) -> str:
    variants = [(f"grading-{g:g}", g, None) for g in CONVERGENCE_GRADINGS] + [
        (f"grading-{g:g}.share-{a:g}", g, a) for g, a in CONVERGENCE_SHARES]
    graded = [(r, "0.3", None)] + [(x, fixed(g, 1), a) for name, g, a in variants
                                   if (x := load(f"bench_element_convergence.{name}")) is not None]
    out = [[f"`{x['element']}`" + ("" if share is None else f", α {num(share)}"), grading,
            " → ".join(num(n) for n in x["tetrahedra"]),
            " / ".join(fixed(d, 3) for d in x["changes_mm"]), " / ".join(fixed(p, 2) for p in x["orders"]),
            fixed(x["finest_error_mm"], 3)] for result, grading, share in graded for x in rows_of(result, "orders")]
    scales = " → ".join(fixed(s, 1) for s in rows_of(r, "orders")[0]["scales"])
    return (table(["element", "grading", f"tetrahedra (scale {scales})", "lesions' change between levels (mm)",
                   "observed order", "finest level's error, Richardson (mm)"], out)
            + "\n\nThe dome with its fibers at ν 0.49, an 8 mm push, Newton to 1e-8; the change is the largest over "
              "the lesions, the order p = log(d_k/d_k+1)/log(h_k+1/h_k+2) with h the mesh scale (the finest three "
              "levels' is the asymptotic one: the coarse levels differ less than their scales, the graded mesh's "
              "largest edges being capped). The bound the elements are held to: scale 1 → 0.7 (the last change) "
              "moves the lesions ≤ 0.05 mm. Grading: `tissue.mesh.grading` (0.3 without `--grading G`: a layer's "
              f"default, and a body's before `nodal`; a body's default is {fixed(BODY_GRADING, 1)}); α: `nodal`'s "
              "share of the deviatoric energy kept per element (`nodal.ELEMENT_SHARE`) where a run set another. "
            + source(*[result for result, _, _ in graded]))


@renderer("element_meshes", "bench_element_meshes")
def _element_meshes(r) -> str:
    rows = rows_of(r, "meshes")
    peer = {x["nu"]: x for x in rows if x["element"] == "p1" and x["grading"] == 0.3 and x["scale"] == 1.0}
    out = []
    for x in rows:
        reference = x["scale"] != 1.0
        p = peer[x["nu"]]
        out.append([fixed(x["nu"], 2), f"`{x['element']}`", fixed(x["grading"], 1) + (f", ×{x['scale']:g} (the "
                    "reference)" if reference else ""), num(x["tetrahedra"]), num(x["unknowns"]),
                    num(x["factor_nnz"], 3), fixed(x["factor_s"], 2), fixed(x["forward_s"], 1),
                    f"{fixed(x['forward_s'] / p['forward_s'], 1)}×",
                    "–" if reference else off_reference(x)])
    strokes = " and ".join(f"{s:+g}" for s in r["data"]["strokes_mm"])
    return (table(["ν", "element", "grading", "tetrahedra", "unknowns", "factor nonzeros", "a factorisation (s)",
                   "the two solves (s)", "time against `p1`, grading 0.3",
                   "lesions off the reference (% of its move)"], out)
            + f"\n\nconfigs/paper_trials_prosthesis_dome.yaml (fibers) at each ν, its cup moved {strokes} mm, "
              "Newton to 1e-8; grading: `tissue.mesh.grading`, the edge's growth per mm from the lesions, vessels "
              f"and cup ({fixed(BODY_GRADING, 1)} a body's default, 0.3 a layer's and a body's before `nodal`); the "
              "reference: `nodal` "
              "graded 0.3 with every edge × "
              f"{r['data']['reference_scale']:g}. Off the reference: the largest over lesions and strokes, in mm "
              "and in % of the reference's move. A factorisation: the tangent at rest, numeric only (the pattern "
              "analysed), the median of the repeats. "
              + source(r))


@renderer("insertion_elements", "bench_insertion_elements")
def _insertion_elements(r) -> str:
    rows = rows_of(r, "insertions")

    def centre(x: dict) -> str:
        if "centre_error_mm" not in x:  # (a result recorded before the lesion became its region's mean)
            return "–"
        return "–" if x["reference"] else f"{fixed(x['centre_error_mm'], 3)} mm ({fixed(x['centre_error_pct'], 1)} %)"

    out = [[f"`{x['element']}`", fixed(x["grading"], 1) + (f", ×{x['scale']:g}" if x["scale"] != 1.0 else "")
            + (" (the reference)" if x["reference"] else ""), num(x["tetrahedra"]), fixed(x["wall_s"], 1),
            fixed(x["drag_mm"], 3), "–" if x["reference"] else off_reference(x), centre(x),
            fixed(x["force_mN"], 0), fixed(x["miss_mm"], 3), fixed(x["push_s"], 2),
            "–" if x["reference"] else f"{fixed(x['push_error_mm'], 3)} mm ({fixed(x['push_error_pct'], 1)} %)"]
           for x in rows]
    case, bound = rows[0]["push_case"], r["data"]["bound_pct"]
    try:
        fair = (f"The coarsest mesh within {bound:g} % on both, where the goals set at 30k tetrahedra are fairly "
                f"measured ([performance.md](performance.md#the-speed-goals)): {as_accurate_mesh(r, as_accurate(r))}. ")
    except ValueError:
        fair = f"No mesh here is within {bound:g} % on both. "
    p1 = [x for x in rows if x["element"] == "p1"]
    if p1:  # the accuracy the goals' 30k tetrahedra gave the element they were set for
        at_30k = min(p1, key=lambda x: abs(x["tetrahedra"] - 30_000))
        try:
            x = as_accurate(r, at_30k["error_pct"], at_30k["push_error_pct"], besides="p1")
            fair += (f"As accurate as `p1` at {num(at_30k['tetrahedra'])} tetrahedra (drag "
                     f"{fixed(at_30k['error_pct'], 1)} %, push {fixed(at_30k['push_error_pct'], 1)} % off) is "
                     f"`{x['element']}` on {num(x['tetrahedra'])}: {case} {fixed(x['push_s'], 2)} s, the insertion "
                     f"{fixed(x['wall_s'], 1)} s. ")
        except ValueError:
            pass
    return (table(["element", "grading", "tetrahedra", "the insertion (s)", "the lesion's drag (mm)",
                   "its end off the reference (% of the drag)", "its centre point's end off the reference's",
                   "last force (mN)", "miss (mm)", f"{case} from rest (s)",
                   "its lesions off the reference (% of the move)"], out)
            + f"\n\nconfigs/example_dome.yaml, T1 along −x from the skin, {num(r['data']['depth_mm'])} mm in "
              f"{num(r['data']['step_mm'])} mm steps, `none`, the default needle–tissue parameters; {case} from rest "
              "on the same tissue, Newton to 1e-8 (the largest error over the lesions); ×s: `tissue.mesh.scale`; "
              "the times are the medians of the repeats. The lesion is its region's mean (as scissor carries it, "
              "[model.md §21](model.md#the-lesion-is-its-regions-mean)); its centre point lies on the needle's line, "
              "where the displacement has no limit under refinement. " + fair + source(r))


@renderer("element_default", "bench_element_meshes", "bench_dome_study.p1.grading-0.3", "bench_dome_study",
          "bench_dome_study.example.p1.grading-0.3", "bench_dome_study.example", "bench_body_insertion.p1.grading-0.3",
          "bench_body_insertion", "bench_insertion_elements")
def _element_default(meshes, study_p, study, example_p, example, insertion_p, insertion, needle) -> str:
    """The body's speed goals and its accuracy on its default (nodal on its grading) and on the former one (p1, 0.3)."""
    grading = study["data"]["grading"]

    def off(element: str, g: float) -> tuple[str, float]:
        x = next(x for x in rows_of(meshes, "meshes")
                 if x["nu"] == 0.45 and x["element"] == element and x["grading"] == g and x["scale"] == 1.0)
        return off_reference(x), x["error_pct"]

    p1_off, nodal_off = off("p1", 0.3), off("nodal", grading)
    drag = {(x["element"], x["grading"]): x for x in rows_of(needle, "insertions") if x["scale"] == 1.0}

    rows = [["the lesions off the refined reference (the paper's dome, ±10 mm, ν 0.45) ≤ 8 %", p1_off[0],
             nodal_off[0], nodal_off[1] <= 8],
            ["the needle's drag on the lesion off the refined reference (example_dome, 50 mm) ≤ 8 %",
             off_reference(drag["p1", 0.3]), off_reference(drag["nodal", grading]),
             drag["nodal", grading]["error_pct"] <= 8],
            ["the paper's dome study (4 × 30) from nothing ≤ 10 min", wall_minutes(study_p), wall_minutes(study),
             fig(study, "wall_s") <= 600],
            ["a dome trial ≤ 10 s (the slowest target's median)", f"{fixed(slowest_trial_s(study_p), 1)} s",
             f"{fixed(slowest_trial_s(study), 1)} s", slowest_trial_s(study) <= 10],
            ["`configs/example_dome.yaml` end to end ≤ 2 min", wall_minutes(example_p), wall_minutes(example),
             fig(example, "wall_s") <= 120],
            ["a 50 mm insertion in the body in 0.5 mm steps ≤ 5 s at 30k tetrahedra", insertion_30k(insertion_p),
             insertion_30k(insertion), fig(insertion, "none_30k_s") <= 5],
            ["a trial in the body with the needle, every strategy ≤ 15 s (median)",
             f"{fixed(fig(insertion_p, 'trial_median_s'), 1)} s", f"{fixed(fig(insertion, 'trial_median_s'), 1)} s",
             fig(insertion, "trial_median_s") <= 15]]
    out = [row[:3] + ["yes" if row[3] else "**no**"] for row in rows]
    g = fixed(grading, 1)
    return (table(["", "`p1`, grading 0.3 (the default before `nodal`)", f"`nodal`, grading {g} (the default)",
                   "met on the default"], out)
            + f"\n\nGrading: `tissue.mesh.grading`, the edge's growth per mm from the lesions, vessels and cup ({g} a "
              "body's default, 0.3 a layer's). The 8 % is the bound set against quadratic elements on the same mesh, "
              "held here against the refined reference (its mesh error included). "
            + source(meshes, needle, study_p, study, example_p, example, insertion_p, insertion))


@renderer("cup_springs", "bench_cup_springs")
def _cup_springs(r) -> str:
    rows = rows_of(r, "holds")
    names = [k[len("move_"):-len("_mm")] for k in rows[0] if k.startswith("move_") and k.endswith("_mm")]
    out = [[x["hold"] if x["k_mN_per_mm3"] is None else f"{x['hold']} (k {num(x['k_mN_per_mm3'])} mN/mm³)",
            fixed(x["wall_s"], 2), str(x["iterations"]), str(x["factorizations"]), str(x["substeps"]),
            fixed(x["min_J"], 3), f"{fixed(x['patch_push_mm'], 2)} ({fixed(x['patch_push_min_mm'], 2)})",
            " / ".join(fixed(x[f"move_{n}_mm"], 3) for n in names),
            " / ".join(fixed(x[f"move_{n}_mm"] / rows[0][f"move_{n}_mm"], 2) for n in names)]
           for x in rows]
    e = r["data"]["element"]
    return (table(["the cup's hold", "push10 from rest (s)", "Newton iterations", "factorisations", "load substeps",
                   "smallest J", "the patch's push: mean (least) (mm)", f"lesions' move, {' / '.join(names)} (mm)",
                   "of the rigid cup's"], out)
            + f"\n\nconfigs/example_dome.yaml ({num(fig(r, 'tetrahedra'))} tetrahedra, `{e}`), its cup's patch of "
              f"{fig(r, 'patch_nodes')} skin nodes ({fixed(fig(r, 'patch_area_mm2'), 1)} mm²) pushed 10 mm from rest, "
              "Newton to 1e-8; the time is the median of the repeats. Springs: each patch node tied to where the rigid "
              "cup would put it, k = E / t per mm² of its share of the skin. " + source(r))


@renderer("continuation", "bench_continuation")
def _continuation(r) -> str:
    rows = rows_of(r, "settings")
    out = [[f"{x['step_fraction']:g}" + (" (default)" if x["default"] else ""), f"{x['substep_tol']:g}",
            fixed(x["wall_s"], 2), str(x["iterations"]), str(x["factorizations"]), str(x["substeps"]),
            num(x["off_reference_mm"])] for x in rows]
    return (table(["STEP_FRACTION", "SUBSTEP_TOL", "push10 from rest (s)", "Newton iterations", "factorisations",
                   "load substeps", "off the answer to 1e-10 (mm)"], out)
            + f"\n\nconfigs/example_dome.yaml ({num(fig(r, 'tetrahedra'))} tetrahedra, `{r['data']['element']}`), "
              "its cup pushed 10 mm from rest, Newton to 1e-8; the time is the median of the repeats, each "
              "starting with the factorisation the last one left (as `bench_body` times it). " + source(r))


@renderer("preconditioner", "bench_preconditioner")
def _preconditioner(r) -> str:
    """benchmarks/bench_preconditioner.py: the p1 factor against the nodal one as the nodal tangent's preconditioner."""
    rtols = r["data"]["rtols"]
    out = [[x["state"], x["preconditioner"], num(x["stored_entries"]), fixed(1e3 * x["factor_s"], 0),
            *[f"{x[f'iterations_{t:g}']} / {fixed(1e3 * x[f'solve_s_{t:g}'], 0)}" for t in rtols],
            *[f"{fixed(1e3 * x[f'solve_s_{t:g}'], 0)} (kept)" if x["kept"]
              else fixed(1e3 * (x["factor_s"] + x[f"solve_s_{t:g}"]), 0) for t in rtols]]
           for x in rows_of(r, "preconditioners")]
    return (table(["state", "preconditioner", "its K_ff's stored entries (upper)", "refactorisation (ms)",
                   *[f"CG to {t:g}: iterations / ms" for t in rtols],
                   *[f"factor and CG to {t:g} (ms)" for t in rtols]], out)
            + f"\n\nconfigs/example_dome.yaml ({num(fig(r, 'tetrahedra'))} tetrahedra), the `nodal` tangent K_ff "
              "solved for a fixed random right-hand side; times are medians of the repeats, the symbolic analysis "
              "done before; a kept factor costs its iterations only. A fresh `p1` factor with its iterations costs "
              "about what a fresh `nodal` one does to the settle's 1e-5 and less to a far step's 1e-2, but a kept "
              "nodal factor solves in a few iterations: "
              "a trial, which solves most columns on a kept factor, would spend more in iterations than it saved in "
              "factorisations. " + source(r))


@renderer("single_factorization", "ab_trials.example_dome.cholmod.single", "ab_trials.example_3d.cholmod.single")
def _single_factorization(*pairs) -> str:
    """benchmarks/ab_trials.py on a body's and a slab's trials: the factorisations that only precondition made by
    CHOLMOD in float64, against float32's own on its layout (`solvers.linear.SINGLE_FACTORIZATION`)."""
    rows = [[r["variant"].split(".")[0], f"`{x['setting']}`", fig(r, "trials"),
             f"{fixed(x['cpu_median_s'], 1)} s ({fixed(x['cpu_min_s'], 1)}–{fixed(x['cpu_max_s'], 1)}, "
             f"{x['rounds']})", f"{fixed(x['over_reference'], 3)}×", x["factorisations"],
             x.get("float32 factorisations", 0), x["solve columns"], x["gradients"],
             f"{num(x['misses_apart_mm'])} mm", f"{num(x['final_errors_apart_mm'])} mm"]
            for r in pairs for x in rows_of(r, "settings")]
    return (table(["config", "setting", "trials", "CPU, the trials (median, range, rounds)", "against `cholmod`",
                   "CHOLMOD factorisations", "float32 factorisations", "sparse-solve columns", "gradients",
                   "insertion misses apart", "final errors apart"], rows)
            + "\n\n`cholmod`: `SINGLE_FACTORIZATION = False`, every factorisation CHOLMOD's in float64 (its float32 "
              "copy then preconditions); `single`: `True`. Each pair replays the same trials in one process, the "
              "settings in turn, each round on a trial context built anew. " + source(*pairs))


@renderer("threads", "bench_threads", "ab_trials.example_dome.needle.one.two")
def _threads(r, ab) -> str:
    """benchmarks/bench_threads.py and ab_trials.py --needle: one compiled-loop thread against two in one process."""
    shares = r["data"]["factor_shares"]
    loops = [[x["what"], num(x["tetrahedra"]), f"{fixed(1e3 * x['one_s'], 1)} ms" if x["one_s"] < 1
              else f"{fixed(x['one_s'], 2)} s", f"{fixed(1e3 * x['two_s'], 1)} ms" if x["two_s"] < 1
              else f"{fixed(x['two_s'], 2)} s", f"{fixed(x['speedup'], 2)}×"] for x in rows_of(r, "loops")]
    trials = [[f"`{x['setting']}`", fig(ab, "trials"),
               f"{fixed(x['wall_median_s'], 1)} s ({fixed(x['wall_min_s'], 1)}–{fixed(x['wall_max_s'], 1)}, "
               f"{x['rounds']})", f"{fixed(x['wall_over_reference'], 3)}×", f"{fixed(x['cpu_median_s'], 1)} s",
               f"{num(x['misses_apart_mm'])} mm", f"{num(x['final_errors_apart_mm'])} mm"]
              for x in rows_of(ab, "settings")]
    return (table(["", "tetrahedra", "one thread", "two threads", "speed-up"], loops)
            + "\n\nconfigs/example_dome.yaml at push10's equilibrium (the loops: the time per call), push10 from "
              "rest, and T1's 50 mm `none` insertion at mesh scale 0.7; medians of the repeats, the two settings "
              "alternating in one process; every pair gave the same numbers to the bit. The float32 "
              f"factorisation's flops: the two parts {', '.join(f'{100 * p:.0f} %' for p in shares['parts'])}, "
              f"the top (one thread) {100 * shares['top']:.0f} %. " + source(r)
            + "\n\n" + table(["setting", "trials with the needle", "wall, the trials (median, range, rounds)",
                               "against `one`", "CPU (both threads)", "insertion misses apart",
                               "final errors apart"], trials)
            + "\n\nconfigs/example_dome.yaml with every insertion strategy, 2 trials per lesion, replayed in one "
              "process with `runtime._threads` at 1 (`one`) and 2 (`two`) in turn. " + source(ab))


@renderer("factor_patterns", "bench_factor_patterns")
def _factor_patterns(r) -> str:
    rows = rows_of(r, "forms")
    nodal = {x["scale"]: x for x in rows if x["form"] == "nodal"}
    out = [[f"{num(x['tetrahedra'])} (×{x['scale']:g})", f"`{x['form']}`" if x["form"] in ("p1", "nodal")
            else x["form"], x["matrix"], num(x["unknowns"]), num(x["nnz_factor"]), fixed(1e3 * x["factor_s"], 0),
            fixed(1e3 * x["solve_s"], 1), f"{fixed(x['factor_s'] / nodal[x['scale']]['factor_s'], 2)}× / "
            f"{fixed(x['solve_s'] / nodal[x['scale']]['solve_s'], 2)}×",
            "–" if x["qdldl_s"] is None else fixed(1e3 * x["qdldl_s"], 0)] for x in rows]
    return (table(["tetrahedra (mesh scale)", "form", "matrix", "unknowns", "factor nonzeros", "factorisation (ms)",
                   "a solve (ms)", "factorisation / solve against `nodal`", "qdldl's LDLᵀ (ms)"], out)
            + "\n\nconfigs/example_dome.yaml at rest. `p1`, `nodal`: the scene's K_ff. u–p (a pressure per node, "
              "the deviatoric energy per element: `nodal` at α = 1) and u–F̄ (the averaged deformation gradient "
              "per node: `nodal` at any α): the mixed systems whose elimination gives `nodal`'s, timed as "
              "CHOLMOD's supernodal LLᵀ on their pattern (what a supernodal LDLᵀ would cost at best), ordered as "
              "scissor orders a 3-D factor; qdldl: the indefinite LDLᵀ scissor has, on the quasi-definite u–p "
              "system. Numeric factorisations (the pattern analysed) and one float64 solve, medians of the "
              "repeats. " + source(r))


@renderer("needle_incompressible", "bench_needle_incompressible")
def _needle_incompressible(r) -> str:
    rows = rows_of(r, "runs")
    shipped = {x["nu"]: x["wall_s"] for x in rows if x["variant"] == "shipped"}
    out = [[fixed(x["nu"], 3), x["variant"], fixed(x["wall_s"], 1), fixed(x["wall_s"] / shipped[x["nu"]], 2) + "×",
            str(x["steps"]), str(x["factorisations"]), str(x["newton"]), num(x["float64"]),
            "–" if x["variant"] == "shipped" else num(x["lesion_off_mm"])] for x in rows]
    return (table(["ν", "solver", "50 mm (s)", "against shipped", "steps", "factorisations", "passes to Newton",
                   "float64 solves", "lesion off the shipped run's (mm)"], out)
            + f"\n\nconfigs/example_dome.yaml's body ({num(rows[0]['tetrahedra'])} tetrahedra, `nodal`) at each ν, T1 "
              "along −x from the skin, 50 mm in 0.5 mm steps, `none`; `no float64 copy`: the float64 solves through "
              "cvxopt's CHOLMOD; `neither`: besides, a fresh factorisation's step that does not contract goes to "
              "Newton, as before. Each ν's three in turn in one process, medians of the repeats. " + source(r))


@renderer("selection_elements", "bench_selection_elements")
def _selection_elements(r) -> str:
    picks = rows_of(r, "picks")

    def pick(x) -> list:
        what = f"`{x['element']}` {x['model']}, ×{x['level']:g} ({num(x['n_elements'])})"
        reference = x["element"] == "nodal" and x["level"] == 0.25 and x["model"] == "neo_hookean_fiber"
        real = "(the reference)" if reference else fixed(x["error_mm"], 3)
        predicted = fixed(x["predicted_error_mm"], 3) + ("" if x["meets_budget"] else " (over)")
        return [what, f"{predicted} / {real}", fixed(1e3 * x["solve_s"], 0)]

    rows = []
    for auto, p1 in zip(picks[0::2], picks[1::2]):
        rows.append([fixed(auto["nu"], 3), num(auto["budget_mm"])] + pick(auto) + pick(p1))
    calibration = {x["nu"]: x["calibration_s"] for x in picks}
    return (table(["ν", "budget (mm)", "`auto` picks", "predicted / real error (mm)", "solve (ms)",
                   "`p1` alone picks", "predicted / real error (mm)", "solve (ms)"], rows)
            + "\n\nconfigs/example.yaml, its hardest case (push10); one calibration per ν with `element: auto` ("
            + " / ".join(f"{fixed(t, 1)} s" for t in calibration.values()) + " at ν "
            + " / ".join(fixed(nu, 3) for nu in calibration)
            + "), the p1 column choosing among its p1 candidates only (what `element: p1` picks). Real error: the "
              "targets' largest distance from `nodal`, the richest model, Newton, on the size field × 0.25; "
              "\"(over)\": no candidate is predicted within 0.7 × the budget, the most accurate one runs. "
            + source(r))


@renderer("cook", "bench_cook")
def _cook(r) -> str:
    levels = rows_of(r, "levels")
    ns = list(dict.fromkeys(x["n"] for x in levels))
    tets = {x["n"]: x["tetrahedra"] for x in levels}
    out = [[f"`{x['element']}`", " / ".join(fixed(f, 3) for f in x["forces_mN"]),
            " / ".join(fixed(e, 1) for e in x["errors_pct"]), " / ".join(fixed(p, 2) for p in x["orders"])]
           for x in rows_of(r, "orders")]
    ref = rows_of(r, "orders")[0]["reference_mN"]
    return (table(["element", "reaction (mN), n = " + " / ".join(str(n) for n in ns), "off the reference (%)",
                   "observed order"], out)
            + f"\n\nn × n × n/4 hexahedra of six tetrahedra ({' / '.join(num(tets[n]) for n in ns)} tetrahedra); "
              f"the reference {fixed(ref, 3)} mN is the Richardson extrapolation of `nodal`'s three finest levels. "
              + source(r))


@renderer("element_downstream", "bench_element_downstream")
def _element_downstream(r) -> str:
    rows = rows_of(r, "downstream")
    value = {(x["scene"], x["what"], x["element"]): x for x in rows}

    def cell(x) -> str:
        return "–" if x is None else f"{fixed(x['value'], 1 if x['unit'] == '%' else 3)} {x['unit']}"

    out = [[scene, what, cell(value.get((scene, what, "p1"))), cell(value.get((scene, what, "nodal")))]
           for scene, what in dict.fromkeys((x["scene"], x["what"]) for x in rows)]
    run_s = {(x["scene"], x["element"]): x["run_s"] for x in rows}
    runs = ", ".join(f"{scene} {fixed(run_s.get((scene, 'p1')), 0)} / {fixed(run_s.get((scene, 'nodal')), 0)} s"
                     for scene in dict.fromkeys(x["scene"] for x in rows))
    return (table(["scene", "figure", "`p1`", "`nodal`"], out)
            + "\n\nThe layer check: how much the 2-D layer overstates the targets' in-plane motion against the "
              "slab; planned strokes: the largest cup's; drag: the target's largest move along the needle during "
              f"the nominal insertion. Newton, no trials; whole runs p1 / nodal: {runs}. " + source(r))


@renderer("element_dome_study", "bench_dome_study.p1.grading-0.3", "bench_dome_study.nodal", "bench_dome_study")
def _element_dome_study(p1, nodal, default) -> str:
    """benchmarks/bench_dome_study.py with --element p1 --grading 0.3, --element nodal (graded 0.3 when it ran) and
    the default: the paper's dome study on each element."""
    out = []
    def label(r: dict) -> str:  # (a file from before the grading was recorded ran on 0.3, the default then)
        return f"`{r['data']['element']}`, {fixed(r['data'].get('grading') or 0.3, 1)}"

    labels = ((label(p1), p1), (label(nodal), nodal), (label(default) + " (the default)", default))
    for label, r in labels:
        for x in rows_of(r, "targets"):
            if not x["trials"]:
                out.append([label, x["target"], 0, "no plan", "", "", "", "", ""])
                continue
            out.append([label, x["target"], x["trials"], fixed(x["max_x_mm"], 2), fixed(x["max_y_mm"], 2),
                        fixed(x["max_z_mm"], 2), f"{fixed(x['miss_median_mm'], 2)} / {fixed(x['miss_p95_mm'], 2)}",
                        x["at_stroke_limit"], f"{fixed(x['trial_s_median'], 1)} s"])
    paper = p1["data"]["paper_max_mm"]
    out.append(["the paper (Fig. 14)", "", 30, num(paper["x"]), num(paper["y"]), "not reported", "", "", ""])
    runs = ", ".join(f"{label} {wall_minutes(r)} wall, {num(fig(r, 'cpu_s'), 3)} CPU-s" for label, r in labels)
    return (table(["element, grading", "target", "trials", "max \\|x\\| (mm)", "max \\|y\\| (mm)", "max \\|z\\| (mm)",
                   "true miss median / p95 (mm)", "at the stroke limit", "a trial (median)"], out)
            + f"\n\nThe whole study with `--jobs 2`, from nothing: {runs} (the wall times and a trial's depend on "
              "the machine's load, in the source line; the CPU seconds less). " + source(p1, nodal, default))


@renderer("element_slab_study", "bench_element_slab_study")
def _element_slab_study(r) -> str:
    """benchmarks/bench_element_slab_study.py: the paper's prosthesis study with slab truth on each element."""
    out = []
    for x in rows_of(r, "targets"):
        if not x["trials"]:
            out.append([f"`{x['element']}`", x["target"], 0, "no plan", "", "", "", ""])
            continue
        out.append([f"`{x['element']}`", x["target"], x["trials"], fixed(x["max_x_mm"], 2), fixed(x["max_y_mm"], 2),
                    f"{fixed(x['miss_median_mm'], 2)} / {fixed(x['miss_p95_mm'], 2)}", x["at_stroke_limit"],
                    f"{fixed(x['trial_s_median'], 1)} s"])
    paper = r["data"]["paper_max_mm"]
    out.append(["the paper (Fig. 14)", "", 30, num(paper["x"]), num(paper["y"]), "", "", ""])
    runs = "; ".join(f"`{x['element']}`: the slab {num(x['slab_tetrahedra'])} tetrahedra (in-plane scale "
                     f"{num(x['slab_in_plane_scale'])}, {x['slab_levels']} levels, {fixed(x['slab_error_mm'], 3)} mm "
                     f"from the finest), {fixed(x['wall_s'] / 60, 1)} min wall, {num(x['cpu_s'], 3)} CPU-s"
                     for x in rows_of(r, "runs"))
    return (table(["element", "target", "trials", "max \\|x\\| (mm)", "max \\|y\\| (mm)",
                   "true miss median / p95 (mm)", "at the stroke limit", "a trial (median)"], out)
            + f"\n\n{r['data']['config']}, slab truth, {r['data']['trials_per_target']} trials per target, the "
              "controller steering by the layer; the layer and the slab on the element, Newton for both; `--jobs 2` "
              f"from nothing: {runs}. " + source(r))


@renderer("control", "bench_control.table")
def _control(r) -> str:
    out = [[x["scene"], x["cups"], f"{fixed(x['iteration_ms'], 1)} ms",
            f"{fixed(x['truth_steps'], 2)} + {fixed(x['model_steps'], 2)}",
            f"{fixed(x['truth_factorisations'], 2)} + {fixed(x['model_factorisations'], 2)}"]
           for x in rows_of(r, "corrective_iteration")]
    return (table(["scene", "cups", "corrective iteration (median)", "chord/Newton steps, truth + model",
                   "factorisations, truth + model"], out)
            + f"\n\nThe manipulation-point search: {fig(r, 'grip_candidates')} candidates in "
              f"{fixed(fig(r, 'grip_search_ms'), 0)} ms (adjoints and ranking); its verification "
              f"(3 re-meshed full solves) {fixed(fig(r, 'grip_verify_ms'), 0)} ms.\n\n" + source(r))


@renderer("control_loop", "bench_control")
def _control_loop(r) -> str:
    out = []
    for x in rows_of(r, "iterations"):
        its = x.get("iterations_per_run")
        out.append([x["measurement"], f"{fixed(x['median_ms'], 1)} ms",
                    f"{fixed(x['p10_ms'], 1)}–{fixed(x['p90_ms'], 1)}",
                    x["n"], "–" if not its else f"{its[0]}–{its[1]}"])
    s = r["data"]["scene"]
    return (table(["measurement", "median", "p10–p90 (ms)", "iterations timed", "iterations per run"], out)
            + f"\n\nThe scene: {s['config']}, {num(s['elements'])} triangles.\n\n" + source(r))


@renderer("one_vs_two", "docs_scenes")
def _one_vs_two(r) -> str:
    out = [[x["cups"], x["target"], x["trials"], fixed(x["miss_median"], 3), fixed(x["miss_p95"], 3),
            fixed(x["along_median_abs"], 3), fixed(x["iterations_mean"], 1)]
           for x in rows_of(r, "cups")]
    return (table(["cups", "target", "trials", "median miss (mm)", "p95 miss (mm)", "median \\|along\\| (mm)",
                   "mean iterations"], out) + "\n\n" + source(r))


@renderer("grip", "docs_scenes")
def _grip(r) -> str:
    g = r["data"]["manipulation_points"]
    chosen = "; ".join(f"({fixed(c[0] + 0.0, 0)}, {fixed(c[1] + 0.0, 0)}) mm" for c in g["chosen"])
    axes = "; ".join(f"({fixed(round(a[0]) + 0.0, 0)}, {fixed(round(a[1]) + 0.0, 0)})" for a in g["axes"])
    return (table(["scene", "candidates", "search (adjoints, ranking)", "verification", "chosen grip", "push axis"],
                  [[g["config"], g["candidates"], f"{fixed(g['search_s'] * 1e3, 0)} ms",
                    f"{fixed(g['verify_s'] * 1e3, 0)} ms", chosen, axes]]) + "\n\n" + source(r))


@renderer("trials", "bench_trials")
def _trials(r) -> str:
    out = [[x["profile"].replace("_", " "), x["trials"], f"{fixed(x['wall_s'], 1)} s",
            f"{fixed(x['max_x_mm'])} ({x['paper_max_x_mm']})", f"{fixed(x['max_y_mm'])} ({x['paper_max_y_mm']})",
            f"{fixed(x['median_x_mm'])} / {fixed(x['median_y_mm'])}",
            f"{fixed(x['p95_x_mm'])} / {fixed(x['p95_y_mm'])}",
            f"{fixed(x['iterations_mean'], 1)} / {x['iterations_max']}"] for x in rows_of(r, "studies")]
    return (table(["profile", "trials", "wall (`--jobs 2`)", "max \\|x\\| mm (paper)", "max \\|y\\| mm (paper)",
                   "median \\|x\\| / \\|y\\| mm", "p95 \\|x\\| / \\|y\\| mm", "iterations mean / max"], out)
            + "\n\n" + source(r))


def _budget_table(rows: list[dict]) -> str:
    rows = [x for x in rows if x.get("trials", 1)]  # a target refused up front has no trials in any row
    targets = list(dict.fromkeys(x["target"] for x in rows))
    out = []
    for src in dict.fromkeys(x["source"] for x in rows):
        xs = {x["target"]: x for x in rows if x["source"] == src}
        mx = max(x["x_max_mm"] for x in xs.values())
        my = max(x["y_max_mm"] for x in xs.values())
        p95 = " / ".join(fixed(xs[t]["miss_p95_mm"]) if t in xs else "–" for t in targets)
        ms = " / ".join(fixed(xs[t].get("mean_square_share"), 2) if t in xs else "–" for t in targets)
        out.append([src, f"{fixed(mx)} / {fixed(my)}", p95, ms])
    t = "–".join([targets[0], targets[-1]]) if len(targets) > 1 else targets[0]
    return table(["source", "max \\|x\\| / \\|y\\| (mm)", f"p95 miss, {t} (mm)", f"mean-square share, {t}"], out)


@renderer("budget_layer", STUDY)
def _budget_layer(r) -> str:
    rows = [x for x in rows_of(r, "budget") if x["run"] == "paper-layer-camera"]
    if not rows:
        return missing_text("study_ultrasound")
    return _budget_table(rows) + "\n\n" + source(r)


@renderer("budget_slab", "bench_needle_3d.full")
def _budget_slab(r) -> str:
    b = r["data"].get("budget_example_3d")
    if not b:
        return missing_text("bench_needle_3d.full")
    return _budget_table(b["rows"]) + f"\n\nThe scene: `{b['title']}` ({b['profile']} profile).\n\n" + source(r)


@renderer("insertion_scene", "docs_scenes")
def _insertion_scene(r) -> str:
    rows = rows_of(r, "insertion")
    order = ["none", "depth", "loop"]
    strategies = sorted(dict.fromkeys(x["strategy"] for x in rows), key=lambda k: (k not in order, order.index(k)
                                                                                    if k in order else 0, k))
    out = []
    for target in dict.fromkeys(x["target"] for x in rows):
        xs = {x["strategy"]: x for x in rows if x["target"] == target}
        out.append([target] + [f"{fixed(xs[s]['miss_mm'], 3)} ({xs[s]['depth_error_mm']:+.2f})" if s in xs else "–"
                               for s in strategies]
                   + [f"{fixed(max(x['peak_force_mN'] for x in xs.values()) / 1e3, 2)} N",
                      f"{fixed(max(x['drag_mm'] for x in xs.values()), 2)} mm"])
    return (table(["target"] + [f"`{s}`: miss (depth error), mm" for s in strategies]
                  + ["peak needle force", "largest drag along the needle"], out)
            + f"\n\nThe scene: {r['data']['insertion_config']}, its nominal insertion of each target.\n\n" + source(r))


@renderer("friction_law", "bench_friction_law.before", "bench_friction_law.after")
def _friction_law(before, after) -> str:
    """benchmarks/bench_friction_law.py's two results: the step refinement, before and after."""
    rows = []
    for a, b in zip(rows_of(before, "steps"), rows_of(after, "steps")):
        rows.append([num(a["step_mm"], 5)] + [
            f"{num(x.get('to_half_step_mm'), 2)} mm, {fixed(x['force_mN'], 1)} mN, {x['steps_with_stuck']}"
            if x.get("to_half_step_mm") is not None else f"–, {fixed(x['force_mN'], 1)} mN, {x['steps_with_stuck']}"
            for x in (a, b)])
    return (table(["step (mm)", "before: end's distance from the half step's, force at the end, steps with a stuck "
                   "node", "after (friction with state): the same"], rows) + "\n\n" + _law_source(before, after))


def _law_source(before, after) -> str:
    packages = ", ".join(f"{r['variant']}: the package at {r['data']['package']['commit'][:7]}"
                         for r in (before, after))
    return source(before, after) + f" ({packages})"


@renderer("friction_law_scenes", "bench_friction_law.before", "bench_friction_law.after")
def _friction_law_scenes(before, after) -> str:
    """The shipped insertion scenes' nominal insertions (`--trials 0`) under the law before and after."""
    rows = []
    for a, b in zip(rows_of(before, "scenes"), rows_of(after, "scenes")):
        rows.append([a["scene"], a["target"], a["strategy"],
                     f"{fixed(a['miss_mm'], 3)} → {fixed(b['miss_mm'], 3)}",
                     f"{fixed(a['depth_error_mm'], 3)} → {fixed(b['depth_error_mm'], 3)}",
                     f"{fixed(a['force_mN'], 0)} → {fixed(b['force_mN'], 0)}",
                     f"{a['stuck']}/{a['slipping']} → {b['stuck']}/{b['slipping']}"])
    return (table(["scene", "target", "strategy", "miss (mm)", "depth error (mm)", "force at the end (mN)",
                   "stuck/slipping at the end"], rows) + "\n\nSource: the same files as the table above.")


@renderer("body_mesh", "bench_body_mesh")
def _body_mesh(r) -> str:
    """benchmarks/bench_body_mesh.py: the example dome meshed at ~10k, 30k and 100k tetrahedra."""
    rows = [[num(x["target_tetrahedra"]), f"{fixed(x['min_edge_mm'], 2)} / {fixed(x['max_edge_mm'], 1)}",
             num(x["tetrahedra"]), num(x["nodes"]), f"{fixed(x['mesh_s_median'], 2)} s",
             f"{fixed(1e3 * x['cached_s_median'], 1)} ms", f"{fixed(x['min_dihedral_deg'], 1)}°",
             f"{fixed(x['worst_region_error_percent'], 1)} %", fixed(x["real_over_estimate"], 2)]
            for x in rows_of(r, "example")]
    return (table(["estimate", "min / max edge (mm)", "tetrahedra", "nodes", "mesh (median)", "from the cache",
                   "smallest dihedral", "worst region's volume error", "real / estimate"], rows)
            + "\n\n" + source(r))


@renderer("dome_study", "bench_dome_study", "bench_dome_study.example")
def _dome_study(study, example) -> str:
    """benchmarks/bench_dome_study.py: the paper's dome study (4 × 30) and the example dome, end to end."""
    paper = study["data"]["paper_max_mm"]
    rows = [[x["target"], x["trials"], fixed(x["max_x_mm"], 2), fixed(x["max_y_mm"], 2), fixed(x["max_z_mm"], 2),
             f"{fixed(x['miss_median_mm'], 2)} / {fixed(x['miss_p95_mm'], 2)}", x["at_stroke_limit"],
             f"{fixed(x['trial_s_median'], 1)} s"] for x in rows_of(study, "targets")]
    targets = rows_of(study, "targets")
    rows.append(["all", sum(x["trials"] for x in targets), fixed(max(x["max_x_mm"] for x in targets), 2),
                 fixed(max(x["max_y_mm"] for x in targets), 2), fixed(max(x["max_z_mm"] for x in targets), 2),
                 "", sum(x["at_stroke_limit"] for x in targets), ""])
    rows.append(["the paper (Fig. 14)", 30, num(paper["x"]), num(paper["y"]), "not reported", "", "", ""])
    runs = [["`configs/paper_trials_prosthesis_dome.yaml`, 4 × 30 trials (≤ 10 min)",
             wall_minutes(study), f"{num(fig(study, 'cpu_s'), 3)} CPU-s"],
            ["`configs/example_dome.yaml`, 2 × 30 trials (≤ 2 min)",
             wall_minutes(example), f"{num(fig(example, 'cpu_s'), 3)} CPU-s"]]
    return (table(["target", "trials", "max \\|x\\| (mm)", "max \\|y\\| (mm)", "max \\|z\\| (mm)",
                   "true miss median / p95 (mm)", "at the stroke limit", "a trial (median)"], rows)
            + "\n\n" + table(["run, `--jobs 2`, from nothing", "wall", "CPU"], runs) + "\n\n" + source(study, example))


def _study_model(r) -> tuple[str, str]:
    """A dome study's (controller's model, held) cells."""
    d = r["data"]
    if d.get("model") == "layer":
        return "the layer on the section", ", ".join(d["section_fixed"])
    scale = d.get("mesh_scale", 1.0)
    name = "the surrogate of the body" if d.get("model") == "surrogate" else "the body"
    return (name + (f", edges ×{num(scale)} the truth's" if scale != 1.0 else "")), "(the base)"


@renderer("dome_reduction", "bench_dome_study", "bench_dome_study.layer", "bench_dome_study.layer.bottom-left-right",
          "bench_dome_study.layer.left-right", "bench_dome_study.surrogate", "bench_dome_study.mesh-scale-2",
          "compare_controller_models.paper_trials_prosthesis_slab")
def _dome_reduction(body, *studies_and_slab) -> str:
    """benchmarks/bench_dome_study.py --model layer | surrogate, --mesh-scale: the controller's models driving the
    dome, the layer per held sides."""
    *studies, slab = studies_and_slab
    rows = []
    for r in (body, *studies):
        t = rows_of(r, "targets")
        model, held = _study_model(r)
        rows.append([model, held,
                     sum(x["trials"] for x in t), fixed(max(x["max_x_mm"] for x in t), 2),
                     fixed(max(x["max_y_mm"] for x in t), 2), fixed(max(x["max_z_mm"] for x in t), 2),
                     fixed(max(x["miss_p95_mm"] for x in t), 2), sum(x["at_stroke_limit"] for x in t),
                     num(max((x["iterations_median"] for x in t if "iterations_median" in x), default=None)),
                     f"{fixed(max(x['trial_s_median'] for x in t), 1)} s", wall_minutes(r)])
    st = [x for x in rows_of(slab, "summary") if x.get("controller") == "layer"]
    rows.append(["the layer (the slab as the truth)", "bottom", sum(x["trials"] for x in st),
                 fixed(max(x["max_x"] for x in st), 2), fixed(max(x["max_y"] for x in st), 2), "", "",
                 sum(x["stroke_limit_stops"] for x in st), "", "", ""])
    paper = body["data"]["paper_max_mm"]
    rows.append(["the paper (Fig. 14), its layer on the prosthesis", "the side opposite the cup", 30,
                 num(paper["x"]), num(paper["y"]), "not reported", "", "", "", "", ""])
    return (table(["the controller's model", "held", "trials", "max \\|x\\| (mm)", "max \\|y\\| (mm)",
                   "max \\|z\\| (mm)", "true miss p95, worst target (mm)", "at the stroke limit",
                   "iterations (slowest target's median)", "a trial (slowest target's median)",
                   "run (`--jobs 2`)"], rows) + "\n\n" + source(body, *studies, slab))


@renderer("dome_family", "bench_dome_family")
def _dome_family(r) -> str:
    """benchmarks/bench_dome_family.py: the dome study with one assumption the paper leaves open changed at a time;
    one row per set-up, each figure as the body's / the layer's (the controller's models)."""
    names = {"baseline": "the baseline: radius 60, height 35, targets and cup at 15, patch 5 mm",
             "radius_mm": "the dome's radius", "height_mm": "the dome's height", "target_height_mm":
             "the targets' (and the cup's) height", "cup_radius_mm": "the cup's patch radius"}
    setups: dict[tuple, dict] = {}
    for x in rows_of(r, "setups"):
        setups.setdefault((x["assumption"], x["value"]), {})[x["model"]] = x

    def pair(runs: dict, fmt) -> str:
        return " / ".join(fmt(runs[m]) for m in ("body", "layer") if m in runs)

    rows = [[names.get(a, a) + ("" if v is None else f": {num(v)} mm"),
             pair(runs, lambda x: f"{x['planned']} of {x['targets']}"),
             pair(runs, lambda x: fixed(x["max_x_mm"], 2)), pair(runs, lambda x: fixed(x["max_y_mm"], 2)),
             pair(runs, lambda x: fixed(x["max_z_mm"], 2)), pair(runs, lambda x: str(x["at_stroke_limit"])),
             pair(runs, lambda x: num(x.get("iterations_median"))), pair(runs, lambda x: f"{fixed(x['wall_s'], 0)} s")]
            for (a, v), runs in setups.items()]
    paper = r["data"]["paper_max_mm"]
    return (table(["set-up (one assumption changed)", "targets planned", "max \\|x\\| (mm)", "max \\|y\\| (mm)",
                   "max \\|z\\| (mm)", "at the stroke limit", "iterations (median)", "run"], rows)
            + f"\n\nEach cell: the controller's model the body / the paper's layer on the section; "
              f"{r['data']['trials_per_target']} trials per planned target. The paper (Fig. 14, prosthesis): max "
              f"\\|x\\| {num(paper['x'])}, \\|y\\| {num(paper['y'])} mm.\n\n" + source(r))


@renderer("body", "bench_body")
def _body(r) -> str:
    """benchmarks/bench_body.py: the example dome's mesh, one equilibrium, its forward run."""
    rows = [
        ["the mesh, from nothing", f"{fixed(fig(r, 'mesh_s'), 2)} s",
         f"{num(fig(r, 'tetrahedra'))} tetrahedra, {num(fig(r, 'nodes'))} nodes, smallest dihedral "
         f"{fixed(fig(r, 'min_dihedral_deg'), 1)}°; ≤ 5 s at ~30k"],
        ["the mesh, from the cache", f"{fixed(1e3 * fig(r, 'mesh_cached_s'), 1)} ms", ""],
        ["push10 from rest", f"{fixed(fig(r, 'from_rest_s'), 2)} s",
         f"`{r['data']['element']}`; {fig(r, 'from_rest_iterations')} Newton iterations (the tangent "
         "predictor, load steps)"],
        ["one control move, 10 → 11 mm warm", f"{fixed(fig(r, 'move_s'), 2)} s",
         f"{fig(r, 'move_iterations')} Newton iterations; one equilibrium ≤ 1 s at 30k"],
        ["the Jacobian at rest", f"{fixed(fig(r, 'jacobian_s'), 2)} s", ""],
        ["`simulate --trials 0` from nothing", f"{fixed(fig(r, 'forward_run_s'), 1)} s", "≤ 30 s"],
    ]
    return table(["measurement", "value", "note"], rows) + "\n\n" + source(r)


@renderer("body_truth_tol", "bench_body_truth_tol")
def _body_truth_tol(r) -> str:
    """benchmarks/bench_body_truth_tol.py: a trial's true dome settled at each relative residual along a travel."""
    d = r["data"]["replay"]
    rows = [[f"`{x['element']}`", f"{x['tol']:g}", f"{num(x['lesion_off_mm'])} mm",
             f"{fixed(x['settle_median_s'], 2)} s", f"{fixed(x['replay_s'], 1)} s", x["factorisations"],
             x["newton_iterations"]] for x in rows_of(r, "tolerances")]
    return (table(["element", "relative residual", "lesion from its 1e-10 settle (max)", "a settle (median)",
                   "the travel", "factorisations", "Newton iterations"], rows)
            + f"\n\n{d['config']}, {d['target']}'s first trial's truth, {d['moves']} moves of {d['step_mm']} mm from "
              f"rest.\n\n" + source(r))


@renderer("trial_steps", "ab_trials.example_dome.tight.loose", "ab_trials.example_dome.on.off",
          "ab_trials.example_dome.forward.central", "ab_trials.example_dome.float32.float64",
          "ab_trials.example_dome.reuse.new", "ab_trials.example_dome.base.both")
def _trial_steps(model_tol, hessian_free, difference, precision, reuse, refactor_later) -> str:
    """benchmarks/ab_trials.py on example_dome's trials: the controller's model settled to 1e-10 against
    `BODY_MODEL_TOL` (`experiments/body_trials.py`), Newton steps with and without the assembled Hessian, the
    forward against the central difference (`solvers/hessian_free.py`), the steps' solves on the factor's
    float32 copy against CHOLMOD's float64 (`solvers.linear.SINGLE_PRECISION_STEPS`), and new trackers on the
    last loop's released factorisations against new ones (`solvers.linear.REUSE_RELEASED`); and, tried without
    a gain, a factor kept for more CG iterations with chord steps accepted at a slower contraction."""
    rows = []
    for r in (model_tol, hessian_free, difference, precision, reuse):
        for x in rows_of(r, "settings"):
            setting = ", ".join(f"`{k.rsplit('.', 1)[1]} = {v}`" for k, v in x["values"].items())
            rows.append([setting, fig(r, "trials"), f"{fixed(x['cpu_median_s'], 1)} s ({fixed(x['cpu_min_s'], 1)}–"
                                  f"{fixed(x['cpu_max_s'], 1)}, {x['rounds']})",
                         f"{fixed(x['over_reference'], 2)}×", x["factorisations"], x["solve columns"],
                         x["gradients"], f"{num(x['final_errors_apart_mm'])} mm"])
    return (table(["setting", "trials", "CPU, the trials (median, range, rounds)", "against the first of its pair",
                   "factorisations", "sparse-solve columns", "gradients", "final errors apart from the first's"],
                  rows)
            + "\n\nEach pair replays the same trials of configs/example_dome.yaml (half per target) in one process, "
              "the settings in turn, each round on a trial context built anew (the controller model's states solved "
              "again, as a run's worker solves them). Tried and not kept: refactoring later, a factor kept until "
              "CG needs more than 9 iterations (`solvers.linear.KRYLOV_STALE_ITER`, 6) with chord steps kept "
              "down to a contraction of 0.6 (`solvers.newton.CHORD_CONTRACTION`, 0.3): " + _tried(refactor_later)
            + ".\n\n" + source(model_tol, hessian_free, difference, precision, reuse, refactor_later))


def _tried(r) -> str:
    """One A/B pair of `benchmarks/ab_trials.py` in a sentence: CPU ratio, whether the rounds overlap, and the
    load-free counts, first → second."""
    a, b = rows_of(r, "settings")[:2]
    overlap = b["cpu_min_s"] <= a["cpu_max_s"] and a["cpu_min_s"] <= b["cpu_max_s"]
    return (f"{fixed(b['over_reference'], 3)}× CPU ({fixed(a['cpu_median_s'], 1)} → {fixed(b['cpu_median_s'], 1)} s, "
            f"{b['rounds']} rounds{', the ranges overlapping' if overlap else ''}), factorisations "
            f"{a['factorisations']} → {b['factorisations']}, gradients {a['gradients']} → {b['gradients']}, "
            f"sparse-solve columns {a['solve columns']} → {b['solve columns']}")


@renderer("body_insertion", "bench_body_insertion")
def _body_insertion(r) -> str:
    """benchmarks/bench_body_insertion.py: one insertion per strategy in the example dome's body, the capture
    radius's two rules, the tolerance's speed against error, loop's J checked, a trial with the needle."""
    rows = [[x["strategy"], x["capture"], x["captured"], x["steps"], fixed(x["depth_mm"], 1),
             f"{fixed(x['wall_s'], 1)} ({x['repeats']})", fixed(1e3 * x["wall_s"] / max(x["steps"], 1), 0),
             fixed(x["miss_mm"], 3), fixed(x["force_mN"], 0), x["unsettled"], x["stop"]]
            for x in rows_of(r, "strategies")]
    sweep = "; ".join(f"{x['step_tol']:.0e}: {fixed(x['wall_s'], 1)} s, {x['target_off_mm']:.1e} mm"
                      for x in rows_of(r, "tolerances"))
    trials = rows_of(r, "trials")
    return (table(["strategy", "capture radius", "captured nodes", "steps", "depth (mm)", "wall (s) (runs, median)",
                   "ms a step", "miss (mm)", "force (mN)", "unsettled steps", "stop"], rows)
            + f"\n\n{num(fig(r, 'tetrahedra'))} tetrahedra; `none` on the dome meshed to "
              f"{num(fig(r, 'tetrahedra_30k'))}: {fixed(fig(r, 'none_30k_s'), 1)} s, miss "
              f"{fixed(fig(r, 'none_30k_miss_mm'), 3)} mm. `loop`'s J from the kept factor against PCG's converged "
              f"J at {len(rows_of(r, 'jacobian_checks'))} points along `none`'s insertion: at most "
              f"{fixed(100 * fig(r, 'jacobian_direct_difference'), 2)} % apart. Speed against error, `none` solved "
              f"to each step tolerance (a body's default {r['data']['default_step_tol']:.0e}; one run each), the "
              f"time and how far the lesion ends from the tightest's: {sweep}. A trial with the needle (example_dome, "
              f"every strategy, one process): median {fixed(fig(r, 'trial_median_s'), 1)} s, slowest "
              f"{fixed(fig(r, 'trial_max_s'), 1)} s over {len(trials)} trials (its loop and three insertions in the "
              f"drawn true body, seen by the scene's one camera); the needle's miss across its line, mean and largest "
              f"over them: " + "; ".join(
                  f"`{k}` {fixed(sum(x[f'miss_{k}_mm'] for x in trials) / len(trials), 3)} / "
                  f"{fixed(max(x[f'miss_{k}_mm'] for x in trials), 3)} mm" for k in ("none", "depth", "loop"))
            + ". " + source(r))


@renderer("body_grips", "bench_body_grips")
def _body_grips(r) -> str:
    """benchmarks/bench_body_grips.py: one, two and three cups chosen over the example dome's skin."""
    rows = [[x["cups"], x["target"], x["candidates"], fixed(x["search_s"], 2), fixed(x["verify_s"], 1),
             fixed(x["score"], 2), fixed(x["miss_mm"], 3), x["iterations"], x["stop"], fixed(x["max_stroke_mm"], 2)]
            for x in rows_of(r, "grips")]
    return (table(["cups", "lesion", "candidates", "search (s)", "verify (s)", "score",
                   "miss across the needle (mm)", "loop iterations", "stop", "largest stroke (mm)"], rows)
            + "\n\n" + source(r))


@renderer("insertion_speed", "bench_insertion")
def _insertion_speed(r) -> str:
    s = r["data"]["scene"]
    out = [["one step (0.5 mm), median", f"{fixed(fig(r, 'step_median_ms'), 1)} ms",
            f"CPU {fixed(fig(r, 'step_cpu_median_ms'), 1)} ms"],
           [f"{num(s['depth_mm'])} mm in 0.5 mm steps, median of {s['repeats']}",
            f"{fixed(fig(r, 'insertion_s'), 2)} s",
            f"CPU {fixed(fig(r, 'insertion_cpu_s'), 2)} s"],
           ["per step: factorisations, active-set passes, chord steps",
            f"{fixed(fig(r, 'factorisations_per_step'), 2)}, {fixed(fig(r, 'passes_per_step'), 1)}, "
            f"{fixed(fig(r, 'chord_steps_per_step'), 1)}", "the counts a busy machine does not change"]]
    steps = [[num(x["step_mm"]), x["steps"], fixed(x["ms_per_step"], 1), x["final_stuck"], fixed(x["force_mN"], 1),
              fixed(x["final_diff_mm"], 3), fixed(x["median_diff_mm"], 3), fixed(x["max_diff_mm"], 3)]
             for x in rows_of(r, "step_size")]
    return (table(["measurement", "value", "note"], out)
            + f"\n\nThe scene: {s['config']}, {num(s['nodes'])} nodes, target {s['target']} from the plan's state, "
              "strategy `none`. Step size against the 0.25 mm run (\\|Δ\\|: the target's distance from it at the "
              "end, and the median and largest over every depth all four reach):\n\n"
            + table(["step (mm)", "steps", "ms a step", "final stuck", "force at the end (mN)", "\\|Δ\\| final (mm)",
                     "median \\|Δ\\| (mm)", "largest (mm)"], steps) + "\n\n" + source(r))


@renderer("layer_check", "docs_scenes")
def _layer_check(r) -> str:
    out = [[x["case"], num(x["slab_tetrahedra"]), f"{fixed(x['layer_check_in_plane_diff_mm'])} mm "
            f"({fixed(x['layer_check_in_plane_diff_pct'], 0)} %)", f"{fixed(x['out_of_plane_mm'])} mm",
            x["closer_to"].replace("_", " "), f"{fixed(x['time_s'], 1)} s ({x['iterations']} it)"]
           for x in rows_of(r, "layer_check")]
    return (table(["case", "slab tetrahedra", "layer overstates the in-plane motion by", "out of the plane",
                   "closer to", "slab solve"], out)
            + f"\n\nThe scene: {r['data']['layer_check_config']}.\n\n" + source(r))


@renderer("workspace", "bench_workspace")
def _workspace(r) -> str:
    out = [["10⁶ samples: kinematics and coverage (median)", f"{fixed(fig(r, 'median_s'), 2)} s"],
           ["coverage of the box reached by IK", f"{fixed(fig(r, 'coverage_reachable'), 1)} %"],
           ["… from ≥ 3 insertion directions", f"{fixed(fig(r, 'coverage_reachable_3dirs'), 1)} %"],
           ["coverage of the samples alone", f"{fixed(fig(r, 'coverage_sampled'), 1)} %"]]
    return table(["measurement", "value"], out) + f"\n\nWhat is missed: {r['data']['summary']}.\n\n" + source(r)


@renderer("peer", "bench_solvers")
def _peer(r) -> str:
    out = []
    for x in rows_of(r, "sizes"):
        cells = [num(x["elements"])]
        for s in ("newton", "admm", "admm+AA5", "peer"):
            cells.append(f"{num(x[f'{s}_s'], 2)} s ({x[f'{s}_iterations']})")
        cells += [f"{fixed(x['peer_over_best'], 1)}×", f"{num(x['peer_1e10_s'], 2)} s / {num(x['newton_1e10_s'], 2)} s",
                  fixed(x["load1"], 2)]
        out.append(cells)
    growth = ", ".join(f"{g['solver']} {fixed(g['exponent'], 2)}" for g in rows_of(r, "growth"))
    return (table(["elements", "scissor Newton (it)", "ADMM", "ADMM + Anderson", "scikit-fem", "peer / best scissor",
                   "to 1e-10: peer / Newton", "load"], out)
            + f"\n\nTimes to a relative target error of 1e-3, medians. Growth exponents (time ∝ elements^p): "
              f"{growth}.\n\n" + source(r))


@renderer("slab", "bench_slab.quick", "bench_slab.no-peer")
def _slab(quick, nopeer) -> str:
    full = load("bench_slab")
    tables_ = [full] if full else [quick, nopeer]
    by_tets: dict[int, dict] = {}
    for t in tables_:
        for x in rows_of(t, "sizes"):
            row = by_tets.setdefault(x["tets"], {})  # a size both runs have: the first run's (its peer's) row
            row.update({k: v for k, v in x.items() if v is not None and not row})
    out = []
    for tets, x in sorted(by_tets.items()):
        peer = f"{fixed(x['peer_s'], 1)} s ({x['peer_it']})" if "peer_s" in x else "–"
        ratio = f"{fixed(x['peer_s'] / x['scissor_s'], 1)}×" if "peer_s" in x else "–"
        out.append([num(tets), num(x["dofs"]), f"{fixed(x['scissor_s'], 1)} s ({x['scissor_it']}, {x['factor']}, "
                                               f"{x['cg']})",
                    f"{fixed(x['nnz_L_M'], 1)}M", peer, ratio, "–" if "diff_mm" not in x else num(x["diff_mm"], 1),
                    fixed(x["load"], 1)])
    return (table(["tetrahedra", "free dofs", "scissor (it, factorisations, CG it)", "nnz(L)", "scikit-fem (it)",
                   "peer / scissor", "target diff (mm)", "load"], out) + "\n\n" + source(*tables_))


@renderer("slab_truth", "bench_slab_truth.trial")
def _slab_truth(r) -> str:
    out = [["the slab", f"{num(fig(r, 'tetrahedra'))} tetrahedra, {num(fig(r, 'free_dofs'))} unknowns"],
           ["worker context (layer model + slab)", f"{fixed(fig(r, 'worker_context_s'), 1)} s"],
           ["gradient: numpy → compiled", f"{num(fig(r, 'gradient_numpy_s') * 1e3, 2)} → "
                                          f"{num(fig(r, 'gradient_compiled_s') * 1e3, 2)} ms"],
           ["element stiffness: numpy → compiled", f"{num(fig(r, 'stiffness_numpy_s') * 1e3, 2)} → "
                                                   f"{num(fig(r, 'stiffness_compiled_s') * 1e3, 2)} ms"],
           ["K_ff assembled", f"{num(fig(r, 'kff_assembled_s') * 1e3, 2)} ms"],
           ["CHOLMOD refactorisation; one solve", f"{num(fig(r, 'refactorisation_s') * 1e3, 2)} ms; "
                                                  f"{num(fig(r, 'solve_s') * 1e3, 2)} ms"],
           ["the nominal slab at the first target's plan", f"{fixed(fig(r, 'nominal_start_s'), 1)} s"],
           [f"replay of {fig(r, 'replay_settles')} settles: median (max)",
            f"{fixed(fig(r, 'settle_median_s'), 2)} s ({fixed(fig(r, 'settle_max_s'), 2)} s); "
            f"{fig(r, 'replay_factorisations')} factorisations, "
            f"{fig(r, 'replay_newton_iterations')} Newton iterations"],
           ["one slab-truth trial (first target, trial 0)",
            f"{fixed(fig(r, 'trial_s'), 1)} s, {fig(r, 'trial_iterations')} iterations, stop "
            f"`{r['data']['trial_stop']}`"]]
    return table(["measurement", "value"], out) + "\n\n" + source(r)


@renderer("dask", "bench_dask_slab")
def _dask(r) -> str:
    out = [[x["executor"], f"{fixed(x['trials_s'], 1)} s", f"{fixed(x['speedup'], 2)}×",
            "yes" if x["identical"] else "**no**",
            fixed(x["load1"], 1)] for x in rows_of(r, "executors")]
    return (table(["executor", "trial stage", "against 1 worker", "final errors identical", "load"], out)
            + f"\n\n{fig(r, 'trials')} slab-truth trials of the paper prosthesis scene's first target.\n\n" + source(r))


@renderer("controller_iteration", "bench_control.models")
def _controller_iteration(r) -> str:
    out = [[x["model"],
            "–" if x["build_s"] is None else f"{fixed(x['build_s'], 1)} s" + (" (cached)" if x["cached"] else ""),
            "–" if x["error_mm"] is None else f"{num(x['error_mm'], 2)} mm", f"{num(x['iteration_ms'], 3)} ms"]
           for x in rows_of(r, "models")]
    s = r["data"]["scene"]
    return (table(["model", "build", "its error against the slab", "controller side of one iteration (median)"], out)
            + f"\n\nThe scene: {s['config']}, {num(s['triangles'])} triangles, its slab {num(s['tetrahedra'])} "
              "tetrahedra.\n\n" + source(r))


def _grouped(rows: list[dict], key) -> dict:
    out: dict = {}
    for x in rows:
        out.setdefault(key(x), []).append(x)
    return out


def _misses(xs: list[dict], digits: int = 2) -> str:
    """'T1 a / b / c, T2 …' (median / p95 / max of the miss across the needle) of one run's targets."""
    return ", ".join(f"{x['target']} " + (f"{fixed(x['miss_median'], digits)} / {fixed(x['miss_p95'], digits)} / "
                                          f"{fixed(x['miss_max'], digits)}" if x.get("miss_median") is not None
                                          else "no trials") for x in xs)


def _runs_of(rows: list[dict]) -> list[list[dict]]:
    """The report's rows (run after run, target after target) split into runs: a run ends where a target repeats
    (runs of one scene share their label; a refused target's row has no controller)."""
    runs: list[list[dict]] = []
    for x in rows:
        if not runs or any(y["target"] == x["target"] for y in runs[-1]):
            runs.append([])
        runs[-1].append(x)
    return runs


def _span(values: list[float], digits: int = 2) -> str:
    if not values:
        return "–"
    lo, hi = num(min(values), digits), num(max(values), digits)
    return lo if lo == hi else f"{lo}–{hi}"


def _summary_rows(r) -> list[list]:
    """One row per run (controller), its targets in the cells."""
    out = []
    for xs in _runs_of(rows_of(r, "summary")):
        done = [x for x in xs if x["trials"]]
        controller = next((x["controller"] for x in xs if x.get("controller")), "–")
        stops = sum(x.get("stroke_limit_stops") or 0 for x in done)
        plan = ", ".join(num(x.get("plan_model_error_mm"), 2) for x in done)
        per_it = [x["time_per_iteration_s"] for x in done if x.get("time_per_iteration_s") is not None]
        misses = _misses(done) + "".join(f", {x['target']} refused" for x in xs if not x["trials"])
        out.append([controller, misses, f"{stops} of {sum(x['trials'] for x in done)}", plan or "–", _span(per_it)])
    return out


@renderer("controller_models_example", "compare_controller_models.accuracy0.1")
def _controller_models_example(r) -> str:
    walls = ", ".join(f"{x['variant']} {fixed(x['wall_s'], 0)} s" for x in rows_of(r, "runs"))
    return (table(["controller", "miss median / p95 / max per target (mm)", "stroke-limit stops",
                   "error at the plan (mm)", "s per iteration"], _summary_rows(r))
            + f"\n\nThe runs (`--jobs 2`): {walls}.\n\n" + source(r))


@renderer("controller_models_paper", "compare_controller_models.paper_trials_prosthesis_slab")
def _controller_models_paper(r) -> str:
    return _controller_models_example(r)


@renderer("ultrasound", "bench_ultrasound")
def _ultrasound(r) -> str:
    out = [[x["measurement"], f"{fixed(x['median_ms'], 2)} ms", f"{fixed(x['p10_ms'], 2)}–{fixed(x['p90_ms'], 2)}",
            num(x.get("scatterers"))] for x in rows_of(r, "timings")]
    acc = [[f"shift {x['shift_mm']} mm" + (", strain" if x["strain"] else "") + (f", band ±{x['band_mm']} mm"
                                                                                 if x["band_mm"] else ""),
            fixed(x["envelope_correlation"], 3), f"{fixed(x['tracking_difference_um'], 1)} µm"]
           for x in rows_of(r, "fast_vs_simus")]
    extra = ""
    if acc:
        tof = [f"tissue {k.split('_')[-1]} m/s: fast {fixed(fig(r, k), 3)} mm, SIMUS "
               f"{fixed(r['figures'][k]['simus'], 3)} mm, the law {fixed(r['figures'][k]['expected'], 3)} mm"
               for k in r["figures"] if k.startswith("time_of_flight_")]
        env = ", ".join(f"{r['figures'][k]['scatterers_per_cell']}: {fixed(fig(r, k), 3)}"
                        for k in r["figures"] if k.startswith("envelope_mean_over_std_"))
        extra = ("\n\nThe fast model against SIMUS on the same scatterers:\n\n"
                 + table(["case", "envelope correlation", "tracked displacements apart"], acc)
                 + f"\n\nEnvelope mean/std in speckle (scatterers per resolution cell: value; Rayleigh 1.913): {env}. "
                 + "Time of flight of a point at 50 mm: " + "; ".join(tof) + ". Tracking: rigid sub-pixel shifts "
                 f"within {fixed(fig(r, 'rigid_tracking_error_max_um'), 1)} µm; first-frame localisation rms "
                 f"{fixed(fig(r, 'localisation_rms_um'), 0)} µm, max {fixed(fig(r, 'localisation_max_um'), 0)} µm.")
    return (table(["measurement", "median", "p10–p90 (ms)", "scatterers"], out)
            + f"\n\nSIMUS: {fixed(fig(r, 'simus_per_scatterer_ms'), 2)} ms per scatterer (a whole frame about "
              f"{fixed(fig(r, 'simus_whole_frame_min'), 0)} min)." + extra + "\n\n" + source(r))


@renderer("ultrasound_loop", "bench_ultrasound_loop")
def _ultrasound_loop(r) -> str:
    out = [[x["measurement"], f"{fixed(x['median_ms'], 2)} ms", num(x.get("scatterers")),
            "–" if "first_s" not in x else f"{fixed(x['first_s'], 2)} s"] for x in rows_of(r, "measure")]
    track = rows_of(r, "loop_tracking")
    p95 = [x["p95_um"] for x in track]
    return (table(["measurement", "median", "scatterers", "first call"], out)
            + f"\n\nThe fast model's validation against SIMUS in this run: envelope correlation "
              f"{fixed(fig(r, 'validation_envelope_correlation'), 3)}, tracked displacements "
              f"{fixed(fig(r, 'validation_tracking_difference_um'), 1)} µm apart. First-frame localisation at rest: "
              f"layer rms {fixed(fig(r, 'localisation_rest_layer_rms_um'), 0)} µm, slab rms "
              f"{fixed(fig(r, 'localisation_rest_slab_rms_um'), 0)} µm. Closed loops moving each target 2 mm "
              f"({len(track)} runs): tracking error of the displacement p95 "
              f"{fixed(min(p95), 0)}–{fixed(max(p95), 0)} µm, "
              f"{sum(x['lost'] for x in track)} frames lost; frame-to-frame jitter "
              f"{fixed(fig(r, 'jitter_std_um'), 1)} µm "
              f"per axis.\n\n" + source(r))


@renderer("study_ultrasound", STUDY)
def _study_ultrasound(r) -> str:
    runs = rows_of(r, "runs")
    out = []
    for x, xs in zip(runs, _runs_of(rows_of(r, "summary"))):
        out.append([x["study"], x["sensor"], f"{fixed(x['wall_s'] / 60, 1)} min", f"{fixed(x['trials_s'], 0)} s",
                    fixed(x["load1"], 1), _misses(xs)])
    top = []
    for run, xs in _grouped([x for x in rows_of(r, "budget") if x["source"] != "all" and x["trials"]],
                            lambda x: x["run"]).items():
        best = {}
        for x in xs:
            if x["mean_square_share"] > best.get(x["target"], {"mean_square_share": -1})["mean_square_share"]:
                best[x["target"]] = x
        top.append(f"{run}: " + ", ".join(f"{t} {b['source']} {fixed(b['mean_square_share'], 2)}"
                                          for t, b in best.items()))
    budget = ("" if not top else "\n\nThe source with the largest share of the miss's mean square per target, in "
              "each budget: " + "; ".join(top) + ".")
    return (table(["study", "sensor", "whole run", "trials", "load", "manipulation miss median / p95 / max per "
                   "target (mm)"], out) + budget + "\n\n" + source(r))


@renderer("ladder", "bench_slab_ladder")
def _ladder(r) -> str:
    out = [[x["config"], num(x["accuracy_mm"]), f"{fixed(x['wall_s'], 1)} s", f"{x['solved']} of {x['candidates']}",
            f"{num(x['pick_tetrahedra'])} (scale {num(x['pick_in_plane_scale'])}, {x['pick_levels']} levels)",
            f"{fixed(x['pick_error_mm'], 3)} mm", fixed(x["load1"], 1)] for x in rows_of(r, "ladders")]
    return (table(["scene", "accuracy (mm)", "choice (`--jobs 2`)", "candidates solved", "pick: tetrahedra",
                   "its distance from the finest", "load"], out) + "\n\n" + source(r))


@renderer("insertion3d", "bench_insertion3d")
@renderer("insertion3d_body", "bench_insertion3d.example_dome")
def _insertion3d(r) -> str:
    """bench_insertion3d's table on the slab or on a body (`data.scene.kind`)."""
    s = r["data"]["scene"]
    out = [[x["precision"], f"{fixed(x['insertion_s'], 1)} s"
            + (" (one run)" if x.get("runs", s["repeats"]) == 1 != s["repeats"] else ""),
            f"{fixed(x['step_median_ms'], 0)} ms",
            f"{fixed(x['factorisations_per_step'], 2)}, {fixed(x['passes_per_step'], 1)}, "
            f"{fixed(x['chord_steps_per_step'], 1)}",
            f"{fixed(x['gradient_ms'], 1)} + {fixed(x['solve_ms'], 1)} ms; {fixed(x['floor_ms'], 0)} ms",
            f"{fixed(x['step_mean_ms'], 0)} ms",
            f"{x['captured']} ({x['stuck']} stuck), {fixed(x['force_mN'], 0)} mN", f"{fixed(x['miss_mm'], 3)} mm"]
           for x in rows_of(r, "precisions")]
    if s.get("kind") == "body":
        what = (f"The body: {s['config']}'s, {num(s['tetrahedra'])} tetrahedra (`{s['element']}`), "
                f"{num(s['free_dofs'])} free dofs, at rest; lesion {s['target']} from the skin, strategy `none`")
    else:
        what = (f"The slab: {s['config']}'s, {num(s['tetrahedra'])} tetrahedra, {num(s['free_dofs'])} free dofs; "
                f"target {s['target']}, strategy `none`")
    return (table(["kept factor", f"{num(s['depth_mm'])} mm, median of {s['repeats']}", "a step (median)",
                   "per step: factorisations, passes, chord steps", "gradient + solve; a step's floor",
                   "a step (mean)", "captured at the end, force", "miss"], out)
            + f"\n\n{what}. The float32 and float64 factors' final nodes "
              f"{num(fig(r, 'float32_float64_nodes_apart_mm'), 2)} mm apart; float32 takes "
              f"{fixed(fig(r, 'float32_over_float64'), 2)}× the time.\n\n" + source(r))


@renderer("needle_trial_parts", "bench_needle_trial_parts")
def _needle_trial_parts(r) -> str:
    """bench_needle_trial_parts: each part's time, refactorisations and Newton take-overs per stage and needle; the
    cup moves under the needle by size."""
    parts = [[x["stage"], f"`{x['strategies']}`".replace(" + ", "` + `"), x["part"], num(x["calls"]),
              f"{fixed(x['wall_s'], 1)} s ({fixed(100 * x['share'], 0)} %)",
              f"{num(x['refactorisations'])} ({fixed(x['refactorisation_s'], 1)} s)",
              f"{num(x['newton'])} ({fixed(x['newton_s'], 1)} s)"] for x in rows_of(r, "parts")]
    moves = [[x["stage"], f"{num(x['from_mm'])}–{num(x['to_mm'])} mm" if x["to_mm"] not in (None, float("inf"))
              else f"over {num(x['from_mm'])} mm", num(x["moves"]), f"{fixed(x['wall_s'], 1)} s",
              f"{fixed(1e3 * x['wall_s'] / x['moves'], 0)} ms" if x["moves"] else "–", num(x["refactorisations"]),
              num(x["newton"])] for x in rows_of(r, "moves")]
    return (table(["stage", "needle", "part", "calls", "time (share of the stage's insertions)",
                   "refactorisations", "Newton take-overs"], parts)
            + "\n\n" + table(["stage", "a cup move under the needle", "moves", "time", "a move (mean)",
                                "refactorisations", "Newton take-overs"], moves)
            + f"\n\n{num(fig(r, 'trials'))} trials, median {fixed(fig(r, 'trial_median_s'), 1)} s each (timed with the "
              f"parts charged; the closed loop before the needle included).\n\n" + source(r))


@renderer("needle_3d", "bench_needle_3d")
def _needle_3d(r) -> str:
    full = load("bench_needle_3d.full")
    results = [r] + ([full] if full else [])
    runs, misses = [], []
    for res in results:
        for x in rows_of(res, "runs"):
            if any(x["run"] == row[0] for row in runs):
                continue
            trial = ", ".join(f"{t} {fixed(v, 1)} s" for t, v in x["trial_s"].items())
            runs.append([x["run"], x["config"], "ok" if x["exit"] == 0 else f"exit {x['exit']}",
                         f"{fixed(x['wall_s'] / 60, 1)} min", trial or "–", fixed(x["load1"], 1)])
        for (run, strategy), xs in _grouped(rows_of(res, "misses"), lambda x: (x["run"], x["strategy"])).items():
            if not any(m[0] == run and m[1] == f"`{strategy}`" for m in misses):
                misses.append([run, f"`{strategy}`", ", ".join(
                    f"{x['target']} {fixed(x['median_mm'], 3)} / {fixed(x['p95_mm'], 3)} / {fixed(x['max_mm'], 3)} "
                    f"({x['trials']})" for x in xs)])
    return (table(["run", "config", "exit", "`simulate --jobs 2` from nothing", "median trial", "load at the end"],
                  runs)
            + "\n\n" + table(["run", "strategy", "needle miss median / p95 / max per target, mm (trials)"], misses)
            + "\n\n" + source(*results))


@renderer("brief")
def _brief() -> str:
    """README's "Results in brief": one headline per section of performance.md, from its result file where there
    is one, else what the section measures (no number)."""
    rows = []

    def add(label: str, anchor: str, name: str | None, fn, fallback: str):
        r = load(name) if name else None
        text = fallback
        if r is not None:
            try:
                text = fn(r)
            except (KeyError, IndexError, TypeError, ValueError, StopIteration):
                text = fallback
        rows.append([f"[{label}](docs/performance.md#{anchor})", text])

    def mechanics(r):
        n = next(x for x in rows_of(r, "solves") if x["case"] == "push10" and x["solver"] == "newton")
        a = next(x for x in rows_of(r, "solves") if x["case"] == "push10" and x["solver"] == "admm"
                 and x["mode"] == "settled")
        return (f"the example's 10 mm push: Newton in {n['iterations']} iterations to 1e-10 ({fixed(n['ms'], 0)} ms); "
                f"ADMM within {num(a['error_rel'], 2)} of it")

    def cups(r):
        m = [x["miss_median"] for x in rows_of(r, "cups")]
        t = rows_of(r, "cups")[0]["trials"]
        return (f"median miss across the needle {fixed(min(m))}–{fixed(max(m))} mm over {t} trials per target, "
                "either way")

    def grip(r):
        return (f"{fig(r, 'grip_candidates')} candidate grips scored in {fixed(fig(r, 'grip_search_ms'), 0)} ms by one "
                "adjoint solve per target component")

    def needle(r):
        xs = rows_of(r, "insertion")
        loop = [x["miss_mm"] for x in xs if x["strategy"] == "loop"]
        none = [x["miss_mm"] for x in xs if x["strategy"] == "none"]
        span = fixed(min(loop), 3) if fixed(min(loop), 3) == fixed(max(loop), 3) else \
            f"{fixed(min(loop), 3)}–{fixed(max(loop), 3)}"
        return f"the `loop` strategy ends {span} mm from the target (no correction: up to {fixed(max(none))} mm)"

    def layer(r):
        p = [x["layer_check_in_plane_diff_pct"] for x in rows_of(r, "layer_check")]
        return f"the 2-D layer overstates the targets' in-plane motion by {fixed(min(p), 0)}–{fixed(max(p), 0)} %"

    def models(r):
        stops = {}
        for xs in _runs_of(rows_of(r, "summary")):
            done = [x for x in xs if x["trials"]]
            controller = next((x["controller"] for x in xs if x.get("controller")), "–")
            stops[controller] = (sum(x.get("stroke_limit_stops") or 0 for x in done), sum(x["trials"] for x in done))
        (a, b), (c, d) = stops["layer"], stops["surrogate"]
        return (f"stroke-limit stops on the paper scene: the paper's layer model {a} of {b}, the slab surrogate "
                f"{c} of {d}")

    def trials(r):
        p, e = rows_of(r, "studies")
        return (f"max \\|x\\| {fixed(p['max_x_mm'])} / {fixed(e['max_x_mm'])} mm (paper {p['paper_max_x_mm']} / "
                f"{e['paper_max_x_mm']}), max \\|y\\| {fixed(p['max_y_mm'])} / {fixed(e['max_y_mm'])} mm (paper "
                f"{p['paper_max_y_mm']} / {e['paper_max_y_mm']})")

    def budget(r):
        rows = [x for x in r["data"]["budget_example_3d"]["rows"] if x["trials"] and x["source"] != "all"]
        top = max(rows, key=lambda x: x["mean_square_share"])
        slab = next(x for x in rows if x["source"] == "slab")
        return (f"slab truth, the surrogate steering (example_3d): {top['source']} holds "
                f"{fixed(100 * top['mean_square_share'], 0)} % of the miss's mean square, the 3-D slab alone "
                f"{fixed(100 * slab['mean_square_share'], 0)} %")

    def goals(_):
        g = _goal_rows()
        measured = [x for x in g if x[2] != "–"]
        unmet = [x[0] for x in measured if x[2] != "yes"]
        return (f"{len(measured) - len(unmet)} of {len(measured)} measured goals met"
                + (f"; not met: {'; '.join(unmet)}" if unmet else ""))

    def needle3d(r):
        run = "example_3d" if r.get("variant") == "full" else "default-slab"
        row = next(x for x in rows_of(r, "runs") if x["run"] == run)
        loop = [x for x in rows_of(r, "misses") if x["strategy"] == "loop" and x["run"] == run]
        what = "`configs/example_3d.yaml`" if run == "example_3d" else "`layer_check: {}` with the needle in the slab"
        return (f"{what}: `simulate --jobs 2` in {fixed(row['wall_s'] / 60, 1)} min from nothing"
                + "".join(f"; {x['target']}'s `loop` miss median / p95 {fixed(x['median_mm'], 2)} / "
                          f"{fixed(x['p95_mm'], 2)} mm ({x['trials']} trials)" for x in loop))

    def ultrasound(r):
        t = {x["measurement"]: x for x in rows_of(r, "timings")}
        c = [x["envelope_correlation"] for x in rows_of(r, "fast_vs_simus")]
        return (f"a B-mode frame {fixed(t['fast frame, in-plane']['median_ms'], 0)} ms, its tracking "
                f"{fixed(t['tracking one frame']['median_ms'], 1)} ms; fast model against SIMUS: envelope correlation "
                f"{fixed(min(c), 2)}–{fixed(max(c), 2)}")

    add("Mechanics", "mechanics", "bench_forward", mechanics, "Newton and ADMM on the example's forward cases")
    add("One cup against two", "one-cup-against-two", "docs_scenes", cups,
        "the miss across the needle with one cup and with two, 30 trials per target")
    add("Where to grip", "where-to-grip", "bench_control.table", grip,
        "candidate grips scored by one adjoint solve per target component")
    add("Needle insertion", "needle-insertion", "docs_scenes", needle, "the miss at the needle per strategy")
    add("Does one layer suffice?", "the-layer-check", "docs_scenes", layer, "the 2-D layer against the 3-D slab")
    add("Controller models", "controller-models-15", "compare_controller_models.paper_trials_prosthesis_slab", models,
        "every controller model against the slab truth: stroke-limit stops, misses, cost per iteration")
    add("Trials against the paper", "trials", "bench_trials", trials, "the paper's 4 × 30 studies against its maxima")
    add("Error budget", "error-budget", "bench_needle_3d.full", budget, "what each error source adds to the miss")
    add("Speed goals", "the-speed-goals", None, goals, "")
    rows[-1][1] = goals(None)
    add("The needle in 3-D", "the-needle-that-hits-in-3-d-18", "bench_needle_3d.full|bench_needle_3d", needle3d,
        "whole runs with the needle in the slab, end to end")
    def dome(r):
        xs = rows_of(r, "targets")
        paper = r["data"]["paper_max_mm"]
        return (f"the paper's bench as a dome, 4 × 30 trials in {wall_minutes(r)}: max \\|x\\| "
                f"{fixed(max(x['max_x_mm'] for x in xs))}, \\|y\\| {fixed(max(x['max_y_mm'] for x in xs))} mm "
                f"(paper {num(paper['x'])} / {num(paper['y'])}); the vertical \\|z\\| the paper could not see "
                f"{fixed(max(x['max_z_mm'] for x in xs))} mm")

    add("The breast in 3-D", "the-breast-in-3-d", "bench_dome_study", dome,
        "the breast as a 3-D dome: meshed, solved, planned and moved in 3-D")

    def reduction(r):
        xs = rows_of(r, "targets")
        return (f"the paper's layer on each target's section driving the dome (held opposite the cup), 4 × 30 "
                f"trials: max \\|x\\| {fixed(max(x['max_x_mm'] for x in xs))}, \\|y\\| "
                f"{fixed(max(x['max_y_mm'] for x in xs))}, \\|z\\| {fixed(max(x['max_z_mm'] for x in xs))} mm, "
                f"{sum(x['at_stroke_limit'] for x in xs)} at the stroke limit")

    add("The paper's reduction on the dome", "the-papers-bench-as-a-dome", "bench_dome_study.layer", reduction,
        "the paper's 2-D layer as the controller's model of the dome")
    add("Ultrasound in the loop", "ultrasound-in-the-loop", "bench_ultrasound", ultrasound,
        "B-mode frames, tracking and the fast model against SIMUS")
    add("Model only what a scene needs", "model-only-what-a-scene-needs", None, None,
        "`solver.accuracy_mm` and `layer_check.accuracy_mm` pick the cheapest model within a budget")
    return table(["result", "headline"], rows)


# ---------------------------------------------------------------------------------------------------- tables


def blocks(text: str):
    """(name, start of its body, end of its body) of every generated block of a doc."""
    for m in BEGIN.finditer(text):
        end = text.find(END, m.end())
        if end < 0:
            raise SystemExit(f"<!-- generated: {m.group(1)} --> without {END}")
        yield m.group(1), m.end(), end


def regenerate(text: str) -> str:
    out, at = [], 0
    for name, start, end in blocks(text):
        if name not in RENDERERS:
            raise SystemExit(f"<!-- generated: {name} -->: no such renderer (benchmarks/docs.py: {sorted(RENDERERS)})")
        out += [text[at:start], render(name), "\n"]
        at = end
    out.append(text[at:])
    return "".join(out)


def table_docs() -> list[Path]:
    return [p for p in DOC_FILES if p.is_file() and BEGIN.search(p.read_text())]


# ---------------------------------------------------------------------------------------------------- images

#: docs/img file → its source: ("results", result file, drawing function name) or ("run", scene key, file in it)
IMAGES = {
    "budget_slab.png": ("results", "bench_needle_3d.full", "draw_budget_slab"),
    "controller_models_example_full.png": ("results", "compare_controller_models.accuracy0.1",
                                           "draw_controller_models"),
    "controller_models_paper.png": ("results", "compare_controller_models.paper_trials_prosthesis_slab",
                                    "draw_controller_models"),
    "insertion_force_T1.png": ("run", "example_insertion", "insertion_force_T1.png"),
    "insertion_path_T2.png": ("run", "example_insertion", "insertion_path_T2.png"),
    "layer_check_push10.png": ("run", "example_full", "layer_check_push10.png"),
    "manipulation_points.png": ("run", "example_full", "manipulation_points.png"),
    "miss_one_vs_two_cups.png": ("run", "cups_report", "miss_boxplots.png"),
    "ultrasound_bmode_T1.png": ("run", "ultrasound", "imaging_T1.png"),
}

#: the runs the images (and benchmarks/results/docs_scenes.json) come from: key → (config, simulate options)
SCENES = {
    "example_full": ("configs/example_full.yaml", ["--trials", "0"]),
    "example_insertion": ("configs/example_insertion.yaml", ["--trials", "0"]),
    # the B-mode figure comes from the nominal manipulation, which a run makes only with trials
    "ultrasound": ("configs/paper_trials_prosthesis_slab_ultrasound.yaml", ["--trials", "1"]),
    "one_cup": ("configs/example.yaml", []),
    "two_cups": ("configs/two_cups.yaml", []),
}


def draw_budget_slab(r: dict, path: Path) -> bool:
    from scissor_cli.output.error_budget.figures import budget_figure  # noqa: PLC0415
    from scissor_cli.output.figures import save  # noqa: PLC0415

    b = r["data"].get("budget_example_3d")
    if not b:
        return False
    save(budget_figure(b["title"], b["rows"], b["profile"]), path)
    return True


def draw_controller_models(r: dict, path: Path) -> bool:
    import numpy as np  # noqa: PLC0415

    from scissor_cli.layer3d.tissue_models import ModelPaths  # noqa: PLC0415
    from scissor_cli.output.controller_model import controller_models_figure  # noqa: PLC0415
    from scissor_cli.output.figures import save  # noqa: PLC0415

    data = r["data"].get("model_paths")
    if not data or not data["paths"]:
        return False
    paths = []
    for p in data["paths"]:
        lines = {k: [np.asarray(v, float) for v in p[k]] for k in ("strokes", "model", "layer", "slab_strokes", "slab")}
        rest = None if p["rest"] is None else np.asarray(p["rest"], float)
        paths.append(ModelPaths(p["kind"], p["cup_names"], p["target_names"], lines["strokes"], lines["model"],
                                lines["layer"], lines["slab_strokes"], lines["slab"], rest))
    save(controller_models_figure(paths, data["title"]), path)
    return True


def simulate(config: str, out: Path, options: list[str]) -> None:
    cmd = [sys.executable, "-m", "scissor_cli", "simulate", str(ROOT / config), "--jobs", "2", "--out", str(out),
           "--force", *options]
    print("  " + " ".join(cmd[1:]), flush=True)
    r = subprocess.run(cmd, capture_output=True, text=True, env=results_io.subprocess_env(), cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(f"{config}: exit {r.returncode}\n{r.stderr[-3000:]}")


def run_scenes(work: Path) -> dict[str, Path]:
    """Run every scene of SCENES into work/<key> (and the cups' report), save docs_scenes.json; {key: folder}."""
    import h5py  # noqa: PLC0415
    import numpy as np  # noqa: PLC0415

    sys.path.insert(0, str(ROOT))
    from scissor_cli.output.layer_check import layer_check_rows  # noqa: PLC0415
    from scissor_cli.output.report import load_run, summary_rows  # noqa: PLC0415

    res = results_io.Results("docs_scenes")
    folders = {}
    for key, (config, options) in SCENES.items():
        t0 = time.perf_counter()
        simulate(config, work / key, options)
        folders[key] = work / key
        res.figure(f"{key}_run_s", time.perf_counter() - t0, "s", config=config, options=" ".join(options),
                   load=results_io.load1())
    folders["cups_report"] = work / "cups_report"
    r = subprocess.run([sys.executable, "-m", "scissor_cli", "report", str(work / "one_cup"), str(work / "two_cups"),
                        "--out", str(folders["cups_report"])], capture_output=True, text=True,
                       env=results_io.subprocess_env(), cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(f"report: exit {r.returncode}\n{r.stderr[-3000:]}")
    rows = summary_rows([load_run(work / "one_cup"), load_run(work / "two_cups")])
    res.table("cups", [{k: x.get(k) for k in ("run", "cups", "target", "trials", "miss_median", "miss_p95", "miss_max",
                                              "along_median_abs", "iterations_mean")} for x in rows],
              {"miss_median": "mm", "miss_p95": "mm", "miss_max": "mm", "along_median_abs": "mm"})
    with h5py.File(work / "example_full" / "results.h5", "r") as f:
        res.table("layer_check", layer_check_rows("example_full", f),
                  {"layer_check_in_plane_diff_mm": "mm", "layer_check_in_plane_diff_pct": "%", "out_of_plane_mm": "mm",
                   "time_s": "s"})
        a = dict(f["manipulation_points"].attrs)
        res.data("manipulation_points", {"config": "configs/example_full.yaml", "candidates": int(a["candidates"]),
                                         "search_s": float(a["search_s"]), "verify_s": float(a["verify_s"]),
                                         "chosen": np.asarray(a["chosen"], float), "axes": np.asarray(a["axes"],
                                                                                                      float)})
    res.data("layer_check_config", "configs/example_full.yaml, on the slab its `layer_check.accuracy_mm` (0.1 mm by "
                                   "default) picks")
    ins = []
    with h5py.File(work / "example_insertion" / "results.h5", "r") as f:
        for target, g in f["insertion"].items():
            for strategy, s in g.items():
                if not isinstance(s, h5py.Group) or "miss_mm" not in s.attrs:
                    continue
                a = s.attrs
                along = np.asarray(s["target"][()], float)
                direction = np.asarray(a["direction"], float)[:2]
                drag = np.abs((along[:, :2] - along[0, :2]) @ direction).max()
                ins.append({"target": target, "strategy": strategy, "miss_mm": float(a["miss_mm"]),
                            "depth_error_mm": float(a["depth_error_mm"]),
                            "peak_force_mN": float(np.max(s["needle_force_mN"][()])), "drag_mm": float(drag),
                            "steps": int(a["steps"])})
    res.table("insertion", ins, {"miss_mm": "mm", "depth_error_mm": "mm", "peak_force_mN": "mN", "drag_mm": "mm"})
    res.data("insertion_config", "configs/example_insertion.yaml")
    res.write()
    return folders


def write_images(only_results: bool = False) -> list[str]:
    """Every image of IMAGES into docs/img; the names it could not make (a result file missing)."""
    failed = []
    work = Path(tempfile.mkdtemp(prefix="scissor-docs-"))
    try:
        folders = {} if only_results else run_scenes(work)
        for name, (kind, src, what) in IMAGES.items():
            if kind == "results":
                r = load(src)
                ok = r is not None and globals()[what](r, IMG / name)
            elif only_results:
                continue  # a scene run's image: left as it is
            else:
                path = folders.get(src, Path("/nonexistent")) / what
                ok = path.is_file()
                if ok:
                    shutil.copyfile(path, IMG / name)
            print(f"{'wrote' if ok else 'NOT written'}: docs/img/{name}"
                  + ("" if ok else f" (needs {src}: {command(src) if kind == 'results' else 'the scene run'})"))
            if not ok:
                failed.append(name)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return failed


# ---------------------------------------------------------------------------------------------------- main


def check() -> list[str]:
    problems = []
    for path in table_docs():
        text = path.read_text()
        if regenerate(text) != text:
            problems.append(f"{path.relative_to(ROOT)}: a generated table differs from benchmarks/results "
                            "(python3 benchmarks/docs.py --tables-only)")
    have = {p.name for p in IMG.iterdir() if p.is_file()}
    for name in sorted(set(IMAGES) - have):
        problems.append(f"docs/img/{name}: missing (python3 benchmarks/docs.py --images-only)")
    for name in sorted(have - set(IMAGES)):
        problems.append(f"docs/img/{name}: no source in benchmarks/docs.py IMAGES")
    for name, (kind, src, _) in IMAGES.items():
        if kind == "results" and load(src) is None:
            print(f"note: docs/img/{name} is drawn from benchmarks/results/{src}.json, which is not there yet "
                  f"({command(src)})", file=sys.stderr)
    return problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--check", action="store_true", help="exit 1 if the committed docs differ (no simulation)")
    mode.add_argument("--list", action="store_true", help="print every file this writes")
    mode.add_argument("--tables-only", action="store_true")
    mode.add_argument("--images-only", action="store_true")
    mode.add_argument("--result-images", action="store_true",
                      help="only the images drawn from result files (no scene runs)")
    args = ap.parse_args(argv)
    if args.list:
        for path in table_docs():
            print(path.relative_to(ROOT))
        for name in IMAGES:
            print(f"docs/img/{name}")
        print("benchmarks/results/docs_scenes.json")  # the scene runs' figures (--images-only)
        return 0
    if args.check:
        problems = check()
        for p in problems:
            print(p)
        return 1 if problems else 0
    if not args.images_only and not args.result_images:
        write_tables()
    if args.tables_only:
        return 0
    failed = write_images(only_results=args.result_images)
    if not args.result_images and not args.images_only:
        write_tables()  # the scene runs rewrote docs_scenes.json: the tables that read it again
    return 1 if failed else 0


def write_tables() -> None:
    """Regenerate every generated table of the docs that read them, writing the files that change."""
    for path in table_docs():
        text = path.read_text()
        new = regenerate(text)
        if new != text:
            path.write_text(new)
            print(f"wrote: {path.relative_to(ROOT)}")


if __name__ == "__main__":
    raise SystemExit(main())
