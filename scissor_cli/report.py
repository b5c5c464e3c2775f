"""`scissor report`: combine runs into box plots and summary tables.

Reads one or more run directories (their results.h5), writes the error box
plots of all runs together, a per-target summary table as Markdown and CSV,
and returns the table for printing.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from . import figures


class ReportError(ValueError):
    """A run cannot be reported (missing, incomplete, or without trials)."""


@dataclass
class TargetTrials:
    errors: np.ndarray  # (T, 2) mm, finished trials only
    iterations: np.ndarray  # (T,)
    time_s: np.ndarray  # (T,)
    corridor_clear: np.ndarray  # (T,) bool


@dataclass
class RunTrials:
    label: str
    path: Path
    status: str
    targets: dict[str, TargetTrials]


def load_run(run_dir: Path, partial: bool = False) -> RunTrials:
    path = Path(run_dir) / "results.h5"
    if not path.is_file():
        raise ReportError(f"{run_dir}: no results.h5 (is this a scissor run directory?)")
    with h5py.File(path, "r") as f:
        status = str(f.attrs.get("status", "unknown"))
        if status != "complete" and not partial:
            reason = f.attrs.get("failure", "")
            raise ReportError(
                f"{path}: status is {status!r}, not 'complete'"
                + (f" ({reason})" if reason else "")
                + "; finish it with 'scissor simulate --resume' or pass --partial"
            )
        if "trials" not in f:
            raise ReportError(f"{path}: the run has no trials (it was run with --trials 0)")
        profile = f["trials"].attrs.get("profile", "")
        name = _config_name(f.attrs.get("config_yaml", ""))
        targets = {}
        for t, g in f["trials"].items():
            ok = g["done"][:] & ~g["failed"][:] & np.isfinite(g["final_error"][:]).all(axis=1)
            targets[t] = TargetTrials(g["final_error"][:][ok], g["iterations"][:][ok], g["time_s"][:][ok],
                                      g["corridor_clear"][:][ok])
    return RunTrials(f"{name} ({profile})", Path(run_dir), status, targets)


def _config_name(text: str) -> str:
    for line in text.splitlines():
        if line.startswith("name:"):
            return line.split(":", 1)[1].strip()
    return "run"


COLUMNS = [
    "run", "target", "trials", "mean_x", "median_x", "max_x", "p95_x", "mean_y", "median_y", "max_y", "p95_y",
    "iterations_mean", "iterations_max", "time_s_mean", "corridor_clear_pct",
]


def summary_rows(runs: list[RunTrials]) -> list[dict]:
    """One row per run and target: statistics of |x| and |y| error (mm), iterations, time."""
    rows = []
    for run in runs:
        for t, d in run.targets.items():
            row = {"run": run.label, "target": t, "trials": len(d.errors)}
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
            rows.append(row)
    return rows


def _fmt(v) -> str:
    if isinstance(v, (float, np.floating)):
        return f"{v:.3f}"
    return str(v)


def markdown_table(rows: list[dict], columns: list[str] = COLUMNS) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c, "")) for c in columns) + " |")
    return "\n".join(lines) + "\n"


def write_csv(path: Path, rows: list[dict], columns: list[str] = COLUMNS) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({c: _fmt(r[c]) if c in r else "" for c in columns})


@dataclass
class ReportOutput:
    out_dir: Path
    files: list[Path]
    table_markdown: str


def report_trials(run_dirs: list[Path], out_dir: Path, partial: bool = False) -> ReportOutput:
    runs = [load_run(d, partial) for d in run_dirs]
    out_dir.mkdir(parents=True, exist_ok=True)
    panels = [(r.label, {t: d.errors for t, d in r.targets.items() if len(d.errors)}) for r in runs]
    panels = [p for p in panels if p[1]]
    files = []
    if panels:
        files.append(figures.save(figures.error_boxplots(panels), out_dir / "error_boxplots.png"))
    rows = summary_rows(runs)
    table = markdown_table(rows)
    (out_dir / "summary.md").write_text(table)
    write_csv(out_dir / "summary.csv", rows)
    files += [out_dir / "summary.md", out_dir / "summary.csv"]
    return ReportOutput(out_dir, files, table)
