"""The shared sparse factorisation: CHOLMOD for definite matrices, qdldl's LDLᵀ otherwise."""

import ctypes
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.linear import Factorization


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


def test_simplicial_factor_solves_the_same_and_still_refuses_an_indefinite_matrix():
    """supernodal=False solves with CHOLMOD's simplicial LDLᵀ, which would take an indefinite matrix: the check
    must not."""
    A = _spd()
    b = np.random.default_rng(2).random((A.shape[0], 2))
    f = Factorization(sp.triu(A).tocsr(), definite=True, upper=True, supernodal=False)
    np.testing.assert_allclose(f.solve(b), Factorization(A).solve(b), rtol=1e-12, atol=1e-14)
    assert f.nnz_factor > 0
    with pytest.raises(SolverError, match="not positive definite"):
        f.refactor(sp.triu(A - 12.0 * sp.eye(A.shape[0])).tocsr())
    f.refactor(sp.triu(2.0 * A).tocsr())
    np.testing.assert_allclose(2.0 * A @ f.solve(b), b, atol=1e-12)


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


def _laplacian_3d(k=8, shift=0.0):
    """The 7-point Laplacian of a k³ grid (+ shift I): a 3-D mesh's fill pattern."""
    T = sp.diags([-np.ones(k - 1), 2 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])
    eye = sp.eye(k)
    A = sp.kron(sp.kron(T, eye), eye) + sp.kron(sp.kron(eye, T), eye) + sp.kron(sp.kron(eye, eye), T)
    return (A + shift * sp.eye(k**3)).tocsr()


def test_nested_dissection_is_a_permutation_and_solves_like_amd():
    from scissor_cli.solvers.ordering import nested_dissection

    A = _laplacian_3d(10, 0.1)
    n = A.shape[0]
    p = nested_dissection(A)
    assert np.array_equal(np.sort(p), np.arange(n))
    grouped = nested_dissection(sp.kron(A, np.ones((3, 3))).tocsr(), np.repeat(np.arange(n), 3))
    assert np.array_equal(np.sort(grouped), np.arange(3 * n))
    # node blocks kept
    assert np.array_equal(grouped.reshape(-1, 3) // 3, np.repeat(grouped[::3, None] // 3, 3, axis=1))
    b = np.random.default_rng(2).random(n)
    x_nd = Factorization(sp.triu(A).tocsr(), definite=True, upper=True, ordering="nested_dissection").solve(b)
    x_amd = Factorization(A, definite=True).solve(b)
    assert np.linalg.norm(x_nd - x_amd) <= 1e-10 * np.linalg.norm(x_amd)
    with pytest.raises(ValueError):
        Factorization(A, ordering="metis")


def test_preconditioned_cg_solves_to_tolerance_and_refuses_indefinite(monkeypatch):
    from scissor_cli.solvers import linear
    from scissor_cli.solvers.linear import preconditioned_cg

    A = _laplacian_3d(8, 0.5)
    near = (A + 0.2 * sp.diags(np.random.default_rng(3).random(A.shape[0]))).tocsr()
    b = np.random.default_rng(4).random(A.shape[0])
    f = Factorization(A, definite=True, float32_steps=True)
    x, k, why = preconditioned_cg(sp.triu(near).tocsr(), b, f, 1e-12, max_iter=50)
    assert x is not None and 1 < k < 50 and f.cg_iterations == k and why == "converged"
    direct = Factorization(near, definite=True).solve(b)
    assert np.linalg.norm(x - direct) <= 1e-10 * np.linalg.norm(direct)
    x1, k1, _ = preconditioned_cg(A, b, f, 1e-10, upper=False)  # its own factor's float32 copy: one or two
    assert k1 <= 2 and np.linalg.norm(A @ x1 - b) <= 1e-10 * np.linalg.norm(b)
    monkeypatch.setattr(linear, "SINGLE_PRECISION_STEPS", False)  # its own factor in float64: one iteration
    x1, k1, _ = preconditioned_cg(A, b, f, 1e-10, upper=False)
    assert k1 == 1 and np.linalg.norm(A @ x1 - b) <= 1e-10 * np.linalg.norm(b)
    bad = (A - 2.0 * sp.eye(A.shape[0])).tocsr()  # indefinite: not returned
    x, _, why = preconditioned_cg(sp.triu(bad).tocsr(), b, f, 1e-12, max_iter=200)
    assert x is None and why == "curvature"
    x, _, why = preconditioned_cg(sp.triu(near).tocsr(), b, f, 1e-14, max_iter=2)
    assert x is None and why == "iterations"  # budget spent


def test_solve_free_uses_cg_on_the_old_factor_refactors_when_stale_or_failing():
    from types import SimpleNamespace

    from scissor_cli.solvers import linear

    A = sp.triu(_laplacian_3d(8, 0.5)).tocsr()
    n = A.shape[0]
    tissue = SimpleNamespace(factor_cache={}, dim=3, free_dofs=np.arange(n))
    b = np.random.default_rng(5).random(n)
    x, factored = linear.solve_free(tissue, A, b, rtol=1e-8)  # no factor yet: factors
    assert factored and tissue.factor_cache["free"].ordering == "nested_dissection"
    near = (A + sp.diags(0.05 * np.random.default_rng(6).random(n))).tocsr()
    x, factored = linear.solve_free(tissue, near, b, rtol=1e-8)  # close: CG on the old factor
    f = tissue.factor_cache["free"]
    assert not factored and 0 < f.cg_iterations <= linear.KRYLOV_STALE_ITER and not f.stale
    assert np.linalg.norm(near @ x + near.T @ x - near.diagonal() * x - b) <= 1e-8 * np.linalg.norm(b)
    far = (A + sp.diags(3.0 * np.random.default_rng(7).random(n))).tocsr()
    x, factored = linear.solve_free(tissue, far, b, rtol=1e-10)
    if not factored:  # CG made it, slowly: the factor is stale and the next solve factors
        assert f.stale
        assert linear.solve_free(tissue, far, b, rtol=1e-10)[1]
    assert not f.stale
    assert linear.solve_free(tissue, far, b)[1]  # no rtol: always the direct solve


def test_solve_free_takes_negative_curvature_as_proof_and_keeps_its_factor():
    """An indefinite K_ff that CG on the slot's factor exposes is refused without the factorisation (which would fail
    after most of its cost); the slot's factor stays usable. Without rtol the factorisation itself says so."""
    from types import SimpleNamespace

    from scissor_cli.solvers import linear

    A = sp.triu(_laplacian_3d(8, 0.5)).tocsr()
    n = A.shape[0]
    tissue = SimpleNamespace(factor_cache={}, dim=3, free_dofs=np.arange(n))
    b = np.random.default_rng(5).random(n)
    linear.solve_free(tissue, A, b, rtol=1e-8)
    f = tissue.factor_cache["free"]
    bad = sp.triu(A - 2.0 * sp.eye(n)).tocsr()
    assert np.linalg.eigvalsh((bad + sp.triu(bad, 1).T).toarray())[0] < 0  # indefinite indeed
    with pytest.raises(linear.NotPositiveDefinite) as caught:
        linear.solve_free(tissue, bad, b, rtol=1e-8)
    assert not caught.value.factored and f.factorizations == 1
    x, factored = linear.solve_free(tissue, A, b, rtol=1e-8)  # the kept factor still preconditions
    assert not factored and np.linalg.norm(A @ x + A.T @ x - A.diagonal() * x - b) <= 1e-8 * np.linalg.norm(b)
    with pytest.raises(linear.NotPositiveDefinite) as caught:
        linear.solve_free(tissue, bad, b)
    assert caught.value.factored and f.factorizations == 2


def test_large_2d_factors_are_ordered_by_nested_dissection():
    """In 2-D, METIS's ordering beyond ND_MIN_UNKNOWNS_2D unknowns: never more fill than AMD's (CHOLMOD keeps the
    sparser)."""
    from types import SimpleNamespace

    from scissor_cli.solvers import linear

    A = _laplacian_2d_blocks(75)  # 2 x 75² = 11250 unknowns
    assert A.shape[0] >= linear.ND_MIN_UNKNOWNS_2D
    tissue = SimpleNamespace(factor_cache={}, dim=2, free_dofs=np.arange(A.shape[0]))
    b = np.random.default_rng(2).random(A.shape[0])
    x, _ = linear.solve_free(tissue, sp.triu(A).tocsr(), b)
    f = tissue.factor_cache["free"]
    assert f.ordering == "nested_dissection"
    assert np.linalg.norm(A @ x - b) <= 1e-10 * np.linalg.norm(b)
    amd = Factorization(sp.triu(A).tocsr(), definite=True, upper=True)
    assert f.nnz_factor <= amd.nnz_factor
    small = SimpleNamespace(factor_cache={}, dim=2, free_dofs=np.arange(2 * 30**2))
    linear.solve_free(small, sp.triu(_laplacian_2d_blocks(30)).tocsr(), np.ones(2 * 30**2))
    assert small.factor_cache["free"].ordering == "amd"


def test_a_new_slot_on_a_known_pattern_reuses_its_nested_dissection(monkeypatch):
    """Each trial's trackers open slots of their own on one pattern: METIS runs for the first only, the others
    take its ordering from the tissue's cache (the same ordering, so the same factor); a given ordering must fit."""
    from types import SimpleNamespace

    from scissor_cli.solvers import linear

    A = _laplacian_3d(8, 0.5)
    upper = sp.triu(A).tocsr()
    tissue = SimpleNamespace(factor_cache={}, dim=3, free_dofs=np.arange(A.shape[0]))
    calls = []
    metis = linear.nested_dissection
    monkeypatch.setattr(linear, "nested_dissection", lambda *a: calls.append(1) or metis(*a))
    b = np.random.default_rng(5).random(A.shape[0])
    first, second = {}, {}
    x1 = linear.factorize_free(tissue, upper, first).solve(b)
    x2 = linear.factorize_free(tissue, upper, second).solve(b)
    assert len(calls) == 1 and second["free"] is not first["free"]
    assert np.array_equal(second["free"].perm, first["free"].perm)
    np.testing.assert_array_equal(x2, x1)
    assert np.linalg.norm(A @ x1 - b) <= 1e-10 * np.linalg.norm(b)
    with pytest.raises(ValueError):
        Factorization(upper, definite=True, upper=True, ordering="nested_dissection", perm=np.arange(3))
    with pytest.raises(ValueError):
        Factorization(upper, definite=True, upper=True, perm=first["free"].perm)  # (AMD takes none)


def test_a_released_slot_is_taken_by_the_next_new_slot_of_its_pattern_only(monkeypatch):
    """A tracker's slot handed back when its loop ends (`release_free`) becomes the next new slot of exactly its
    pattern: refactored at the new matrix, its counts and conjugate-gradient record gone, solving exactly as a new
    factorisation; a pattern with as many entries elsewhere gets a new one, and with reuse off nothing is kept."""
    from types import SimpleNamespace

    from scissor_cli.solvers import linear

    A = _laplacian_3d(6, 0.5)
    n = A.shape[0]
    tissue = SimpleNamespace(factor_cache={}, dim=3, free_dofs=np.arange(n))
    first = {}
    f = linear.factorize_free(tissue, sp.triu(A).tocsr(), first)
    f.stale, f.cg_rate = True, 0.5
    linear.release_free(tissue, first)
    assert "free" not in first and tissue.factor_cache["released"] == [f]
    shifted = sp.triu(A + 0.3 * sp.eye(n)).tocsr()
    second = {}
    g = linear.factorize_free(tissue, shifted, second)
    assert g is f and second["free"] is f and tissue.factor_cache["released"] == []
    assert g.factorizations == 1 and not g.stale and g.cg_rate is None
    fresh = Factorization(shifted, definite=True, upper=True, ordering="nested_dissection", perm=f.perm)
    b = np.random.default_rng(6).random(n)
    np.testing.assert_array_equal(g.solve(b), fresh.solve(b))
    linear.release_free(tissue, second)
    moved = A.tolil()
    moved[0, 1] = moved[1, 0] = 0.0
    moved[0, n - 1] = moved[n - 1, 0] = -0.5
    moved = sp.triu(moved.tocsr()).tocsr()
    moved.eliminate_zeros()
    assert moved.nnz == shifted.nnz
    third = {}
    assert linear.factorize_free(tissue, moved, third) is not f
    monkeypatch.setattr(linear, "REUSE_RELEASED", False)
    linear.release_free(tissue, third)
    assert "free" not in third and tissue.factor_cache["released"] == [f]


def _laplacian_2d_blocks(m: int) -> sp.csr_matrix:
    """A 2-D grid Laplacian (m², m²) + I, each node carrying 2 unknowns (I ⊗ 2x2 SPD block): a 2-D stiffness's
    pattern."""
    T = sp.diags([-np.ones(m - 1), 4.2 * np.ones(m), -np.ones(m - 1)], [-1, 0, 1])
    L = (sp.kron(sp.eye(m), T) + sp.kron(sp.diags([np.ones(m - 1), np.ones(m - 1)], [-1, 1]), -sp.eye(m)))
    return sp.kron(L, np.array([[2.0, 0.5], [0.5, 1.0]])).tocsr()


def test_a_preconditioned_solve_records_its_rate_and_a_refactorisation_forgets_it():
    from scissor_cli.solvers import linear

    A = sp.triu(_laplacian_3d(6, 0.5)).tocsr()
    n = A.shape[0]
    f = linear.Factorization(A, definite=True, upper=True)
    assert f.cg_rate is None and f.cg_iterations_for(1e-2) == 0.0  # unknown: worth a try
    near = (A + sp.diags(0.2 * np.random.default_rng(3).random(n))).tocsr()
    b = np.random.default_rng(4).random(n)
    x, k, _ = linear.preconditioned_cg(near, b, f, 1e-6)
    assert x is not None and k > 1 and f.cg_rate == pytest.approx(1e-6 ** (1.0 / k))
    assert f.cg_iterations_for(1e-6) == pytest.approx(k) and f.cg_iterations_for(1e-12) == pytest.approx(2 * k)
    f.refactor(near)
    assert f.cg_rate is None


def test_reading_the_factor_size_leaves_the_factor_usable():
    """nnz_factor factors a copy: cvxopt's getfactor would turn the factor it reads into a symbolic one."""
    import numpy as np
    import scipy.sparse as sp

    from scissor_cli.solvers.linear import Factorization

    n = 40
    A = sp.diags([np.full(n - 1, -1.0), np.full(n, 4.0), np.full(n - 1, -1.0)], [-1, 0, 1], format="csr")
    f = Factorization(A, definite=True)
    b = np.arange(1.0, n + 1)
    x = f.solve(b)
    assert f.nnz_factor >= n and f.nnz_factor == f.nnz_factor
    assert np.allclose(f.solve(b), x) and np.allclose(A @ x, b)


@pytest.mark.parametrize("ordering", ["amd", "nested_dissection"])
def test_a_float32_copy_solves_to_single_precision_and_leaves_the_factor_in_float64(ordering):
    """single copies the supernodal factor, read where CHOLMOD keeps it (solvers.cholmod_factor), into float32
    blocks: it solves one or many columns to float32's precision in the original ordering; the Factorization still
    solves in float64, and after a refactorisation its copy is the new factor's."""
    A = sp.triu(_laplacian_3d(12, 0.1)).tocsr()  # wide supernodes in a nested-dissection order
    full = (A + sp.triu(A, 1).T).tocsc()
    f = Factorization(A, definite=True, upper=True, ordering=ordering, supernodal=True)
    kept = f.single()
    assert kept is not None and f.single() is kept  # one copy per factorisation
    b = np.random.default_rng(3).random((A.shape[0], 3))
    ref = spla.spsolve(full, b)
    for x, r in ((kept.solve(b), ref), (kept.solve(b[:, 2]), ref[:, 2])):
        assert x.shape == r.shape and x.dtype == np.float64
        assert np.linalg.norm(x - r) <= 1e-5 * np.linalg.norm(r)
    np.testing.assert_allclose(f.solve(b), ref, rtol=1e-10)
    twice = sp.triu(2.0 * full).tocsr()
    f.refactor(twice)
    assert f.single() is not kept
    np.testing.assert_allclose(f.single().solve(b), 0.5 * ref, rtol=1e-4)



@pytest.mark.parametrize("ordering", ["amd", "nested_dissection"])
def test_a_float64_copy_solves_as_cholmod_does(ordering):
    """double: the same compiled loops on float64 blocks (for a factor float32 cannot carry) solve one or many
    columns to double precision, each right-hand side as the Factorization itself solves it; a copy per
    factorisation, apart from the float32 one."""
    A = sp.triu(_laplacian_3d(12, 0.1)).tocsr()
    f = Factorization(A, definite=True, upper=True, ordering=ordering, supernodal=True)
    kept = f.double()
    assert kept is not None and f.double() is kept and f.single() is not kept and kept.blocks.dtype == np.float64
    b = np.random.default_rng(4).random((A.shape[0], 5))
    ref = f.solve(b)
    for x, r in ((kept.solve(b), ref), (kept.solve(b[:, 1]), ref[:, 1])):
        assert x.shape == r.shape and x.dtype == np.float64
        assert np.linalg.norm(x - r) <= 1e-12 * np.linalg.norm(r)
    f.refactor(sp.triu(4.0 * (A + sp.triu(A, 1).T)).tocsr())
    assert f.double() is not kept
    np.testing.assert_allclose(f.double().solve(b), 0.25 * ref, rtol=1e-10)


@pytest.mark.parametrize("ordering", ["amd", "nested_dissection"])
def test_a_float32_factorisation_on_cholmod_s_layout_solves_as_cholmod_does(ordering):
    """SingleFactorizer: a matrix of the pattern, factored in float32 on the layout of CHOLMOD's factor of another
    (the values scaled per unknown), solves as CHOLMOD's factor of it does to float32's precision, its blocks
    CHOLMOD's L rounded; a matrix that is not positive definite gives None."""
    from scissor_cli.solvers.single_factor import SingleFactorizer

    A = sp.triu(_laplacian_3d(12, 0.1)).tocsr()
    f = Factorization(A, definite=True, upper=True, ordering=ordering, supernodal=True)
    factorizer = SingleFactorizer(f.single(), A.indptr, A.indices)
    D = sp.diags(np.random.default_rng(5).uniform(0.5, 2.0, A.shape[0]))
    B = sp.triu(D @ (A + sp.triu(A, 1).T) @ D).tocsr()
    assert factorizer.matches(B)
    own = factorizer.factor(B.data)
    f.refactor(B)
    cholmod = f.single()
    assert own.blocks.dtype == np.float32 and own.blocks.shape == cholmod.blocks.shape
    assert np.abs(own.blocks - cholmod.blocks).max() <= 1e-5 * np.abs(cholmod.blocks).max()
    b = np.random.default_rng(6).random((A.shape[0], 3))
    ref = f.solve(b)
    assert np.linalg.norm(own.solve(b) - ref) <= 1e-4 * np.linalg.norm(ref)
    indefinite = sp.triu(A - 2.0 * sp.eye(A.shape[0])).tocsr()
    assert factorizer.matches(indefinite) and factorizer.factor(indefinite.data) is None


def test_a_refactorisation_that_only_preconditions_is_made_in_float32_and_float64_on_demand(monkeypatch):
    """`refactor(single=True)` (a 3-D slot, supernodal): the first factorisation is CHOLMOD's, which lays out the
    float32 ones, and float32's of the same values, which `stepping_solve` steps on (`in_float32`: so whether a slot
    is new or not changes no bit); the next is float32's alone (`deferred`), solved to float32's precision, and
    CHOLMOD factors the same values only when a float64 solve asks; `solve_free` with rtol solves on it by CG
    without that. Where float32 breaks down CHOLMOD decides (an indefinite matrix is refused), and off it is
    CHOLMOD each time."""
    from types import SimpleNamespace

    from scissor_cli.solvers import linear

    A = sp.triu(_laplacian_3d(10, 0.5)).tocsr()
    n = A.shape[0]
    tissue = SimpleNamespace(factor_cache={}, dim=3, free_dofs=np.arange(n))
    b = np.random.default_rng(5).random(n)

    def residual(M, x):
        return np.linalg.norm(M @ x + M.T @ x - M.diagonal() * x - b) / np.linalg.norm(b)

    f = linear.factorize_free(tissue, A, single=True)
    assert f.in_float32 and not f.deferred and f.factorizations == 1
    first = linear.stepping_solve(f)(b)
    assert residual(A, first) <= 1e-5
    near = (A + sp.diags(np.random.default_rng(6).uniform(0.0, 0.5, n))).tocsr()
    f = linear.factorize_free(tissue, near, single=True)
    assert f.in_float32 and f.deferred and f.method == "cholesky"
    assert np.array_equal(linear.Factorization(A, definite=True, upper=True, ordering="nested_dissection",
                                               groups=np.arange(n), float32_steps=True, single=True,
                                               perm=f.perm).single().solve(b), first)  # a new slot's: the same bits
    assert residual(near, linear.stepping_solve(f)(b)) <= 1e-5  # float32's factor of `near` itself
    assert residual(near, f.solve(b)) <= 1e-12 and not f.deferred  # CHOLMOD's, made for this solve
    f.stale = True  # the slot's factor is not to precondition: solve_free refactors
    x, factored = linear.solve_free(tissue, near, b, rtol=1e-10)
    assert factored and f.deferred and residual(near, x) <= 2e-10  # by CG on float32's factor, CHOLMOD not asked
    bad = sp.triu(A - 2.0 * sp.eye(n)).tocsr()
    with pytest.raises(linear.NotPositiveDefinite):
        linear.factorize_free(tissue, bad, single=True)
    assert not f.in_float32
    monkeypatch.setattr(linear, "SINGLE_FACTORIZATION", False)
    assert not linear.factorize_free(tissue, near, single=True).in_float32


def test_only_a_supernodal_cholesky_factor_has_a_float32_copy():
    """A simplicial LDLᵀ, an indefinite matrix's qdldl factor and a capsule that is not CHOLMOD's factor give no
    copy (the callers then solve in float64)."""
    from scissor_cli.solvers.cholmod_factor import supernodal_copy

    A = sp.triu(_laplacian_3d(6, 0.1)).tocsr()
    assert Factorization(A, definite=True, upper=True, supernodal=False).single() is None
    indefinite = (_laplacian_3d(6, 0.1) - 2.0 * sp.eye(A.shape[0])).tocsr()
    f = Factorization(indefinite)
    assert f.method == "ldl" and f.single() is None
    supernodal = Factorization(A, definite=True, upper=True)
    assert supernodal_copy(supernodal._chol, A.shape[0] + 1) is None  # not the order asked for
    new_capsule = ctypes.pythonapi.PyCapsule_New
    new_capsule.restype, new_capsule.argtypes = ctypes.py_object, [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p]
    name = ctypes.c_char_p(b"something else")  # (kept alive: the capsule holds its address)
    other = new_capsule(ctypes.addressof(ctypes.c_double(1.0)), name, None)
    assert supernodal_copy(other, 3) is None


def test_a_float32_factor_solves_a_block_as_it_solves_each_column():
    """Many right-hand sides go through the BLAS-3 sweeps (`_forward_block`), one through the matrix-vector ones: the
    same solution to float32's precision, whatever the block's width."""
    A = sp.triu(_laplacian_3d(12, 0.1)).tocsr()
    kept = Factorization(A, definite=True, upper=True, ordering="nested_dissection", supernodal=True).single()
    rng = np.random.default_rng(8)
    for k in (2, 7, 40):
        b = rng.normal(size=(A.shape[0], k))
        block = kept.solve(b)
        each = np.column_stack([kept.solve(b[:, j]) for j in range(k)])
        assert np.linalg.norm(block - each) <= 1e-5 * np.linalg.norm(each)


def test_the_float32_solve_compiled_in_one_process_solves_in_another():
    """The compiled solve links BLAS by symbol name (solvers.supernodal._link_blas), so numba may cache it: a
    second process, which loads the cached code and links the name again, solves as the first did."""
    script = (
        "import numpy as np, scipy.sparse as sp\n"
        "from scissor_cli.solvers.linear import Factorization\n"
        "n = 400\n"
        "A = sp.diags([-1.0, 4.0, -1.0], [-1, 0, 1], (n, n), format='csr')\n"
        "x = Factorization(A, definite=True).single().solve(np.ones(n))\n"
        "print(np.abs(A @ x - 1.0).max())\n"
    )
    for _ in range(2):  # the first may compile (and cache), the second loads
        out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        assert float(out.stdout.strip()) < 1e-5
