"""`scissor report`: combine runs into box plots and summary tables.

Reads one or more run directories (their results.h5), writes the error box
plots of all runs together, a per-target summary table as Markdown and CSV,
and returns the table for printing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import h5py
import numpy as np

from scissor_cli.config import ConfigError, parse_config
from scissor_cli.experiments import study as study_mod
from scissor_cli.output import figures, layer_check, tables
from scissor_cli.output.controller_model import report_models_figure
from scissor_cli.output.error_budget.report import report_budget
from scissor_cli.output.imaging.report import report_sensors
from scissor_cli.output.imaging.results import sensor_of
from scissor_cli.output.insertion.report import report_insertion
from scissor_cli.output.results import finished_trials, read_study


class ReportError(ValueError):
    """A run cannot be reported (missing, incomplete, or without trials)."""


@dataclass
class TargetTrials:
    errors: np.ndarray  # (T, 2) mm, finished trials only
    iterations: np.ndarray  # (T,)
    time_s: np.ndarray  # (T,)
    corridor_clear: np.ndarray  # (T,) bool
    miss: np.ndarray = None  # (T,) mm across the needle (runs before it was stored: None)
    along: np.ndarray = None  # (T,) mm along the needle, for the depth
    stroke_limit: int = 0  # trials that ended at a stroke limit
    #: the controller's model against the nominal slab at the plan's strokes (mm; /plan/<t> model_error_mm)
    plan_model_error_mm: float = float("nan")
    #: (T,) iterations beyond the fewest control periods the drives need, at full speed, to reach each trial's
    #: final strokes from rest (None without histories)
    extra_iterations: np.ndarray = None


@dataclass
class RunTrials:
    label: str
    path: Path
    status: str
    targets: dict[str, TargetTrials]
    cups: int = 0
    #: the controller's model (docs/model.md §15): kind + jacobian_update, its build time (s) and error (mm)
    controller: str = "layer"
    model_build_s: float = float("nan")
    model_error_mm: float = float("nan")
    #: what the loop saw the target with: "ultrasound" (the run has /imaging) or "camera"
    sensor: str = "camera"


def load_run(run_dir: Path, partial: bool = False) -> RunTrials:
    path = _check_status(run_dir, partial)
    with h5py.File(path, "r") as f:
        status = str(f.attrs.get("status", "unknown"))
        if "trials" not in f:
            raise ReportError(f"{path}: the run has no trials (it was run with --trials 0)")
        profile = f["trials"].attrs.get("profile", "")
        name = _config_name(f.attrs.get("config_yaml", ""))
        step_mm = _period_step_mm(f.attrs.get("config_yaml", ""))
        targets = {}
        for t, g in f["trials"].items():
            ok = finished_trials(g) & np.isfinite(g["final_error"][:]).all(axis=1)
            miss = g["manipulation_miss_mm"][:][ok] if "manipulation_miss_mm" in g else None
            along = g["along_mm"][:][ok] if "along_mm" in g else None
            stops = int(np.sum(g["stop_reason"][:][ok].astype(str) == "stroke_limit")) if "stop_reason" in g else 0
            plan = f["plan"][t].attrs if "plan" in f and t in f["plan"] else {}
            targets[t] = TargetTrials(g["final_error"][:][ok], g["iterations"][:][ok], g["time_s"][:][ok],
                                      g["corridor_clear"][:][ok], miss, along, stops,
                                      float(plan.get("model_error_mm", np.nan)),
                                      _extra_iterations(g, np.flatnonzero(ok), step_mm))
        cups = len(f["cups"]) if "cups" in f else 0
        controller, build, error = _controller(f)
        sensor = sensor_of(f)
    return RunTrials(f"{name} ({profile})", Path(run_dir), status, targets, cups, controller, build, error, sensor)


def _period_step_mm(config_yaml: str) -> Optional[np.ndarray]:
    """(C,) mm each drive moves in one control period at full speed (speed / rate), or None (no readable config)."""
    try:
        cfg = parse_config(config_yaml, "<run config>")
    except ConfigError:
        return None
    return np.array([c.speed_mm_per_s for c in cfg.cups]) / cfg.controller.rate_hz if cfg.cups else None


def _extra_iterations(g, trials: np.ndarray, step_mm: Optional[np.ndarray]) -> Optional[np.ndarray]:
    """(len(trials),) each trial's iterations less ceil(max_c |final stroke_c| / step_c): what the loop took beyond
    the drives' speed (docs/model.md §15); None without histories or cups."""
    if step_mm is None or "history" not in g:
        return None
    out = []
    for k in trials:
        h = g["history"][str(k)]
        columns = [str(c) for c in h.attrs["columns"]]
        strokes = [j for j, c in enumerate(columns) if c.startswith("stroke_") and not c.startswith("stroke_cmd_")]
        final = np.abs(h[-1, strokes]) if len(strokes) == len(step_mm) and len(h) else np.zeros(len(step_mm))
        out.append(int(g["iterations"][k]) - int(np.ceil(np.max(final / step_mm) - 1e-9)))
    return np.asarray(out, int)


def _controller(f) -> tuple[str, float, float]:
    """(kind[+broyden], build time s, error mm) of a run's controller model; a run without /controller_model: the
    kind its /trials name (a body's `body`), else the layer."""
    if "controller_model" in f:
        a = f["controller_model"].attrs
        update = str(a.get("jacobian_update", "none"))
        kind = str(a["kind"]) + ("+broyden" if update == "broyden" else "")
        return kind, float(a.get("build_time_s", np.nan)), float(a.get("validation_error_mm", np.nan))
    text = str(f.attrs.get("config_yaml", ""))
    trials = f["trials"].attrs if "trials" in f else {}
    kind = str(trials["controller_model"]) if "controller_model" in trials else "layer"
    return (kind + "+broyden" if "jacobian_update: broyden" in text else kind), float("nan"), float("nan")


def _config_name(text: str) -> str:
    for line in text.splitlines():
        if line.startswith("name:"):
            return line.split(":", 1)[1].strip()
    return "run"


COLUMNS = [
    "run", "target", "trials", "mean_x", "median_x", "max_x", "p95_x", "mean_y", "median_y", "max_y", "p95_y",
    "iterations_mean", "iterations_max", "time_s_mean", "corridor_clear_pct",
    "cups", "miss_median", "miss_p95", "miss_max", "along_median_abs",
    "controller", "sensor", "stroke_limit_stops", "time_per_iteration_s", "model_build_s", "model_error_mm",
    "plan_model_error_mm", "extra_iterations_median", "extra_iterations_max",
]


def summary_rows(runs: list[RunTrials]) -> list[dict]:
    """One row per run and target: statistics of |x| and |y| error (mm), iterations, time."""
    rows = []
    for run in runs:
        for t, d in run.targets.items():
            row = {"run": run.label, "target": t, "trials": len(d.errors), "sensor": run.sensor}
            if len(d.errors):
                a = np.abs(d.errors)
                for j, axis in enumerate("xy"):
                    row[f"mean_{axis}"] = a[:, j].mean()
                    row[f"median_{axis}"] = np.median(a[:, j])
                    row[f"max_{axis}"] = a[:, j].max()
                    row[f"p95_{axis}"] = np.percentile(a[:, j], 95)
                row["iterations_mean"] = d.iterations.mean()
                row["iterations_max"] = int(d.iterations.max())
                row["time_s_mean"] = d.time_s.mean()
                row["corridor_clear_pct"] = 100.0 * d.corridor_clear.mean()
                row["cups"] = run.cups
                row["controller"], row["stroke_limit_stops"] = run.controller, d.stroke_limit
                moved = d.iterations > 0
                row["time_per_iteration_s"] = (float(np.median(d.time_s[moved] / d.iterations[moved])) if moved.any()
                                               else float("nan"))
                row["model_build_s"], row["model_error_mm"] = run.model_build_s, run.model_error_mm
                row["plan_model_error_mm"] = d.plan_model_error_mm
                if d.extra_iterations is not None and len(d.extra_iterations):
                    row["extra_iterations_median"] = float(np.median(d.extra_iterations))
                    row["extra_iterations_max"] = int(d.extra_iterations.max())
                if d.miss is not None:
                    row["miss_median"], row["miss_max"] = np.median(d.miss), d.miss.max()
                    row["miss_p95"] = np.percentile(d.miss, 95)
                    row["along_median_abs"] = np.median(np.abs(d.along))
            rows.append(row)
    return rows


def markdown_table(rows: list[dict], columns: list[str] = COLUMNS) -> str:
    return tables.markdown_table(rows, columns)


def write_csv(path: Path, rows: list[dict], columns: list[str] = COLUMNS) -> None:
    tables.write_csv(path, rows, columns)


@dataclass
class ReportOutput:
    out_dir: Path
    files: list[Path]
    table_markdown: str


STUDY_THRESHOLDS_MM = (1.0, 0.1, 0.01)
CHEAPEST_COLUMNS = ["run", "case", "accuracy_mm", "solver", "tolerance", "model", "kind", "level", "n_elements",
                    "time_s", "error_reference_mm", "note"]


def _check_status(run_dir: Path, partial: bool) -> Path:
    path = Path(run_dir) / "results.h5"
    if not path.is_file():
        raise ReportError(f"{run_dir}: no results.h5 (is this a scissor run directory?)")
    with h5py.File(path, "r") as f:
        status = str(f.attrs.get("status", "unknown"))
        if status != "complete" and not partial:
            reason = f.attrs.get("failure", "")
            raise ReportError(
                f"{path}: status is {status!r}, not 'complete'" + (f" ({reason})" if reason else "")
                + "; finish it with 'scissor simulate --resume' or pass --partial"
            )
    return path


def make_report(run_dirs: list[Path], out_dir: Path, partial: bool = False) -> ReportOutput:
    """Trials (box plots, summary) and studies (speed vs error, cheapest settings) of the runs."""
    paths = [_check_status(d, partial) for d in run_dirs]
    with_trials, with_study, checks = [], [], []
    for d, p in zip(run_dirs, paths):
        with h5py.File(p, "r") as f:
            checks += layer_check.layer_check_rows(_config_name(f.attrs.get("config_yaml", "")), f)
            if "trials" in f:
                with_trials.append(d)
            if "study" in f:
                with_study.append((d, study_mod.rows_from_columns(read_study(f)),
                                   _config_name(f.attrs.get("config_yaml", ""))))
    if not with_trials and not with_study and not checks:
        raise ReportError("none of the runs has trials, a study or a layer check "
                          "(run simulate with --trials N or --study)")
    out_dir.mkdir(parents=True, exist_ok=True)
    files, text = [], ""
    if with_trials:
        trials = report_trials(with_trials, out_dir, partial=True)
        files += trials.files
        text += trials.table_markdown
    if with_study:
        files_s, text_s = report_studies(with_study, out_dir)
        files += files_s
        text += ("\n" if text else "") + text_s
    if checks:  # docs/model.md §13: how far the 2-D layer is from the 3-D slab
        table = markdown_table(checks, layer_check.REPORT_COLUMNS)
        (out_dir / "layer_check.md").write_text(table)
        write_csv(out_dir / "layer_check.csv", checks, layer_check.REPORT_COLUMNS)
        files += [out_dir / "layer_check.md", out_dir / "layer_check.csv"]
        text += ("\n" if text else "") + "Layer check (3-D slab against the 2-D layer):\n" + table
    return ReportOutput(out_dir, files, text)


def report_studies(studies: list[tuple[Path, list, str]], out_dir: Path) -> tuple[list[Path], str]:
    files, rows_out, ratios = [], [], []
    for run_dir, rows, name in studies:
        ok = np.array([r.converged for r in rows])
        curves = {}
        for key in {(r.solver, r.model, r.kind) for r in rows}:
            sel = np.array([(r.solver, r.model, r.kind) == key and r.converged for r in rows])
            # one point per (level, tolerance): the slowest case, the largest error (a setting serves all cases)
            curves[key] = _per_setting(rows, sel)
        settings_err, settings_t = zip(*curves.values()) if curves else ((), ())
        all_err = np.concatenate(settings_err) if settings_err else np.zeros(0)
        all_t = np.concatenate(settings_t) if settings_t else np.zeros(0)
        front = study_mod.pareto_front(all_t, all_err)
        fig = figures.speed_error_figure(f"{name}: speed against error ({ok.sum()} solves)", curves,
                                         (all_err[front], all_t[front]))
        tag = Path(run_dir).name
        files.append(figures.save(fig, out_dir / f"speed_vs_error_{tag}.png"))
        for case in sorted({r.case for r in rows}):
            for thr in STUDY_THRESHOLDS_MM:
                best = study_mod.cheapest(rows, thr, case)
                row = {"run": name, "case": case, "accuracy_mm": thr}
                if best is not None:
                    row.update({c: getattr(best, c) for c in CHEAPEST_COLUMNS[3:-1]})
                    # errors are measured against the finest graded Newton solve, which meets any threshold trivially
                    row["note"] = "the reference itself" if best.error_reference_mm == 0 else ""
                else:
                    row["solver"] = "none reaches it"
                rows_out.append(row)
        for thr in STUDY_THRESHOLDS_MM:
            counts = study_mod.graded_vs_uniform(rows, thr)
            if counts:
                ratios.append(f"{name}: to {thr:g} mm a graded mesh needs {counts[0]} elements, a uniform one "
                              f"{counts[1]} ({counts[1] / counts[0]:.1f}x more)")
    table = markdown_table(rows_out, CHEAPEST_COLUMNS)
    (out_dir / "study_cheapest.md").write_text(table + "\n" + "\n".join(ratios) + "\n")
    write_csv(out_dir / "study_cheapest.csv", rows_out, CHEAPEST_COLUMNS)
    files += [out_dir / "study_cheapest.md", out_dir / "study_cheapest.csv"]
    return files, table + ("\n" + "\n".join(ratios) + "\n" if ratios else "")


def _per_setting(rows, sel) -> tuple[np.ndarray, np.ndarray]:
    settings: dict[tuple, list] = {}
    for r, s in zip(rows, sel):
        if s:
            settings.setdefault((r.level, r.tolerance if r.tolerance == r.tolerance else -1.0), []).append(r)
    err = np.array([max(r.error_reference_mm for r in v) for v in settings.values()], float)
    t = np.array([max(r.time_s for r in v) for v in settings.values()], float)
    return err, t


def report_trials(run_dirs: list[Path], out_dir: Path, partial: bool = False) -> ReportOutput:
    runs = [load_run(d, partial) for d in run_dirs]
    out_dir.mkdir(parents=True, exist_ok=True)
    panels = [(r.label, {t: d.errors for t, d in r.targets.items() if len(d.errors)}) for r in runs]
    panels = [p for p in panels if p[1]]
    files = []
    if panels:
        files.append(figures.save(figures.error_boxplots(panels), out_dir / "error_boxplots.png"))
    misses = [(f"{r.label}, {r.cups} cup(s)", {t: d.miss for t, d in r.targets.items() if d.miss is not None})
              for r in runs]
    if any(m for _, m in misses):
        from scissor_cli.output.miss_figures import miss_boxplots  # noqa: PLC0415

        files.append(figures.save(miss_boxplots([m for m in misses if m[1]]), out_dir / "miss_boxplots.png"))
    rows = summary_rows(runs)
    table = markdown_table(rows)
    (out_dir / "summary.md").write_text(table)
    write_csv(out_dir / "summary.csv", rows)
    files += [out_dir / "summary.md", out_dir / "summary.csv"]
    h5_files = [(r.label, _check_status(r.path, True)) for r in runs]
    files += report_models_figure(h5_files, out_dir)
    ins_files, ins_table = report_insertion(h5_files, out_dir)
    if ins_files:
        files += ins_files
        table += "\n" + ins_table
    sensor_files, sensor_table = report_sensors(h5_files, out_dir)
    if sensor_files:
        files += sensor_files
        table += "\nCamera against ultrasound:\n" + sensor_table
    budget_files, budget_table = report_budget(h5_files, out_dir)
    files += budget_files
    table += budget_table
    return ReportOutput(out_dir, files, table)
