"""The compiled element loops (mechanics/compiled.py) against the numpy reference path.

Both evaluate the same closed forms; the compiled loops must give the same
energy, gradient and (exact or per-term projected) element Hessians to
round-off, and hand every element they cannot take (inverted, absurd) back
to the numpy path, whose policy then holds.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scissor_cli.config import parse_config
from scissor_cli.experiments.build import scene_of
from scissor_cli.mechanics import compiled, fem, materials
from scissor_cli.mechanics.tissue import build_tissue
from scissor_cli.mesh.mesh import mesh_for_config

SCENE = """
tissue: {size_mm: [30, 20], mesh: {max_edge_mm: 4, min_edge_mm: 2}}
material: {model: %s, E_kPa: 10, nu: 0.45, eta_kPa: 6, fiber_angle_deg: 35, fiber_tension_only: %s}
cups: [{name: c, contact_mm: [15, 20], axis: [0, -1], radius_mm: 4}]
obstacles: [{name: v, circle: {center_mm: [10, 10], radius_mm: 2.5}, stiffness_factor: 3}]
"""


def _tissue(model, tension_only=False):
    cfg = parse_config(SCENE % (model, str(tension_only).lower()))
    scene = scene_of(cfg)
    return build_tissue(scene, mesh_for_config(scene, cfg.tissue.mesh))


@pytest.fixture(scope="module",
                params=[("neo_hookean", False), ("neo_hookean_fiber", False), ("neo_hookean_fiber", True)],
                ids=["neo_hookean", "fiber", "fiber_tension_only"])
def tissue(request):
    t = _tissue(*request.param)
    assert t.compiled
    return t


def _numpy_gradient(tissue, x):
    F = fem.deformation_gradients(tissue.ops, x)
    psi, P, _ = materials.evaluate(F, tissue.params, order=1)
    return float(psi @ tissue.ops.volume), fem.scatter_vector(tissue.ops, fem.element_forces(tissue.ops, P))


def _numpy_stiffness(tissue, x, project):
    F = fem.deformation_gradients(tissue.ops, x)
    C = materials.evaluate_projected(F, tissue.params)[2] if project else materials.evaluate(F, tissue.params, 2)[2]
    return fem.element_matrices(tissue.ops, C)


def _state(tissue, A, noise, seed):
    """An affine deformation A of the rest mesh with random nodal noise (mm)."""
    rng = np.random.default_rng(seed)
    return tissue.rest @ np.asarray(A).T + noise * rng.standard_normal(tissue.rest.shape)


# stretch along and across the fibers, compression (fibers compressed: the projection's fiber part acts), shear
DEFORMATIONS = [np.eye(2), [[1.15, 0.0], [0.0, 0.9]], [[0.8, 0.1], [-0.05, 0.85]], [[1.0, 0.4], [0.0, 1.0]]]


@pytest.mark.parametrize("A", DEFORMATIONS)
@pytest.mark.parametrize("seed", [0, 1])
def test_same_energy_gradient_and_stiffness_as_numpy(tissue, A, seed):
    x = _state(tissue, A, 0.15, seed)
    U, g = compiled.energy_gradient(tissue.ops, tissue.params, x)
    U0, g0 = _numpy_gradient(tissue, x)
    assert U == pytest.approx(U0, rel=1e-13, abs=1e-13)
    assert np.allclose(g, g0, rtol=1e-12, atol=1e-12 * np.abs(g0).max())
    for project in (False, True):
        Ke = compiled.element_stiffness(tissue.ops, tissue.params, x, project)
        K0 = _numpy_stiffness(tissue, x, project)
        assert np.allclose(Ke, K0, rtol=1e-12, atol=1e-12 * np.abs(K0).max())


@pytest.mark.parametrize("A", DEFORMATIONS)
def test_the_jacobians_are_numpys_bit_for_bit(tissue, A):
    x = _state(tissue, A, 0.15, 3)
    J = tissue.jacobians(x)
    np.testing.assert_array_equal(J, materials.jacobian_det(fem.deformation_gradients(tissue.ops, x)))
    x[tissue.mesh.triangles[0, 0]] = x[tissue.mesh.triangles[0, 1]]  # a collapsed element: J = 0, not skipped
    assert tissue.jacobians(x)[0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("A", DEFORMATIONS)
def test_one_pass_gradient_and_stiffness_equal_the_separate_loops(tissue, A):
    """compiled.energy_gradient_stiffness (the tangent predictor's) = energy_gradient + element_stiffness, bit for
    bit."""
    x = _state(tissue, A, 0.15, 4)
    U, g, Ke = compiled.energy_gradient_stiffness(tissue.ops, tissue.params, x, False)
    U0, g0 = compiled.energy_gradient(tissue.ops, tissue.params, x)
    assert U == U0 and np.array_equal(g, g0)
    assert np.array_equal(Ke, compiled.element_stiffness(tissue.ops, tissue.params, x, False))
    assert np.array_equal(tissue.energy_gradient_stiffness(x)[2], Ke)


def test_one_pass_gradient_and_stiffness_leave_inverted_elements_to_numpy(tissue):
    x = tissue.rest.copy()
    e = 0
    a, b, c = tissue.mesh.triangles[e]
    x[a] = x[b] + 2.0 * (x[c] - x[b])  # fold element 0 over its edge
    assert compiled.energy_gradient_stiffness(tissue.ops, tissue.params, x, False) is None


@pytest.mark.parametrize("seed", [0, 1])
def test_stiffness_times_equals_the_numpy_product(tissue, seed):
    """Tissue.stiffness_times runs `compiled.packed_times`: Σ_e K_e v_e as fem.packed_times has it."""
    x = _state(tissue, DEFORMATIONS[2], 0.15, seed)
    Ke = tissue.element_stiffness(x, project=bool(seed))
    v = np.random.default_rng(seed).standard_normal(x.size)
    ref = fem.packed_times(tissue.ops, Ke, v)
    assert np.allclose(tissue.stiffness_times(x, v, Ke), ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    if not seed:  # a v on a few nodes: the elements touching them alone give the same product
        local = tissue.cup_displacement(0)
        assert local.any()
        ref = fem.packed_times(tissue.ops, Ke, local)
        assert np.allclose(tissue.stiffness_times_near(x, local), ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


def test_projection_acts_and_is_psd(tissue):
    """Under compression the exact element Hessians are indefinite; the projected ones are PSD and differ."""
    x = _state(tissue, [[0.8, 0.1], [-0.05, 0.85]], 0.15, 3)
    Ke = fem.unpack(compiled.element_stiffness(tissue.ops, tissue.params, x, True))
    Kx = fem.unpack(compiled.element_stiffness(tissue.ops, tissue.params, x, False))
    lo = np.linalg.eigvalsh(Ke).min(axis=1) / np.abs(Ke).max(axis=(1, 2))
    assert lo.min() > -1e-12
    assert np.linalg.eigvalsh(Kx).min() < 0


def test_inverted_element_goes_to_the_numpy_policy(tissue):
    x = tissue.rest.copy()
    a, b, c = tissue.ops.triangles[0]
    x[a], x[b] = x[b].copy(), x[a].copy()  # turns the first triangle over
    assert compiled.energy_gradient(tissue.ops, tissue.params, x) is None
    assert compiled.element_stiffness(tissue.ops, tissue.params, x, True) is None
    assert tissue.energy_gradient(x, require_positive_J=True) == (float("inf"), None)
    U, g = tissue.energy_gradient(x)
    assert U == float("inf") and np.all(np.isfinite(g))
    assert np.all(np.isfinite(tissue.element_stiffness(x, project=True)))


def test_not_taken_where_the_numpy_path_answers():
    assert not _tissue("linear").compiled


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-0.6, 0.6), min_size=4, max_size=4), st.integers(0, 2**16))
def test_any_deformation_agrees_with_numpy(entries, seed):
    """Random affine deformations (with J > 0) plus noise: the two paths agree wherever the compiled one answers."""
    t = _FIBER
    A = np.eye(2) + np.reshape(entries, (2, 2))
    if np.linalg.det(A) < 0.2:
        return
    x = _state(t, A, 0.05, seed)
    fast = compiled.energy_gradient(t.ops, t.params, x)
    if fast is None:
        assert np.min(t.jacobians(x)) <= 0
        return
    U0, g0 = _numpy_gradient(t, x)
    assert fast[0] == pytest.approx(U0, rel=1e-12, abs=1e-12)
    assert np.allclose(fast[1], g0, rtol=1e-11, atol=1e-11 * np.abs(g0).max())
    K0 = _numpy_stiffness(t, x, True)
    assert np.allclose(compiled.element_stiffness(t.ops, t.params, x, True), K0, rtol=1e-11,
                       atol=1e-11 * np.abs(K0).max())


_FIBER = _tissue("neo_hookean_fiber", True)


@pytest.mark.parametrize("seed", range(5))
def test_feasible_step_is_where_the_first_element_turns_over(seed):
    """The largest α keeping every J > 0 along x + α dx: some element's J vanishes there and none before."""
    t = _FIBER
    rng = np.random.default_rng(seed)
    x = _state(t, np.eye(2), 0.05, seed)
    dx = rng.standard_normal(x.shape)
    alpha = t.max_feasible_step(x, dx)
    assert 0 < alpha < np.inf
    assert t.jacobians(x + (1 - 1e-9) * alpha * dx).min() > 0
    J_at = t.jacobians(x + alpha * dx)
    assert np.abs(J_at).min() <= 1e-8 * np.abs(t.jacobians(x)).max()
    # each element's own quadratic, by numpy's polynomial roots: the same first root
    F, dF = fem.deformation_gradients(t.ops, x), fem.deformation_gradients(t.ops, dx)
    roots = []
    for f, g in zip(F, dF):
        c = [g[0, 0] * g[1, 1] - g[0, 1] * g[1, 0],
             f[0, 0] * g[1, 1] + g[0, 0] * f[1, 1] - f[0, 1] * g[1, 0] - g[0, 1] * f[1, 0],
             f[0, 0] * f[1, 1] - f[0, 1] * f[1, 0]]
        r = np.roots(c)
        r = r[(np.abs(r.imag) < 1e-12) & (r.real > 0)].real
        roots.append(r.min() if r.size else np.inf)
    assert alpha == pytest.approx(min(roots), rel=1e-9)


def test_feasible_step_unbounded_for_rigid_translation_and_zero_motion():
    t = _FIBER
    x = _state(t, np.eye(2), 0.05, 0)
    assert t.max_feasible_step(x, np.zeros_like(x)) == np.inf
    assert t.max_feasible_step(x, np.tile([1.0, -2.0], (len(x), 1))) > 1e12  # dF is round-off only


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40).flatmap(lambda size: st.tuples(
    st.just(size), st.lists(st.tuples(st.integers(0, size - 1), st.integers(0, size - 1)), max_size=200))))
def test_the_csr_pattern_is_numpys_unique_of_the_keys(case):
    """`compiled.csr_pattern` (two counting sorts) gives np.unique's sorted keys and inverse, empty rows included."""
    size, entries = case
    rows = np.array([r for r, _ in entries], np.int64)
    cols = np.array([c for _, c in entries], np.int64)
    indptr, indices, slot = compiled.csr_pattern(rows, cols, size)
    unique, inverse = np.unique(rows * size + cols, return_inverse=True)
    r, c = np.divmod(unique, size)
    assert np.array_equal(indices, c) and indices.dtype == np.int32
    assert np.array_equal(slot, inverse.ravel())
    assert np.array_equal(indptr, np.concatenate([[0], np.cumsum(np.bincount(r, minlength=size))]))
