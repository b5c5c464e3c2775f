"""docs/licenses.md keeps up with pyproject.toml: every declared dependency has its row, and the
package's own licence is the one LICENSE holds."""

from __future__ import annotations

import re

from helpers import ROOT

PAGE = ROOT / "docs" / "licenses.md"


def _section(text: str, header: str) -> str:
    """The body of one TOML table: from its header line to the next header."""
    text = "\n" + text
    start = text.index(f"\n[{header}]\n") + len(header) + 3
    end = text.find("\n[", start)
    return text[start:] if end < 0 else text[start:end]


def declared(pyproject: str) -> set[str]:
    """The distribution names in [project] dependencies and every [project.optional-dependencies] list."""
    no_comments = "\n".join(line.split("#", 1)[0] for line in pyproject.splitlines())
    lists = re.findall(r"^dependencies = \[(.*?)\]", _section(no_comments, "project"), re.M | re.S)
    lists += re.findall(r"^\w+ = \[(.*?)\]", _section(no_comments, "project.optional-dependencies"), re.M | re.S)
    return {m.lower() for body in lists for m in re.findall(r'"([A-Za-z0-9][A-Za-z0-9._-]*)', body)}


def test_the_reader_finds_runtime_and_extra_requirements():
    text = ('[project]\nname = "x"\n# a comment "fake>=1"\ndependencies = [\n    "numpy>=2.0",  # "not-me"\n'
            '    "Typer>=0.16",\n]\n\n[project.optional-dependencies]\nt = ["pytest>=7", "ruff>=0.17"]\n\n[tool.x]\n'
            'dependencies = ["elsewhere"]\n')
    assert declared(text) == {"numpy", "typer", "pytest", "ruff"}


def test_every_dependency_has_a_row():
    names = declared((ROOT / "pyproject.toml").read_text())
    assert {"numpy", "triangle", "cvxopt", "pymust", "pytest"} <= names  # the reader read the real file
    rows = {m.lower() for m in re.findall(r"^\| ([A-Za-z0-9._-]+) \|", PAGE.read_text(), re.M)}
    assert not names - rows, f"dependencies without a row in docs/licenses.md: {sorted(names - rows)}"
    assert not rows - names - {"package"}, f"rows for packages pyproject.toml does not declare: {sorted(rows - names)}"


def test_the_package_licence_is_the_licence_file():
    assert re.search(r'^license = "BSD-3-Clause"$', (ROOT / "pyproject.toml").read_text(), re.M)
    assert (ROOT / "LICENSE").read_text().startswith("BSD 3-Clause License\n")
    assert "BSD 3-Clause" in PAGE.read_text()
