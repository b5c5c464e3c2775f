"""Numbers as the messages and tables print them: one definition of each format."""

from __future__ import annotations

import numpy as np


def signed(values, digits: int = 2) -> str:
    """Values as '+1.00, -2.50' (a stroke vector, mm)."""
    return ", ".join(f"{v:+.{digits}f}" for v in np.atleast_1d(values))


def vector(values, digits: int = 2) -> str:
    """Values as '(+1.00, -2.50)'."""
    return f"({signed(values, digits)})"


def ranges(lo, hi) -> str:
    """Paired limits as '[-15.00, +15.00], [+0.00, +10.00]' (stroke ranges, mm)."""
    return ", ".join(f"[{a:+.2f}, {b:+.2f}]" for a, b in zip(np.atleast_1d(lo), np.atleast_1d(hi)))


def cell(value, missing: str | None = None) -> str:
    """A table cell: floats to three decimals (a non-finite one as `missing` when given), anything else as it is."""
    if isinstance(value, (float, np.floating)):
        if missing is not None and not np.isfinite(value):
            return missing
        return f"{value:.3f}"
    return str(value)


def duration(seconds: float) -> str:
    """A wall time for a person: '4.2 s', '37 s', '12 min', '1.5 h'."""
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
