"""docs/performance.md is what benchmarks/docs.py writes from benchmarks/results, and stays a reference.

`docs.py --check` compares the generated tables as text and docs/img's images by name (it runs no simulation);
a changed digit in a generated table must make it fail; the page keeps to 1000 lines and table cells of at most
160 characters; `--list` names every file of docs/img.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS_PY = ROOT / "benchmarks" / "docs.py"
PAGE = ROOT / "docs" / "performance.md"
MAX_LINES = 1000
MAX_CELL = 160


def _docs_py(root: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, str(root / "benchmarks" / "docs.py"), *args], capture_output=True,
                          text=True, env=env, timeout=120, check=False)


def test_committed_docs_are_what_docs_py_writes():
    r = _docs_py(ROOT, "--check")
    assert r.returncode == 0, r.stdout + r.stderr


def test_a_changed_digit_in_a_generated_table_fails_the_check(tmp_path):
    for part in ("benchmarks", "docs"):
        shutil.copytree(ROOT / part, tmp_path / part, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")
    page = tmp_path / "docs" / "performance.md"
    text = page.read_text()
    assert _docs_py(tmp_path, "--check").returncode == 0
    # the last digit of the first row of the first generated table of figures (not the list of result files)
    block = next((m for m in re.finditer(r"<!-- generated: ([a-z0-9_]+) -->\n\|.*\n\|.*\n(\|.*\d.*\n)", text)
                  if m.group(1) != "provenance"), None)
    assert block, "performance.md has no generated table of figures"
    at = block.start(2) + max(k for k, c in enumerate(block.group(2)) if c.isdigit())
    digit = text[at]
    page.write_text(text[:at] + str((int(digit) + 1) % 10) + text[at + 1:])
    r = _docs_py(tmp_path, "--check")
    assert r.returncode != 0, r.stdout + r.stderr
    assert "performance.md" in r.stdout


def test_page_length_and_table_cells():
    lines = PAGE.read_text().splitlines()
    assert len(lines) <= MAX_LINES, f"docs/performance.md has {len(lines)} lines (at most {MAX_LINES})"
    long = []
    for k, line in enumerate(lines, 1):
        if line.startswith("|"):
            cells = re.split(r"(?<!\\)\|", line.strip())[1:-1]
            long += [(k, len(c.strip()), c.strip()[:60]) for c in cells if len(c.strip()) > MAX_CELL]
    assert not long, f"table cells over {MAX_CELL} characters (line, length, start): {long}"


def test_list_names_every_image():
    r = _docs_py(ROOT, "--list")
    assert r.returncode == 0, r.stderr
    listed = set(r.stdout.split())
    images = {f"docs/img/{p.name}" for p in (ROOT / "docs" / "img").iterdir() if p.is_file()}
    assert images <= listed, f"not written by docs.py: {sorted(images - listed)}"
    assert "docs/performance.md" in listed
