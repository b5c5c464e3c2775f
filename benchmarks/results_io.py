"""The benchmarks' result files: benchmarks/results/<name>.json, what benchmarks/docs.py renders docs from.

Each script makes one `Results` when it starts and writes it when it ends:

    res = results_io.Results("bench_forward")          # the load average and the clock, now
    res.figure("newton_s", 0.033, "s")                   # one figure with its unit
    res.table("cases", rows, units={"newton_ms": "ms"})  # rows: list of dicts, units per column
    res.data("paths", {...})                             # other data a docs image is drawn from
    res.write()                                          # benchmarks/results/bench_forward.json

A file holds, beside the figures: the machine (CPU model from /proc/cpuinfo, core count), the 1-minute load
average when the script started and when it ended, the date (ISO, UTC), the commit (git rev-parse HEAD and
whether the tree had changes outside benchmarks/results and docs), the exact command line, the script's wall
time, the python / numpy versions, and the machine's speed when the script started and when it ended
(`speed_index_ms`: a shared VM's speed changes between hours, which a figure alone would not show). A run with
other than the default arguments that change what is measured names a variant:
benchmarks/results/<name>.<variant>.json, so it does not overwrite the figures the docs quote.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parent
ROOT = BENCHMARKS.parent
RESULTS_DIR = BENCHMARKS / "results"
#: changes here do not change what a benchmark measures
NOT_CODE = ("benchmarks/results/", "docs/")


def load1() -> float:
    """The 1-minute load average."""
    return round(os.getloadavg()[0], 2)


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


#: the speed index's kernel: the 7-point Laplacian on this many nodes a side, and products a timing
SPEED_INDEX_SIDE, SPEED_INDEX_PRODUCTS = 64, 20


def speed_index_ms(repeats: int = 7) -> float:
    """The machine's speed now: the median time (ms) of SPEED_INDEX_PRODUCTS products of a fixed sparse matrix (the
    7-point 3-D Laplacian, SPEED_INDEX_SIDE³ rows) with a vector, over `repeats` timings. scipy runs it on one
    thread and it is bound by memory, as a sparse solve or an element loop's gathers are: a neighbour loading the
    host or a throttled CPU shows here as in any figure taken beside it. Lower is faster."""
    import numpy as np  # noqa: PLC0415 (results_io itself needs neither)
    import scipy.sparse as sp  # noqa: PLC0415

    n = SPEED_INDEX_SIDE
    line = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    eye = sp.identity(n)
    A = (sp.kron(sp.kron(line, eye), eye) + sp.kron(sp.kron(eye, line), eye) + sp.kron(sp.kron(eye, eye), line)).tocsr()
    v = np.linspace(0.0, 1.0, A.shape[0])

    def products() -> None:
        for _ in range(SPEED_INDEX_PRODUCTS):
            A @ v

    products()  # (the first touch of the arrays)
    return round(1e3 * median_s(products, repeats), 2)


def machine() -> dict:
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "system": f"{platform.system()} {platform.release()}"}


def _git(*args: str) -> str:
    try:
        r = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=30, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return r.stdout if r.returncode == 0 else ""


def commit() -> dict:
    changed = [line[3:] for line in _git("status", "--porcelain", "--untracked-files=no").splitlines() if line]
    code = [p for p in changed if not p.startswith(NOT_CODE)]
    return {"head": _git("rev-parse", "HEAD").strip() or None, "dirty": bool(code), "changed_files": code[:20]}


def versions() -> dict:
    out = {"python": platform.python_version()}
    for module in ("numpy", "scipy"):
        mod = sys.modules.get(module)
        if mod is None:
            try:
                mod = __import__(module)
            except ImportError:
                continue
        out[module] = getattr(mod, "__version__", None)
    return out


def command_line() -> str:
    """The command as run, with the interpreter's name as typed (python3) and the script relative to the repo."""
    argv = list(sys.argv)
    try:
        argv[0] = str(Path(argv[0]).resolve().relative_to(ROOT))
    except ValueError:
        pass
    return " ".join(shlex.quote(a) for a in ["python3", *argv])


def subprocess_env() -> dict:
    """The environment for a `python3 -m scissor_cli` child: this checkout first on PYTHONPATH."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]])
    return env


def clean(value):
    """JSON-able: numpy scalars and arrays to Python, NaN and inf to None, tuples to lists."""
    if isinstance(value, dict):
        return {str(k): clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return clean(value.tolist())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (bytes, bytearray)):
        return value.decode()
    if isinstance(value, Path):
        return str(value)
    return value


class Results:
    """One benchmark run's figures and the facts a reader needs to judge them; `write` saves the JSON."""

    def __init__(self, name: str, variant: str | None = None):
        self.name = name
        self.variant = variant
        self.started = time.perf_counter()
        self.record = {
            "benchmark": name, "variant": variant, "command": command_line(),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": machine(), "load1_before": load1(), "speed_index_ms_before": speed_index_ms(),
            "commit": commit(), "versions": versions(), "figures": {}, "tables": {}, "data": {},
        }

    @property
    def path(self) -> Path:
        return RESULTS_DIR / (f"{self.name}.{self.variant}.json" if self.variant else f"{self.name}.json")

    def figure(self, key: str, value, unit: str, **note) -> None:
        """One figure: its value and unit (and optional context, e.g. load=..., repeats=...)."""
        self.record["figures"][key] = {"value": clean(value), "unit": unit, **clean(note)}

    def table(self, key: str, rows: list[dict], units: dict[str, str] | None = None) -> None:
        """A table: rows of {column: value}; units per column (a column without one is a count, a name or a ratio)."""
        self.record["tables"][key] = {"units": dict(units or {}), "rows": clean(rows)}

    def data(self, key: str, value) -> None:
        """Other data (what a docs image is drawn from)."""
        self.record["data"][key] = clean(value)

    def write(self) -> Path:
        self.record["load1_after"] = load1()
        self.record["speed_index_ms_after"] = speed_index_ms()
        self.record["wall_s"] = round(time.perf_counter() - self.started, 2)
        RESULTS_DIR.mkdir(parents=True, exist_ok=True)
        self.path.write_text(json.dumps(self.record, indent=1, allow_nan=False) + "\n")
        print(f"results: {self.path.relative_to(ROOT)}", file=sys.stderr)
        return self.path


def median_s(call, repeats: int = 5) -> float:
    """The median wall time (s) of `call()` over `repeats` calls: what a benchmark quotes of a repeated step."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return float(statistics.median(times))


def read(name: str) -> dict:
    """benchmarks/results/<name>.json (name may carry a variant: 'bench_slab.quick')."""
    return json.loads((RESULTS_DIR / f"{name}.json").read_text())
