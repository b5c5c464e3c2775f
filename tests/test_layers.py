"""The package's layers: data flows one way, and no module imports a later layer or forms a cycle.

Order (docs/architecture.md): the base modules (`geometry`, `geometry3d`, `runtime`,
`progress`, `text`, the package root), then config → scene → mesh → mechanics → solvers → robot →
planning → sensing → control → insertion → layer3d → experiments → output → cli. A
module may import from its own package and from any earlier layer; the test
reads every `import` statement (including those inside functions) with `ast`.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "scissor_cli"
LAYERS = [
    "", "geometry", "geometry3d", "runtime", "progress", "text", "config", "scene", "mesh", "mechanics", "solvers",
    "robot", "planning", "sensing", "control", "insertion", "layer3d", "experiments", "output", "api", "gym", "cli",
    "__main__",
]
RANK = {name: i for i, name in enumerate(LAYERS)}
BASE = {"", "geometry", "geometry3d", "runtime", "progress", "text"}  # importable from everywhere


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "scissor_cli"}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "scissor_cli":
                continue
            # `from scissor_cli.pkg import module` names a module, not a value
            for a in node.names:
                sub = f"{mod}.{a.name}"
                found.add(sub if (PACKAGE.parent / (sub.replace(".", "/") + ".py")).exists()
                          or (PACKAGE.parent / sub.replace(".", "/")).is_dir() else mod)
    return found


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def test_every_package_is_a_known_layer():
    unknown = {_layer(m) for m in MODULES} - set(RANK)
    assert not unknown, f"packages without a place in LAYERS: {unknown}"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_only_from_earlier_layers(module):
    mine = _layer(module)
    bad = []
    for imported in _imports(MODULES[module]):
        theirs = _layer(imported)
        if theirs == mine or theirs in BASE:
            continue
        if RANK[theirs] > RANK[mine]:
            bad.append(f"{imported} (layer {theirs!r} comes after {mine!r})")
    assert not bad, f"{module} imports from later layers: {bad}"


def test_no_import_cycles():
    graph = {m: {i for i in _imports(p) if i in MODULES and i != m} for m, p in MODULES.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(n):] + [n]))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_no_module_over_500_lines():
    big = {m: n for m, p in MODULES.items() if (n := len(p.read_text().splitlines())) > 500}
    assert not big, f"modules over 500 lines (one concern each): {big}"


def test_importing_has_no_process_side_effects():
    """Importing every module leaves the BLAS thread pools as the libraries set them (the CLI sets them)."""
    import os
    import subprocess
    import sys

    code = (
        "import numpy, scipy.sparse, cvxopt, cvxopt.cholmod, qdldl, h5py, matplotlib\n"
        "from threadpoolctl import threadpool_info\n"
        "before = {i['filepath']: i['num_threads'] for i in threadpool_info()}\n"
        "import importlib\n"
        f"for m in {sorted(m for m in MODULES if not m.endswith('__main__'))!r}:\n"
        "    importlib.import_module(m)\n"
        "after = {i['filepath']: i['num_threads'] for i in threadpool_info()}\n"
        "changed = {k: (v, after[k]) for k, v in before.items() if after.get(k) != v}\n"
        "assert not changed and max(after.values()) == 2, (changed, after)\n"
    )
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=120)


def test_runtime_configure_limits_every_blas_to_one_thread():
    """`runtime.configure()` works even when it runs before numpy and scipy are imported."""
    import os
    import subprocess
    import sys

    code = (
        "from scissor_cli import runtime\n"
        "runtime.configure()\n"
        "import numpy, scipy.sparse, cvxopt\n"
        "from threadpoolctl import threadpool_info\n"
        "blas = {i['filepath']: i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'}\n"
        "assert len(blas) >= 2 and set(blas.values()) == {1}, blas\n"
    )
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=120)


def test_runtime_configure_gives_cvxopts_blas_the_kernels_numpys_picked():
    """CHOLMOD's dense kernels run what numpy's OpenBLAS detected (cvxopt's own fell back to Prescott on recent CPUs);
    a core the user set is kept."""
    import os
    import subprocess
    import sys

    code = (
        "import os, sys\n"
        "from scissor_cli import runtime\n"
        "runtime.configure()\n"
        "import numpy, cvxopt\n"
        "from threadpoolctl import threadpool_info\n"
        "arch = {i['prefix']: i.get('architecture') for i in threadpool_info()\n"
        "        if i.get('internal_api') == 'openblas'}\n"
        "mine = [a for p, a in arch.items() if 'scipy' not in p]\n"
        "theirs = {a for p, a in arch.items() if 'scipy' in p}\n"
        "core = os.environ.get('OPENBLAS_CORETYPE')\n"
        "if sys.argv[1] != '-':\n"
        "    assert core == sys.argv[1], core\n"
        "elif core is not None:\n"
        "    assert runtime.KNOWN_CORES[theirs.pop()] == core and mine == [core], (arch, core)\n"
        "else:\n"
        "    assert not theirs & set(runtime.KNOWN_CORES), arch\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
    subprocess.run([sys.executable, "-c", code, "-"], check=True, env=env, timeout=120)
    subprocess.run([sys.executable, "-c", code, "Prescott"], check=True, env={**env, "OPENBLAS_CORETYPE": "Prescott"},
                   timeout=120)


ROOT = PACKAGE.parent
#: file names that mean the same thing in every feature sub-package of output/ (the feature's results.h5
#: writers, figures, report rows) and at its top
SHARED_OUTPUT_NAMES = {"results.py", "figures.py", "report.py"}


def _is_face(path: Path) -> bool:
    """A package's `__init__.py` that only hands names on (a docstring, imports, `__all__`)."""
    if path.name != "__init__.py":
        return False
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.Import, ast.ImportFrom)) or (isinstance(node, ast.Expr)
                                                             and isinstance(node.value, ast.Constant)):
            continue
        if isinstance(node, ast.Assign) and [getattr(t, "id", "") for t in node.targets] == ["__all__"]:
            continue
        return False
    return True


def test_every_module_has_its_row_in_the_architecture_page():
    """docs/architecture.md lists every module by its path from scissor_cli/ (a package's face needs no row)."""
    import re

    rows = set(re.findall(r"^\| `([\w/]+\.py)` \|", (ROOT / "docs" / "architecture.md").read_text(), re.M))
    modules = {str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py") if not _is_face(p)}
    assert not modules - rows, f"modules without a row in docs/architecture.md: {sorted(modules - rows)}"
    gone = {r for r in rows if not (PACKAGE / r).exists()}
    assert not gone, f"rows of docs/architecture.md for modules that do not exist: {sorted(gone)}"


def test_a_file_name_means_one_thing():
    """Two modules share a file name only as the same kind of file of output/'s features."""
    by_name: dict[str, list[str]] = {}
    for p in PACKAGE.rglob("*.py"):
        if p.name != "__init__.py":
            by_name.setdefault(p.name, []).append(str(p.relative_to(PACKAGE)))
    shared = {n: sorted(ps) for n, ps in by_name.items() if len(ps) > 1
              and not (n in SHARED_OUTPUT_NAMES and all(q.startswith("output/") for q in ps))}
    assert not shared, f"one file name, several modules: {shared}"


def test_the_readme_names_the_layers_in_order():
    """README's layer chain is LAYERS' (the package root, base modules and __main__ aside)."""
    import re

    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Code"):]
    chain = re.findall(r"`(\w+)(?:/|\.py)`", section[:section.index("importable")])
    assert chain == [m for m in LAYERS if m and m not in BASE and m != "__main__"], chain


def test_no_function_takes_more_than_12_parameters():
    """Options travel as a dataclass (docs/architecture.md, "Few parameters")."""
    many = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
                count = len(names) + bool(a.vararg) + bool(a.kwarg) - (names[:1] in (["self"], ["cls"]))
                if count > 12:
                    many.append(f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name} ({count})")
    assert not many, many


def test_equilibria_outside_solvers_go_through_solvers_equilibrium():
    """README: "Every equilibrium goes through `solvers.equilibrium`": outside solvers/, no module imports or
    calls `solve_newton` (the one Newton solve `solve_equilibrium` wraps)."""
    direct = []
    for module, path in MODULES.items():
        if _layer(module) == "solvers":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            named = (isinstance(node, ast.ImportFrom) and any(a.name == "solve_newton" for a in node.names)
                     or isinstance(node, ast.Attribute) and node.attr == "solve_newton"
                     or isinstance(node, ast.Name) and node.id == "solve_newton")
            if named:
                direct.append(f"{module}:{node.lineno}")
    assert not direct, f"solve_newton outside solvers/ (call solvers.equilibrium.solve_equilibrium): {direct}"
