"""The cache beside the runs, `<run's parent>/.scissor-cache/`: what a run may reuse from an earlier one.

Fitted controller models, the slab grading a `layer_check.accuracy_mm`
chose and the nominal slab's starts live there, each file named by a key
that hashes what it depends on (`key`) and written whole (`write_whole`):
a killed run leaves no half-written file for the next one to read.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Callable, Optional

from scissor_cli import __version__

CACHE_DIR = ".scissor-cache"
#: what the cached files mean, beside the code's version: raised when that changes between versions (2: a body's
#: lesion became its region's mean; 3: the slab's cups grip by area, docs/model.md §21), so a cache written
#: before is not read as today's
REVISION = 3


def cache_dir(location: Optional[Path]) -> Optional[Path]:
    """The cache beside a run directory (None: no run directory)."""
    return None if location is None else Path(location).parent / CACHE_DIR


def key(parts: dict) -> str:
    """20 hex digits of the SHA-256 of `parts` (JSON-able), the code's version and the cache's `REVISION`."""
    parts = {**parts, "version": __version__, "revision": REVISION}
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:20]


def write_whole(path: Path, write: Callable[[Path], None]) -> None:
    """write(partial) to a file beside `path` (same suffix), then renamed onto it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f"{path.stem}.partial{path.suffix}")
    write(partial)
    partial.replace(path)
