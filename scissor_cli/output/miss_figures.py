"""The miss across the needle (docs/model.md §6) in `scissor report`: box plots of runs side by side.

One panel per target, one box per run (e.g. one cup against two): the
final miss of every finished trial, `/trials/<target>/manipulation_miss_mm`.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure


def miss_boxplots(runs: list[tuple[str, dict[str, np.ndarray]]], tolerance_mm: float = 0.1) -> Figure:
    """runs: (label, {target: miss (T,) mm}); the targets of all runs, each a panel with one box per run."""
    targets = sorted({t for _, d in runs for t in d})
    fig = Figure(figsize=(max(4.0, 2.2 * len(runs)) * max(1, len(targets)) / 1.5, 3.8))
    axes = np.atleast_1d(fig.subplots(1, max(1, len(targets)), squeeze=False)[0])
    for ax, t in zip(axes, targets):
        data = [(label, d[t]) for label, d in runs if t in d and len(d[t])]
        if data:
            # a run's label is "name (profile), N cup(s)": one line each, so long names stay inside the panel
            ax.boxplot([v for _, v in data],
                       tick_labels=[lab.replace(" (", "\n(").replace(", ", "\n") for lab, _ in data])
        ax.axhline(tolerance_mm, color="tab:red", ls="--", lw=1, label=f"{tolerance_mm:g} mm")
        ax.set_title(f"{t}: miss across the needle")
        ax.set_ylabel("miss (mm)")
        ax.tick_params(axis="x", labelsize=7)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig
