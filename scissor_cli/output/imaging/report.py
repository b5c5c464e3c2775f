"""`scissor report` across sensors (docs/contract.md#report): the camera's runs beside the ultrasound's.

A run whose results.h5 has /imaging saw its target by ultrasound, any other
by the camera (`results.sensor_of`). When the reported runs hold both,
sensors.md has one row per run, target and quantity:

* `manipulation miss`: the true target's distance across the plan's needle
  axis after the loop (`/trials/<target>/manipulation_miss_mm`);
* `needle miss (<strategy>)`: with insertion, the final miss at the needle
  per strategy (`/trials/<target>/miss_mm`);
* `sensor error`: |measured − true| at every control step of the trials
  (their histories' `measured_x/_y` and `true_x/_y`): what the sensor got
  wrong, before the loop's control.

Each with the number of values, their median, 95th percentile and maximum (mm).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from scissor_cli.output import tables
from scissor_cli.output.imaging.results import sensor_of
from scissor_cli.output.insertion.report import load_insertion_trials
from scissor_cli.output.results import finished_trials

COLUMNS = ["run", "sensor", "target", "what", "count", "median_mm", "p95_mm", "max_mm"]


def _stats(values) -> dict:
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v)]
    if not v.size:
        return {"count": 0}
    return {"count": int(v.size), "median_mm": float(np.median(v)), "p95_mm": float(np.percentile(v, 95)),
            "max_mm": float(v.max())}


def sensor_errors(g: h5py.Group) -> np.ndarray:
    """|measured − true| (S,) mm at every control step of a target's finished trials (empty without histories)."""
    if "history" not in g:
        return np.zeros(0)
    out = []
    for k in np.flatnonzero(finished_trials(g)):
        if str(k) not in g["history"]:
            continue
        h = g["history"][str(k)]
        columns = [str(c) for c in h.attrs["columns"]]
        if not {"measured_x", "measured_y", "true_x", "true_y"} <= set(columns):
            continue
        table = h[()]
        col = {c: j for j, c in enumerate(columns)}
        out.append(np.hypot(table[:, col["measured_x"]] - table[:, col["true_x"]],
                            table[:, col["measured_y"]] - table[:, col["true_y"]]))
    return np.concatenate(out) if out else np.zeros(0)


def sensor_rows(label: str, path: Path) -> list[dict]:
    """The rows of one run (its label, its results.h5) in target order."""
    rows = []
    needle = load_insertion_trials(path)
    with h5py.File(path, "r") as f:
        sensor = sensor_of(f)
        for t, g in f.get("trials", {}).items():
            ok = finished_trials(g)
            head = {"run": label, "sensor": sensor, "target": t}
            if "manipulation_miss_mm" in g:
                rows.append(head | {"what": "manipulation miss"} | _stats(g["manipulation_miss_mm"][:][ok]))
            for strategy, miss in needle.get(t, {}).get("miss", {}).items():
                rows.append(head | {"what": f"needle miss ({strategy})"} | _stats(miss))
            rows.append(head | {"what": "sensor error"} | _stats(sensor_errors(g)))
    return rows


def report_sensors(runs: list[tuple[str, Path]], out_dir: Path) -> tuple[list[Path], str]:
    """sensors.md for runs (label, results.h5) when they hold both sensors; ([], "") otherwise."""
    sensors = set()
    for _, path in runs:
        with h5py.File(path, "r") as f:
            sensors.add(sensor_of(f))
    if len(sensors) < 2:
        return [], ""
    rows = [r for label, path in runs for r in sensor_rows(label, path)]
    table = tables.markdown_table(rows, COLUMNS)
    md = Path(out_dir) / "sensors.md"
    md.write_text(table)
    return [md], table
