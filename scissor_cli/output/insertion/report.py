"""`scissor report` for runs with insertion (docs/contract.md): the final miss per strategy beside the
manipulation error.

For every run and target with `/trials/<target>/miss_mm`: box plots of the
manipulation error (|true − desired| at the end of the cup loop, the
paper's Fig. 14 quantity) and of the final miss at the needle per strategy,
and a table (median, 90th percentile and maximum; the median |depth error|).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
from matplotlib.figure import Figure

from scissor_cli.output.figures import save
from scissor_cli.output.results import finished_trials
from scissor_cli.text import cell


def load_insertion_trials(path: Path) -> dict[str, dict]:
    """{target: {"manipulation": (T,), "miss": {strategy: (T,)}, "depth_error": {strategy: (T,)}}} of finished
    trials."""
    out: dict[str, dict] = {}
    with h5py.File(path, "r") as f:
        if "trials" not in f:
            return out
        for t, g in f["trials"].items():
            if "miss_mm" not in g:
                continue
            ok = finished_trials(g)
            strategies = [s.decode() if isinstance(s, bytes) else str(s) for s in g["miss_mm"].attrs["strategies"]]
            miss, derr = g["miss_mm"][:][ok], g["depth_error_mm"][:][ok]
            out[t] = {
                "manipulation": np.linalg.norm(g["final_error"][:][ok], axis=1),
                "miss": {s: miss[:, i] for i, s in enumerate(strategies)},
                "depth_error": {s: derr[:, i] for i, s in enumerate(strategies)},
            }
    return out


def insertion_boxplots(panels: list[tuple[str, dict[str, dict]]]) -> Figure:
    """One axis per (run, target): manipulation error, then the miss per strategy (mm)."""
    cells = [(label, t, d) for label, targets in panels for t, d in targets.items()]
    fig = Figure(figsize=(max(4.0, 3.2 * len(cells)), 4.2))
    for i, (label, t, d) in enumerate(cells):
        ax = fig.add_subplot(1, len(cells), i + 1)
        data = [d["manipulation"]] + list(d["miss"].values())
        names = ["manipulation\n|error|"] + [f"miss\n{s}" for s in d["miss"]]
        ax.boxplot(data, showfliers=True)
        ax.set_xticks(range(1, len(names) + 1), names, fontsize=7)
        ax.set_title(f"{label}\n{t}", fontsize=8)
        ax.set_ylabel("mm")
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle("final miss at the needle per strategy beside the manipulation error", fontsize=9)
    return fig


def insertion_rows(panels: list[tuple[str, dict[str, dict]]]) -> list[dict]:
    rows = []
    for label, targets in panels:
        for t, d in targets.items():
            entries = [("manipulation", d["manipulation"], None)]
            entries += [(s, d["miss"][s], d["depth_error"][s]) for s in d["miss"]]
            for what, v, de in entries:
                v = np.asarray(v, float)
                rows.append({
                    "run": label, "target": t, "what": what if what == "manipulation" else f"miss ({what})",
                    "trials": int(v.size),
                    "median_mm": float(np.median(v)) if v.size else float("nan"),
                    "p90_mm": float(np.percentile(v, 90)) if v.size else float("nan"),
                    "max_mm": float(v.max()) if v.size else float("nan"),
                    "median_abs_depth_error_mm": (float(np.median(np.abs(de))) if de is not None and de.size
                                                  else float("nan")),
                })
    return rows


COLUMNS = ["run", "target", "what", "trials", "median_mm", "p90_mm", "max_mm", "median_abs_depth_error_mm"]


def report_insertion(runs: list[tuple[str, Path]], out_dir: Path) -> tuple[list[Path], str]:
    """insertion_boxplots.png and insertion_summary.md for the runs (label, results.h5) with insertion trials."""
    panels = [(label, d) for label, path in runs if (d := load_insertion_trials(path))]
    if not panels:
        return [], ""
    rows = insertion_rows(panels)
    table = "| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS) + "\n"
    table += "".join("| " + " | ".join(cell(r[c], missing="–") for c in COLUMNS) + " |\n" for r in rows)
    md = out_dir / "insertion_summary.md"
    md.write_text(table)
    return [save(insertion_boxplots(panels), out_dir / "insertion_boxplots.png"), md], table
