"""docs/api.md's code runs: its python blocks, in order, in one namespace, from the repository's root."""

import re

import pytest

from helpers import ROOT

BLOCKS = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "api.md").read_text(), flags=re.S)


def test_api_md_has_examples():
    assert len(BLOCKS) >= 3


def test_api_md_examples_run(monkeypatch):
    monkeypatch.chdir(ROOT)
    namespace: dict = {}
    for k, block in enumerate(BLOCKS):
        if "gymnasium" in block:
            pytest.importorskip("gymnasium")
        exec(compile(block, f"docs/api.md block {k + 1}", "exec"), namespace)  # noqa: S102 - the docs' own code


def test_the_package_root_hands_on_exactly_the_apis_names():
    import scissor_cli
    import scissor_cli.api

    assert set(scissor_cli.API_NAMES) == set(scissor_cli.api.__all__)
    assert scissor_cli.manipulate is scissor_cli.api.manipulate


def test_the_core_runs_without_gymnasium(tmp_path):
    """`pip install .` without the extra: nothing but scissor_cli.gym imports gymnasium."""
    import subprocess
    import sys

    from test_cli import small_scene

    # (one trial per target, on the pool's two workers: every stage's imports, the trials' included, not their
    # statistics: the forward cases, plans, manipulations and figures import the pipeline)
    scene = small_scene(tmp_path, **{"trials.count": 1})
    code = ("import sys; sys.modules['gymnasium'] = None\n"  # any `import gymnasium` now fails
            "from scissor_cli.cli import app\n"
            f"sys.argv = ['scissor', 'simulate', {str(scene)!r}, '--out', {str(tmp_path / 'out')!r}, '--jobs', '2',"
            " '--quiet']\n"
            "app()")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "out" / "results.h5").is_file()
