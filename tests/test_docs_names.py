"""The code names and file paths the documentation gives resolve: README.md and every docs/*.md.

What counts, precisely:

* A *span* is inline code, the text between a pair of backticks on one line.
  Fenced code blocks (```) are left out for names (they hold YAML, shell and
  Python text) but read for paths.
* A *code name* is a span that, with a trailing call `(...)` dropped, is a
  dotted identifier `a.b[.c...]` whose first component is `scissor_cli` or
  one of its top-level modules or packages (`solvers`, `mesh`, `runtime`, ...),
  or one of the classes scissor_cli defines (`Tissue`, `RobotModel`, ...).
  It resolves when importing `scissor_cli.<the longest importable prefix>`
  and getattr-ing the rest succeeds; a class-first name resolves when the
  rest is an attribute of some scissor_cli class of that name.
* Config field paths are not code: a dotted span that walks the fields of
  the scene's config from the root or from any of its sections
  (`robot.voxel_mm`, `insertion.step_mm`, `tissue.mesh.file`, `mesh.scale`:
  through the pydantic models of `scissor_cli.config.Config`) is skipped even
  when its first component is also a package name (`robot`, `insertion`,
  `mesh`). So are file names, spans whose last component is a file
  extension (`cli.py`, `mesh.EXT`, see EXTENSIONS). Spans whose first
  component is neither a module nor a class (`trials.truth`, `np.linalg`)
  are not names of this package and are skipped too.
* A *path* is any whitespace-separated word of a span or a fenced block that
  ends in `.py` (a `::test` suffix dropped) and holds only path characters; it
  resolves when it exists relative to the repository root, scissor_cli/ or
  the document's folder. A bare file name (no folder: `transducer.py` in a
  list of a package's modules) resolves when a file of that name exists in
  scissor_cli/, tests/ or benchmarks/. Globs and placeholders (`*`, `<...>`)
  are skipped.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import re
import typing
from functools import lru_cache
from pathlib import Path

import pytest

import scissor_cli
from scissor_cli.config import Config

from helpers import ROOT

DOCS = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))
PACKAGE = ROOT / "scissor_cli"

FENCE = re.compile(r"^```.*?^```", re.M | re.S)
SPAN = re.compile(r"`([^`\n]+)`")
DOTTED = re.compile(r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+")
PATH = re.compile(r"[\w./-]+\.py")
#: a dotted span ending in one of these is a file name, not code
EXTENSIONS = {"py", "h5", "yaml", "yml", "png", "gif", "csv", "md", "npz", "vtu", "xdmf", "txt", "json", "tmp", "toml",
              "journal", "EXT"}


def spans(markdown: str) -> tuple[list[str], list[str]]:
    """(inline code spans outside fenced blocks, the fenced blocks' text)."""
    fences = FENCE.findall(markdown)
    return SPAN.findall(FENCE.sub("", markdown)), fences


def code_names(markdown: str, first_components: set[str]) -> list[str]:
    """The dotted code names of the markdown's inline spans whose first component is one of first_components."""
    names = []
    for span in spans(markdown)[0]:
        text = re.sub(r"\(.*\)$", "", span.strip())
        if DOTTED.fullmatch(text) and text.split(".")[0] in first_components and text.split(".")[-1] not in EXTENSIONS:
            names.append(text)
    return names


def py_paths(markdown: str) -> list[str]:
    """Every path-like word ending .py in the markdown's inline spans and fenced blocks."""
    inline, fences = spans(markdown)
    words = [w for text in inline + fences for w in text.split()]
    out = []
    for word in words:
        word = word.split("::")[0].strip("()[],;:'\"")
        if word.endswith(".py") and PATH.fullmatch(word) and not {"*", "<"} & set(word):
            out.append(word)
    return out


@lru_cache(maxsize=1)
def top_level() -> set[str]:
    """scissor_cli and its top-level modules and packages."""
    return {"scissor_cli"} | {m.name for m in pkgutil.iter_modules(scissor_cli.__path__) if m.name != "__main__"}


@lru_cache(maxsize=1)
def classes() -> dict[str, list[type]]:
    """Every class defined in a scissor_cli module, by name."""
    found: dict[str, list[type]] = {}
    for m in pkgutil.walk_packages(scissor_cli.__path__, "scissor_cli."):
        if m.name.endswith("__main__"):
            continue
        module = importlib.import_module(m.name)
        for name, obj in vars(module).items():
            if inspect.isclass(obj) and obj.__module__ == m.name and obj not in found.get(name, []):
                found.setdefault(name, []).append(obj)
    return found


def _fields(model) -> dict:
    fields = getattr(model, "model_fields", None)
    return fields if isinstance(fields, dict) else {}


def _models(annotation) -> list:
    """The pydantic models an annotation holds (through Optional, list, dict, Annotated)."""
    if _fields(annotation):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models(arg)]


@lru_cache(maxsize=1)
def config_models() -> list:
    """Config and every section model reachable from it."""
    found, todo = [], [Config]
    while todo:
        model = todo.pop()
        if model not in found:
            found.append(model)
            todo += [m for f in _fields(model).values() for m in _models(f.annotation)]
    return found


def is_config_field(dotted: str) -> bool:
    """Whether dotted ('robot.voxel_mm', 'tissue.mesh.file', 'mesh.scale') walks fields of the config's models."""
    for start in config_models():
        models = [start]
        for part in dotted.split("."):
            field = next((_fields(m)[part] for m in models if part in _fields(m)), None)
            if field is None:
                break
            models = _models(field.annotation)
        else:
            return True
    return False


def resolves(name: str) -> bool:
    """Whether a code name (see the module doc) names something that exists."""
    parts = name.split(".")
    if parts[0] in classes():
        return any(_getattr_chain(cls, parts[1:]) for cls in classes()[parts[0]])
    parts = parts if parts[0] == "scissor_cli" else ["scissor_cli"] + parts
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ModuleNotFoundError:
            continue
        return _getattr_chain(obj, parts[k:])
    return False


def _getattr_chain(obj, attrs: list[str]) -> bool:
    for a in attrs:
        if not hasattr(obj, a):
            fields = getattr(obj, "__dataclass_fields__", None) or _fields(obj)
            if a not in fields:  # a dataclass's or a model's field without a class-level default
                return False
            return a == attrs[-1]
        obj = getattr(obj, a)
    return True


def path_exists(path: str, doc: Path) -> bool:
    if "/" not in path:
        return any(next((ROOT / folder).rglob(path), None) for folder in ("scissor_cli", "tests", "benchmarks"))
    return any((base / path).exists() for base in (ROOT, PACKAGE, doc.parent))


# -- the extractor and the resolver on small cases ------------------------------------------------------------------


def test_extractor_finds_the_names_and_paths_it_should():
    doc = """A solve goes through `solvers.equilibrium.solve_equilibrium(tissue, s)`; see `mesh/mesh.py`,
`tests/test_layers.py::test_no_import_cycles`, `trials.truth`, `np.linalg.norm`, `mesh.Mesh.nope`, `cli.py`.
Run `python3 benchmarks/bench_none.py --quick`; not a path: `tests/test_*.py`, `<name>.py`.

```
python3 benchmarks/bench_fenced.py
solvers.not_a_name_in_a_fence
```
"""
    assert code_names(doc, top_level() | set(classes())) == ["solvers.equilibrium.solve_equilibrium",
                                                              "mesh.Mesh.nope"]
    assert py_paths(doc) == ["mesh/mesh.py", "tests/test_layers.py", "cli.py", "benchmarks/bench_none.py",
                             "benchmarks/bench_fenced.py"]


def test_resolver_tells_real_names_from_broken_ones():
    assert resolves("solvers.equilibrium.solve_equilibrium") and resolves("mesh.mesh.Mesh.n_elements")
    assert resolves("scissor_cli.runtime.configure") and resolves("solvers.equilibrium")
    assert resolves("Tissue.max_feasible_step")
    assert not resolves("solvers.equilibrium.solve_it") and not resolves("mesh.Mesh.nope")
    assert not resolves("solvers.nowhere.f") and not resolves("Tissue.nope")
    assert is_config_field("robot.voxel_mm") and is_config_field("tissue.mesh.file")
    assert is_config_field("insertion.step_mm") and not is_config_field("robot.chain.RobotModel")
    assert is_config_field("mesh.scale") and not is_config_field("mesh.mesh")
    doc = ROOT / "docs" / "model.md"
    assert path_exists("mechanics/fem.py", doc) and path_exists("transducer.py", doc)
    assert not path_exists("mechanics/nope.py", doc) and not path_exists("nope.py", doc)


# -- the documents ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_code_names_resolve(doc):
    names = code_names(doc.read_text(), top_level() | set(classes()))
    broken = sorted({n for n in names if not is_config_field(n) and not resolves(n)})
    assert not broken, f"{doc.relative_to(ROOT)} names code that does not exist: {broken}"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_py_paths_exist(doc):
    missing = sorted({p for p in py_paths(doc.read_text()) if not path_exists(p, doc)})
    assert not missing, f"{doc.relative_to(ROOT)} names files that do not exist: {missing}"
