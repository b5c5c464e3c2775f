"""What a `scissor simulate` run did, for the command to report: `RunSummary`."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from scissor_cli.solvers.common import SolveResult


@dataclass
class RunSummary:
    """A run's directory, mesh size, forward solves, figures, plans, trials run and status."""

    out_dir: Path
    n_elements: int
    forward: dict[str, SolveResult] = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)
    plans: list = field(default_factory=list)
    trials_run: int = 0
    status: str = "complete"
    failure: str = ""
