"""The shared sparse factorisation: CHOLMOD for definite matrices, qdldl's LDLᵀ otherwise."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from scissor_cli.solvers.linear import Factorization
from scissor_cli.solvers.common import SolverError


def _spd(n=60, shift=10.0, seed=1):
    A = sp.random(n, n, density=0.08, random_state=seed)
    return (A + A.T + shift * sp.eye(n)).tocsr()


def test_definite_matrix_gets_cholesky_and_solves_like_superlu():
    A = _spd()
    b = np.random.default_rng(0).random((A.shape[0], 3))
    f = Factorization(A)
    assert f.method == "cholesky"
    ref = spla.spsolve(A.tocsc(), b)
    np.testing.assert_allclose(f.solve(b), ref, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(f.solve(b[:, 1]), ref[:, 1], rtol=1e-12, atol=1e-14)
    assert f.solve(b[:, 1]).shape == (A.shape[0],)


def test_indefinite_matrix_falls_back_to_ldl_and_back():
    A = _spd()
    B = (A - 12.0 * sp.eye(A.shape[0])).tocsr()  # same pattern, negative eigenvalues
    assert np.linalg.eigvalsh(B.toarray()).min() < 0
    b = np.random.default_rng(1).random((A.shape[0], 2))
    f = Factorization(A)
    f.refactor(B)
    assert f.method == "ldl"
    np.testing.assert_allclose(B @ f.solve(b), b, atol=1e-10)
    f.refactor(A)  # the Cholesky analysis is still there
    assert f.method == "cholesky"
    np.testing.assert_allclose(A @ f.solve(b[:, 0]), b[:, 0], atol=1e-12)


def test_definite_request_refuses_an_indefinite_matrix_and_forgets_the_old_factor():
    A = _spd()
    f = Factorization(A, definite=True)
    with pytest.raises(SolverError, match="not positive definite"):
        f.refactor((A - 12.0 * sp.eye(A.shape[0])).tocsr())
    with pytest.raises(SolverError, match="no valid factorisation"):
        f.solve(np.ones(A.shape[0]))


def test_singular_matrix_is_an_error_not_inf():
    S = sp.csr_matrix(np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]]))
    with pytest.raises(SolverError):
        Factorization(S)


def test_refactor_with_a_new_pattern_and_unsorted_indices():
    A = _spd(seed=2)
    f = Factorization(A)
    C = _spd(n=40, seed=3)
    # the same matrix with its column indices scrambled within each row
    perm_rows = [np.random.default_rng(r).permutation(np.arange(C.indptr[r], C.indptr[r + 1])) for r in range(40)]
    order = np.concatenate(perm_rows)
    U = sp.csr_matrix((C.data[order], C.indices[order], C.indptr), shape=C.shape)
    U.has_sorted_indices = False
    b = np.arange(40.0)
    np.testing.assert_allclose(f.refactor(U).solve(b), spla.spsolve(C.tocsc(), b), rtol=1e-12)
