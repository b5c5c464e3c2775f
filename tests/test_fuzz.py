"""Any input: mutated scenes get exit 0 or 2 with one message, never a traceback, in bounded time.

Property-based (hypothesis): the example scene's values are replaced
(NaN, ±inf, ±1e308, 0, negatives, huge integers, strings, None, lists,
mappings), its keys deleted or joined by unknown ones, and its bytes flipped,
cut and salted with invalid UTF-8. `validate` must exit 0 or 2; a smaller set
of value mutations of a coarse copy runs `simulate --trials 0`, which may
also exit 1 (a genuine solver failure, with its reason). docs/contract.md
("Commands", "Config") is the contract these hold the program to.

The quick profile runs by default; the long one (>= 500 examples per
property) is marked `fuzz` and left out unless asked for:

    python3 -m pytest -m fuzz tests/test_fuzz.py
"""

from __future__ import annotations

import copy
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from scissor_cli.cli import app
from scissor_cli.config.messages import field_type

from helpers import EXAMPLE, deep_update, example_dict

#: seconds one `validate` may take in process (it takes ~0.02 s; the machine is shared)
VALIDATE_SECONDS = 5.0
#: seconds one coarse `simulate --trials 0` may take (~2 s; a mutated solver cap can add ~10 s)
SIMULATE_SECONDS = 120.0

LONG = dict(deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
#: the default run is the same examples every time; the long profile draws new ones
QUICK = dict(LONG, derandomize=True)

runner = CliRunner()

# --------------------------------------------------------------------------
# Strategies


def _paths(node, prefix=()):
    """Every path (tuple of keys/indices) into a YAML-like tree, containers included."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, prefix + (i,))
    return out


EXAMPLE_DATA = example_dict()
EXAMPLE_PATHS = _paths(EXAMPLE_DATA)

NASTY_FLOATS = [math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0, -0.0, -1.0, 5e-324, 1e-300, 0.5, 2.0, 1e6]
NASTY_INTS = [0, -1, 1, 2**31, 2**63, 2**64, 10**30, -(10**30), 10**400]

scalars = st.one_of(
    st.sampled_from(NASTY_FLOATS),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(NASTY_INTS),
    st.integers(min_value=-(10**20), max_value=10**20),
    st.booleans(),
    st.none(),
    st.text(max_size=12),
    st.sampled_from(["", "10", "nan", "cup", "T1", "left", "a/b", "$x$", "\x00", "\ud800", "é" * 3]),
)
values = st.one_of(
    scalars,
    st.lists(scalars, max_size=4),
    st.dictionaries(st.text(max_size=6), scalars, max_size=3),
    st.lists(st.lists(scalars, min_size=2, max_size=2), max_size=4),
)


@st.composite
def mutated_scene(draw, base=EXAMPLE_DATA, paths=EXAMPLE_PATHS, max_mutations=3):
    """The example's data with 1..max_mutations replaced values, deleted keys or unknown keys."""
    data = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, max_mutations))):
        path = draw(st.sampled_from(paths))
        parent = data
        try:
            for key in path[:-1]:
                parent = parent[key]
            if not isinstance(parent, (dict, list)):
                continue
            parent[path[-1]]
        except (KeyError, IndexError, TypeError):
            continue  # an earlier mutation removed or replaced this branch
        action = draw(st.sampled_from(["replace", "replace", "replace", "delete", "unknown"]))
        if action == "replace":
            parent[path[-1]] = draw(values)
        elif action == "delete" and isinstance(parent, dict):
            del parent[path[-1]]
        elif isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=8))] = draw(scalars)
    return data


def _bounds(path) -> tuple[float, float] | None:
    """The documented range of a numeric field of the config, or None."""
    tp, meta = field_type(tuple(path))
    if tp not in (float, int):
        return None
    lo = next((getattr(m, k) for m in meta for k in ("ge", "gt") if getattr(m, k, None) is not None), None)
    hi = next((getattr(m, k) for m in meta for k in ("le", "lt") if getattr(m, k, None) is not None), None)
    return (lo, hi) if lo is not None and hi is not None else None


@st.composite
def edge_of_range(draw, base, paths):
    """base with 1-2 numeric fields set to values at the edges of their documented ranges (valid or just not)."""
    data = copy.deepcopy(base)
    numeric = [p for p in paths if _bounds(p) is not None]
    for _ in range(draw(st.integers(1, 2))):
        path = draw(st.sampled_from(numeric))
        lo, hi = _bounds(path)
        parent = data
        for key in path[:-1]:
            parent = parent[key]
        old = parent[path[-1]]
        choice = draw(st.sampled_from([lo, hi, lo + (hi - lo) * 1e-9, hi - (hi - lo) * 1e-9, (lo + hi) / 2,
                                       old * 10 if isinstance(old, (int, float)) else hi,
                                       old / 10 if isinstance(old, (int, float)) else lo, -old if old else 1]))
        parent[path[-1]] = int(choice) if isinstance(old, int) and not isinstance(old, bool) else float(choice)
    return data


def _dump(data) -> str:
    # allow_unicode=False: the odd characters a strategy draws are written as YAML escapes
    return yaml.safe_dump(data, sort_keys=False)


EXAMPLE_BYTES = EXAMPLE.read_bytes()


@st.composite
def mutated_bytes(draw):
    """The example's bytes flipped, cut, or with invalid UTF-8, NUL or junk inserted."""
    data = bytearray(EXAMPLE_BYTES)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "truncate", "insert", "junk"]))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if kind == "flip" and data:
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif kind == "truncate":
            del data[at:]
        elif kind == "insert":
            data[at:at] = draw(st.sampled_from([b"\xff", b"\xc3", b"\xed\xa0\x80", b"\x00", b"\x80\x80", b"\xfe\xff",
                                                b"\t", b"\r", b"&a [*a]", b"*x", b"!!python/object:os.system ",
                                                b"[[[[[[[[", b"{", b": :", b"- ", b"\x1b[2J"]))
        else:
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
    return bytes(data)


# --------------------------------------------------------------------------
# What every run must satisfy


def _validate(path: Path):
    t0 = time.perf_counter()
    result = runner.invoke(app, ["validate", str(path)])
    return result, time.perf_counter() - t0


def _assert_clean(result, seconds: float, limit: float, path: Path, codes=(0, 2)) -> None:
    out = result.output
    assert result.exit_code in codes, (result.exit_code, out[-2000:], result.exception)
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in out
    assert seconds < limit, f"took {seconds:.1f} s"
    if result.exit_code == 2:
        message = result.stderr
        assert message.startswith(f"error: {path}"), message  # one message that names the file
        assert message.count("error:") == 1, message


def _check_validate(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "scene.yaml"
    path.write_bytes(content)
    result, seconds = _validate(path)
    _assert_clean(result, seconds, VALIDATE_SECONDS, path)


# --------------------------------------------------------------------------
# Quick profile (default run)


@settings(max_examples=120, **QUICK)  # (the long profile: 1500)
@given(data=mutated_scene())
def test_validate_mutated_values(tmp_path_factory, data):
    _check_validate(tmp_path_factory.mktemp("v"), _dump(data).encode())


@settings(max_examples=150, **QUICK)
@given(content=mutated_bytes())
def test_validate_mutated_bytes(tmp_path_factory, content):
    _check_validate(tmp_path_factory.mktemp("b"), content)


@settings(max_examples=60, **QUICK)
@given(content=st.binary(max_size=512))
def test_validate_random_bytes(tmp_path_factory, content):
    _check_validate(tmp_path_factory.mktemp("r"), content)


def _coarse_example() -> dict:
    """The example at edges 8/2 mm with Newton: a simulate in about two seconds."""
    data = example_dict()
    deep_update(data, "tissue.mesh.max_edge_mm", 8.0)
    deep_update(data, "tissue.mesh.min_edge_mm", 2.0)
    deep_update(data, "solver.kind", "newton")
    return data


COARSE = _coarse_example()
COARSE_PATHS = _paths(COARSE)


def _check_simulate(tmp_path: Path, data: dict, codes=(0, 1, 2)) -> None:
    path = tmp_path / "scene.yaml"
    path.write_text(_dump(data))
    t0 = time.perf_counter()
    result = runner.invoke(app, ["simulate", str(path), "--trials", "0", "--out", str(tmp_path / "out"), "--quiet"])
    seconds = time.perf_counter() - t0
    _assert_clean(result, seconds, SIMULATE_SECONDS, path, codes=codes)
    if result.exit_code == 1:  # a run-time failure: where the partial results are, then the reason
        reason = result.stderr.split("error: ", 1)
        assert len(reason) == 2 and reason[1].strip(), result.stderr
        assert "results so far:" in result.stderr and "(status = failed)" in result.stderr, result.stderr


@settings(max_examples=10, **QUICK)  # (each a run; the long profile: 200)
@given(data=st.one_of(mutated_scene(base=COARSE, paths=COARSE_PATHS, max_mutations=2),
                      edge_of_range(COARSE, COARSE_PATHS)))
def test_simulate_mutated_values(tmp_path_factory, data):
    _check_simulate(tmp_path_factory.mktemp("s"), data)


#: offsets (mm) that make two points coincide, nearly coincide, or sit just either side of the spacing allowed
NEAR_OFFSETS = [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.049, 0.05, 0.051, 0.3]


@st.composite
def coincident_points(draw, base=COARSE):
    """The scene with two of its points made (nearly) coincident: targets, a target on an obstacle's
    vertex or centre, a copied obstacle or cup shifted by a small offset."""
    data = copy.deepcopy(base)
    d = draw(st.sampled_from(NEAR_OFFSETS))
    angle = draw(st.sampled_from([0.0, 0.5 * math.pi, 0.25 * math.pi, math.pi]))
    dx, dy = d * math.cos(angle), d * math.sin(angle)
    kind = draw(st.sampled_from(["targets", "target-on-obstacle", "obstacle", "cup"]))
    if kind == "targets":
        x, y = data["targets"][0]["position_mm"]
        data["targets"][1]["position_mm"] = [x + dx, y + dy]
        data["targets"][1].pop("desired_mm", None)
    elif kind == "target-on-obstacle":
        obstacle = draw(st.sampled_from(data["obstacles"]))
        if "polygon_mm" in obstacle:
            x, y = draw(st.sampled_from(obstacle["polygon_mm"]))
        else:
            (x, y), r = obstacle["circle"]["center_mm"], obstacle["circle"]["radius_mm"]
            y += draw(st.sampled_from([0.0, r]))
        data["targets"][0]["position_mm"] = [x + dx, y + dy]
    elif kind == "obstacle":
        copy_of = copy.deepcopy(draw(st.sampled_from(data["obstacles"])))
        copy_of["name"] = "copy"
        if "polygon_mm" in copy_of:
            copy_of["polygon_mm"] = [[x + dx, y + dy] for x, y in copy_of["polygon_mm"]]
        else:
            x, y = copy_of["circle"]["center_mm"]
            copy_of["circle"]["center_mm"] = [x + dx, y + dy]
        data["obstacles"].append(copy_of)
    else:
        cup = copy.deepcopy(data["cups"][0])
        cup["name"] = "copy"
        x, y = cup["contact_mm"]
        cup["contact_mm"] = [x + d, y]  # along the top side
        data["cups"].append(cup)
    return data


@settings(max_examples=6, **QUICK)  # (each a run; the long profile: 150)
@given(data=coincident_points())
def test_simulate_coincident_points(tmp_path_factory, data):
    """Coincident or nearly coincident targets, obstacles and cups: the run works or is refused (exit 2)."""
    _check_simulate(tmp_path_factory.mktemp("c"), data, codes=(0, 2))


@settings(max_examples=100, **QUICK)  # (the long profile: 500)
@given(data=edge_of_range(EXAMPLE_DATA, EXAMPLE_PATHS))
def test_validate_edges_of_ranges(tmp_path_factory, data):
    _check_validate(tmp_path_factory.mktemp("e"), _dump(data).encode())


# --------------------------------------------------------------------------
# A few real processes: the console script's own exit codes and streams


def _run(*args, timeout=VALIDATE_SECONDS * 12):
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    return subprocess.run([sys.executable, "-m", "scissor_cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)


@pytest.mark.parametrize("content", [
    b"", b"\xff\xfe\x00\x00", b"tissue:\n  size_mm: [1e308, .nan]\n", b"- just\n- a list\n",
    b"a: &a [1, 2]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\nc: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\n"
    b"d: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c]\ne: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d]\n"
    b"f: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e]\ng: [*f, *f, *f, *f, *f, *f, *f, *f, *f]\n",
], ids=["empty", "utf16-bom", "nan", "list", "billion-laughs"])
def test_validate_subprocess(tmp_path, content):
    path = tmp_path / "scene.yaml"
    path.write_bytes(content)
    proc = _run("validate", path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith(f"error: {path}") and proc.stderr.count("error:") == 1


@pytest.mark.parametrize("args", [["--seed", str(2**70)], ["--trials", str(10**9)], ["--jobs", str(10**5)]],
                         ids=["seed", "trials", "jobs"])
def test_overrides_keep_to_the_config_ranges(tmp_path, args):
    """Command-line overrides bypass the config's validation, so they carry its ranges themselves."""
    path = tmp_path / "scene.yaml"
    path.write_text(_dump(COARSE))
    result = runner.invoke(app, ["simulate", str(path), "--out", str(tmp_path / "o"), "--quiet", *args])
    assert result.exit_code == 2 and args[0] in result.output and not (tmp_path / "o").exists()


@pytest.mark.parametrize("samples", [0, 10**11])
def test_workspace_samples_are_bounded(tmp_path, samples):
    """A sample count the machine cannot hold is refused before anything is allocated."""
    result = runner.invoke(app, ["workspace", "--samples", str(samples), "--out", str(tmp_path / "w"), "--quiet"])
    assert result.exit_code == 2 and "--samples" in result.output and not (tmp_path / "w").exists()


# --------------------------------------------------------------------------
# Long profile: python3 -m pytest -m fuzz tests/test_fuzz.py


@pytest.mark.fuzz
@settings(max_examples=1500, **LONG)
@given(data=mutated_scene(max_mutations=4))
def test_fuzz_validate_mutated_values(tmp_path_factory, data):
    _check_validate(tmp_path_factory.mktemp("v"), _dump(data).encode())


@pytest.mark.fuzz
@settings(max_examples=1000, **LONG)
@given(content=mutated_bytes())
def test_fuzz_validate_mutated_bytes(tmp_path_factory, content):
    _check_validate(tmp_path_factory.mktemp("b"), content)


@pytest.mark.fuzz
@settings(max_examples=500, **LONG)
@given(content=st.binary(max_size=4096))
def test_fuzz_validate_random_bytes(tmp_path_factory, content):
    _check_validate(tmp_path_factory.mktemp("r"), content)


@pytest.mark.fuzz
@settings(max_examples=500, **LONG)
@given(data=edge_of_range(EXAMPLE_DATA, EXAMPLE_PATHS))
def test_fuzz_validate_edges_of_ranges(tmp_path_factory, data):
    _check_validate(tmp_path_factory.mktemp("e"), _dump(data).encode())


@pytest.mark.fuzz
@settings(max_examples=200, **LONG)
@given(data=st.one_of(mutated_scene(base=COARSE, paths=COARSE_PATHS, max_mutations=2),
                      edge_of_range(COARSE, COARSE_PATHS)))
def test_fuzz_simulate_mutated_values(tmp_path_factory, data):
    _check_simulate(tmp_path_factory.mktemp("s"), data)


@pytest.mark.fuzz
@settings(max_examples=150, **LONG)
@given(data=coincident_points())
def test_fuzz_simulate_coincident_points(tmp_path_factory, data):
    _check_simulate(tmp_path_factory.mktemp("c"), data, codes=(0, 2))


# --------------------------------------------------------------------------
# A 3-D scene (docs/model.md §19): the normative dome's values mutated


DOME_DATA = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs" / "example_dome.yaml").read_text())
DOME_PATHS = _paths(DOME_DATA)


@settings(max_examples=120, **QUICK)
@given(data=mutated_scene(base=DOME_DATA, paths=DOME_PATHS))
def test_validate_mutated_dome(tmp_path_factory, data):
    _check_validate(tmp_path_factory.mktemp("d"), _dump(data).encode())


#: the paper's dome with the paper's layer as the controller's model (`config.body_section`): each target's section
LAYER_DOME_DATA = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs" /
                                  "paper_trials_prosthesis_dome.yaml").read_text())
LAYER_DOME_DATA["controller"]["model"] = "layer"
LAYER_DOME_DATA["controller"]["section_fixed"] = ["bottom"]
LAYER_DOME_PATHS = _paths(LAYER_DOME_DATA)


@settings(max_examples=40, **QUICK)
@given(data=mutated_scene(base=LAYER_DOME_DATA, paths=LAYER_DOME_PATHS))
def test_validate_mutated_layer_dome(tmp_path_factory, data):
    _check_validate(tmp_path_factory.mktemp("ld"), _dump(data).encode())


def _coarse_dome() -> dict:
    """The dome at edges 10/4 mm, one lesion, no trials: a simulate in a few seconds."""
    data = copy.deepcopy(DOME_DATA)
    data["tissue"]["mesh"] = {"max_edge_mm": 10.0, "min_edge_mm": 4.0}
    data["trials"] = {"count": 0}
    return data


COARSE_DOME = _coarse_dome()
COARSE_DOME_PATHS = _paths(COARSE_DOME)


@settings(max_examples=3, **QUICK)  # (each a dome's run: `-m fuzz`'s long profile draws 40)
@given(data=mutated_scene(base=COARSE_DOME, paths=COARSE_DOME_PATHS, max_mutations=2))
def test_simulate_mutated_dome(tmp_path_factory, data):
    _check_simulate(tmp_path_factory.mktemp("ds"), data)


@pytest.mark.fuzz
@settings(max_examples=40, **LONG)
@given(data=mutated_scene(base=COARSE_DOME, paths=COARSE_DOME_PATHS, max_mutations=2))
def test_fuzz_simulate_mutated_dome(tmp_path_factory, data):
    _check_simulate(tmp_path_factory.mktemp("ds"), data)
