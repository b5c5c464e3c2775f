"""The example scene's numbers do not change when code moves.

`tests/golden/example_seed7.npz` was recorded from `scissor simulate` on the
example scene with seed 7 (forward displacements, Jacobians, needle plans and
the 30 trials per target) before the package was restructured; see
`tests/golden/extract.py`. A change that is meant to change these numbers
re-records the file and says why in its commit.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from helpers import EXAMPLE

sys.path.insert(0, str(Path(__file__).parent / "golden"))
from extract import extract  # noqa: E402

GOLDEN = Path(__file__).parent / "golden" / "example_seed7.npz"


def test_example_scene_reproduces_the_golden_numbers(tmp_path):
    out = tmp_path / "run"
    subprocess.run(
        [sys.executable, "-m", "scissor_cli", "simulate", str(EXAMPLE), "--seed", "7", "--jobs", "2",
         "--out", str(out), "--quiet"],
        check=True, timeout=300,
    )
    now = extract(out / "results.h5")
    golden = dict(np.load(GOLDEN))
    assert sorted(now) == sorted(golden)
    worst = {k: float(np.max(np.abs(now[k] - golden[k]), initial=0.0)) for k in golden}
    bad = {k: v for k, v in worst.items() if not v <= 1e-9}
    assert not bad, f"changed beyond 1e-9: {bad}"
