"""`scissor report` for error budgets and the paper's table (docs/model.md §16).

* Every run with a `/budget`: one row per error source and target (|x|, |y|
  and miss: median, p95, max; the shares of the total variance and mean
  square), as
  `budget.md` / `budget.csv`.
* Every run with trials of a profile the paper measured: the simulated
  maxima of |x| (across the push) and |y| (along it) over all targets
  beside the paper's Fig. 14 (`paper_table.md` / `.csv`), with the run's
  truth (layer or slab) and the set-up of its slab (prone or free).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import yaml

from scissor_cli.output import tables
from scissor_cli.output.error_budget.results import PAPER_MAX_MM, PAPER_PROFILES, budget_rows, read_budget
from scissor_cli.output.results import finished_trials

BUDGET_COLUMNS = ["run", "source", "target", "trials", "x_median_mm", "x_p95_mm", "x_max_mm", "y_median_mm",
                  "y_p95_mm", "y_max_mm", "miss_median_mm", "miss_p95_mm", "miss_max_mm", "variance_share",
                  "mean_square_share"]
PAPER_COLUMNS = ["run", "profile", "truth", "set_up", "trials", "max_x_mm", "paper_max_x_mm", "max_y_mm",
                 "paper_max_y_mm", "stroke_limit_stops"]


def paper_row(label: str, h5: h5py.File) -> dict | None:
    """The run's maxima over every target's finished trials beside the paper's, or None (no such profile)."""
    if "trials" not in h5:
        return None
    profile = str(h5["trials"].attrs.get("profile", ""))
    if profile not in PAPER_PROFILES:
        return None
    cfg = yaml.safe_load(h5.attrs.get("config_yaml", "")) or {}
    truth = (cfg.get("trials") or {}).get("truth", "layer")
    lc = cfg.get("layer_check") or {}
    set_up = "-" if truth != "slab" else ("prone" if lc.get("chest_wall_fixed", True) and lc.get("cup_holds_z", True)
                                          else "vertical motion free")
    errors, stops = [], 0
    for g in h5["trials"].values():
        keep = finished_trials(g)
        errors.append(np.abs(g["final_error"][:][keep]))
        stops += int(np.sum(g["stop_reason"].asstr()[:][keep] == "stroke_limit"))
    e = np.concatenate(errors) if errors else np.zeros((0, 2))
    if not len(e):
        return None
    paper = PAPER_MAX_MM[PAPER_PROFILES.index(profile)]
    return {"run": label, "profile": profile, "truth": truth, "set_up": set_up, "trials": len(e),
            "max_x_mm": float(e[:, 0].max()), "paper_max_x_mm": float(paper[0]),
            "max_y_mm": float(e[:, 1].max()), "paper_max_y_mm": float(paper[1]), "stroke_limit_stops": stops}


def report_budget(runs: list[tuple[str, Path]], out_dir: Path) -> tuple[list[Path], str]:
    """Budget and paper tables of runs [(label, results.h5)]; (files written, Markdown to print)."""
    budget, paper = [], []
    for label, path in runs:
        with h5py.File(path, "r") as h5:
            budget += [{"run": label, **r} for r in budget_rows(read_budget(h5))]
            row = paper_row(label, h5)
            if row is not None:
                paper.append(row)
    files, text = [], ""
    for name, rows, columns, title in (("budget", budget, BUDGET_COLUMNS, "error budget: one source at a time"),
                                       ("paper_table", paper, PAPER_COLUMNS, "maxima against the paper's Fig. 14")):
        if not rows:
            continue
        if name == "budget" and any("z_max_mm" in r for r in rows):  # a body's: its vertical too
            at = columns.index("miss_median_mm")
            columns = columns[:at] + ["z_median_mm", "z_p95_mm", "z_max_mm"] + columns[at:]
            rows = [{"z_median_mm": "-", "z_p95_mm": "-", "z_max_mm": "-", **r} for r in rows]
        table = tables.markdown_table(rows, columns)
        (out_dir / f"{name}.md").write_text(table)
        tables.write_csv(out_dir / f"{name}.csv", rows, columns)
        files += [out_dir / f"{name}.md", out_dir / f"{name}.csv"]
        text += f"\n{title}\n\n{table}"
    return files, text
