"""Shared test fixtures' building blocks: scenes as YAML text, small models."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
#: the normative example scene, as the package ships it (`scissor simulate` with no config runs it);
#: configs/example.yaml is the same file (test_config checks)
EXAMPLE = ROOT / "scissor_cli" / "scenes" / "example.yaml"


def example_dict() -> dict:
    return yaml.safe_load(EXAMPLE.read_text())


def write_scene(tmp_path: Path, data: dict, name: str = "scene.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def deep_update(data: dict, dotted: str, value) -> dict:
    """Set data[a][b]... for 'a.b...' (integers index lists) and return data."""
    keys = [int(k) if k.isdigit() else k for k in dotted.split(".")]
    node = data
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value
    return data


#: relative residuals below this are treated as round-off when judging a solver's rate: at the
#: example's sizes the floor is 1e-12..1e-9 and varies between CPUs (and a CG step may land on it
#: anywhere), so a rate is only read from steps that start 100x above its top
ROUNDOFF_FLOOR = 1e-7


def rates_above_roundoff(history) -> list[float]:
    """Residual ratios r[k+1]/r[k] of the steps that start above ROUNDOFF_FLOOR, in order."""
    return [b / a for a, b in zip(history[:-1], history[1:]) if a >= ROUNDOFF_FLOOR]


def benchmark_module(name: str):
    """benchmarks/NAME.py as a module: benchmarks/ is no package (registered in sys.modules, for its dataclasses)."""
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def simulate_here(directory: Path, data: dict, name: str = "run", jobs: int = 1) -> Path:
    """`scissor simulate` of the scene `data` (written to directory/NAME.yaml) into directory/NAME, through the
    Python API in this process (`api.simulate`: the CLI's own `api.run`, without the process's start-up, for the
    tests that read what a run stores rather than how the command behaves as a process); returns the run's
    directory."""
    from scissor_cli import api  # noqa: PLC0415

    out = Path(directory) / name
    api.simulate(api.load_config(write_scene(Path(directory), data, f"{name}.yaml")), out, jobs=jobs)
    return out


def cli_here(*args):
    """`scissor ARGS` run in this process (typer's CliRunner): for commands whose files a test reads, not its exit
    as a process (those tests start `python -m scissor_cli`). The result has exit_code, stdout and stderr."""
    from typer.testing import CliRunner  # noqa: PLC0415

    from scissor_cli.cli import app  # noqa: PLC0415

    return CliRunner().invoke(app, [str(a) for a in args])
