"""The error budget's figure: p95 miss per error source and target, and the simulated maxima beside the paper's."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from scissor_cli.output.error_budget.results import PAPER_MAX_MM, PAPER_PROFILES


def budget_figure(title: str, rows: list[dict], profile: str) -> Figure:
    """Left: bars of the p95 miss (mm) per source, one bar per target. Right: max |x|, |y| of `all` and the paper's.

    rows: `budget_results.budget_rows` output.
    """
    sources = list(dict.fromkeys(r["source"] for r in rows))
    targets = list(dict.fromkeys(r["target"] for r in rows))
    p95 = {(r["source"], r["target"]): r["miss_p95_mm"] for r in rows}
    fig = Figure(figsize=(11, 4.2))
    ax, ax_paper = fig.subplots(1, 2, gridspec_kw={"width_ratios": [3, 1]})
    width = 0.8 / max(len(targets), 1)
    at = np.arange(len(sources))
    for k, target in enumerate(targets):
        ax.bar(at + (k - (len(targets) - 1) / 2) * width, [p95.get((s, target), 0.0) for s in sources], width,
               label=target)
    ax.set_xticks(at)
    ax.set_xticklabels(sources, rotation=30, ha="right")
    ax.set_ylabel("p95 miss across the needle (mm)")
    ax.set_title(f"{title}: one error source at a time ({profile})")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    simulated = [max((r[f"{axis}_max_mm"] for r in rows if r["source"] == "all"), default=0.0) for axis in ("x", "y")]
    paper = PAPER_MAX_MM[PAPER_PROFILES.index(profile)] if profile in PAPER_PROFILES else None
    ax_paper.bar([0 - 0.2, 1 - 0.2], simulated, 0.4, label="simulated (all)")
    if paper is not None:
        ax_paper.bar([0 + 0.2, 1 + 0.2], paper, 0.4, label="paper, Fig. 14")
    ax_paper.set_xticks([0, 1])
    ax_paper.set_xticklabels(["max |x|", "max |y|"])
    ax_paper.set_ylabel("mm")
    ax_paper.set_title("maxima over targets")
    ax_paper.legend(fontsize=8)
    return fig
