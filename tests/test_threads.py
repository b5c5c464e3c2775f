"""Two threads in one process (`runtime.set_threads`): the compiled loops split their work into fixed parts, so one
thread or two give the same numbers, bit for bit; the setting's bad values are refused clearly."""

from __future__ import annotations

import contextlib
import os

import numpy as np
import pytest
import scipy.sparse as sp
import yaml

from scissor_cli import runtime
from scissor_cli.config import parse_config
from scissor_cli.experiments.build import body_model
from scissor_cli.solvers.equilibrium import solve_equilibrium
from scissor_cli.solvers.linear import Factorization
from scissor_cli.solvers.single_factor import SingleFactorizer
from scissor_cli.solvers.supernode_tree import supernode_parents, tree_cuts

from test_body import SCENE
from test_cli import run_cli


@contextlib.contextmanager
def threads(n: int):
    kept = runtime.threads()
    runtime.set_threads(n)
    try:
        yield
    finally:
        runtime.set_threads(kept)


def _laplacian_3d(k: int, shift: float) -> sp.csr_matrix:
    """The 7-point Laplacian of a k³ grid + shift I: a 3-D mesh's fill, its nested dissection a tree that branches."""
    T = sp.diags([-np.ones(k - 1), 2 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])
    eye = sp.eye(k)
    A = sp.kron(sp.kron(T, eye), eye) + sp.kron(sp.kron(eye, T), eye) + sp.kron(sp.kron(eye, eye), T)
    return (A + shift * sp.eye(k**3)).tocsr()


@pytest.fixture(scope="module")
def factor():
    A = sp.triu(_laplacian_3d(14, 0.1)).tocsr()
    return A, Factorization(A, definite=True, upper=True, ordering="nested_dissection", supernodal=True)


def test_the_tree_is_cut_into_independent_runs_and_a_top(factor):
    """Every part is a run of supernodes whose rows below lie in the part itself or in the top, and the parts
    carry comparable work: what lets two threads take them at once."""
    _, f = factor
    L = f.single()
    cuts = L.cuts
    K = runtime.MOST_THREADS
    assert cuts.shape == (K + 2,) and cuts[0] == 0 and cuts[-1] == L.starts.size - 1
    assert np.all(np.diff(cuts) > 0)  # a nested-dissection tree branches: every part has supernodes
    owner = np.repeat(np.arange(L.starts.size - 1), np.diff(L.starts))
    part = np.searchsorted(cuts, np.arange(L.starts.size - 1), side="right") - 1
    for s in range(cuts[K]):
        rows = L.block_rows[L.row_ptr[s]:L.row_ptr[s + 1]]
        assert set(part[owner[rows]]) <= {part[s], K}
    parent = supernode_parents(L.starts, L.row_ptr, L.block_rows)
    assert np.all((parent == -1) | (parent > np.arange(parent.size)))


def test_a_tree_that_is_not_postordered_is_left_whole():
    """A layout whose parents do not follow their children gives one serial run: everything in the top."""
    starts = np.array([0, 1, 2])
    row_ptr = np.array([0, 1, 3])
    block_rows = np.array([0, 1, 0], np.int32)  # supernode 1's row below is supernode 0's column
    assert tree_cuts(starts, row_ptr, block_rows, 2).tolist() == [0, 0, 0, 2]


def test_a_float32_factorisation_and_its_solves_are_the_same_on_one_thread_or_two(factor):
    """The factorisation, a solve of one column and of several, and a float64 copy's solve."""
    A, f = factor
    factorizer = SingleFactorizer(f.single(), A.indptr, A.indices)
    D = sp.diags(np.random.default_rng(5).uniform(0.5, 2.0, A.shape[0]))
    B = sp.triu(D @ (A + sp.triu(A, 1).T) @ D).tocsr()
    b = np.random.default_rng(6).normal(size=(A.shape[0], 4))
    out = {}
    for n in (1, 2):
        with threads(n):
            own = factorizer.factor(B.data)
            out[n] = own.blocks.copy(), own.solve(b[:, 0]), own.solve(b), f.double().solve(b[:, 1])
    assert all(np.array_equal(x, y) for x, y in zip(out[1], out[2]))
    full = (B + sp.triu(B, 1).T).tocsr()
    for x, rhs in ((out[2][1], b[:, 0]), (out[2][2], b)):
        assert np.linalg.norm(full @ x - rhs) <= 1e-4 * np.linalg.norm(rhs)


def test_a_body_s_gradient_tangent_and_equilibrium_are_the_same_on_one_thread_or_two():
    """The nodal element's gradient, the elements' packed Hessians and a Newton solve from rest on the test dome."""
    _, _, tissue = body_model(parse_config(yaml.safe_dump(SCENE)))
    x = tissue.rest + 0.05 * np.random.default_rng(0).standard_normal(tissue.rest.shape)
    out = {}
    for n in (1, 2):
        with threads(n):
            U, g = tissue.energy_gradient(x)
            K = tissue.stiffness_free(x)
            r = solve_equilibrium(tissue, np.array([6.0, 0.0]), tol=1e-8)
            out[n] = U, g, K.data, r.x
    assert out[1][0] == out[2][0]
    assert all(np.array_equal(a, b) for a, b in zip(out[1][1:], out[2][1:]))


def test_a_thread_count_out_of_range_is_refused():
    with pytest.raises(ValueError, match="allowed values are 1 to 2"):
        runtime.set_threads(3)
    assert runtime.in_parts(lambda: 1, lambda: 2) == [1, 2]


def test_a_bad_scissor_threads_is_a_clear_error_not_a_traceback(tmp_path):
    kept = os.environ.get(runtime.THREADS_VARIABLE)
    os.environ[runtime.THREADS_VARIABLE] = "four"
    try:
        r = run_cli("validate", "configs/example.yaml", cwd=os.path.dirname(os.path.dirname(__file__)))
    finally:
        if kept is None:
            del os.environ[runtime.THREADS_VARIABLE]
        else:
            os.environ[runtime.THREADS_VARIABLE] = kept
    assert r.returncode == 2
    assert "SCISSOR_THREADS" in r.stderr and "1 to 2" in r.stderr and "Traceback" not in r.stderr
