"""The compiled 3-D element loops (mechanics/compiled3d.py) against the numpy reference path (materials.solid3d).

Both evaluate the same closed forms, so energy, gradient and exact element
Hessians agree to round-off; an element the loops cannot take (inverted)
goes back to the numpy path, whose policy then holds; a slab uses the loops.
"""

import numpy as np
import pytest
import yaml

from scissor_cli.config import parse_config
from scissor_cli.experiments.build import build_model
from scissor_cli.layer3d.slab import SlabSpec, build_slab
from scissor_cli.mechanics import compiled3d, fem, materials
from tests.helpers import example_dict


def _slab(model, tension_only=False):
    data = example_dict()
    data["material"].update(model=model, fiber_tension_only=tension_only, eta_kPa=6.0)
    cfg = parse_config(yaml.safe_dump(data), "scene.yaml")
    scene, mesh, _ = build_model(cfg, mesh_scale=4.0)
    return build_slab(scene, mesh, SlabSpec(6.0, 3.0, levels_mm=(0.0, 1.5, 3.0, 6.0)))


@pytest.fixture(scope="module",
                params=[("neo_hookean", False), ("neo_hookean_fiber", False), ("neo_hookean_fiber", True)],
                ids=["neo_hookean", "fiber", "fiber_tension_only"])
def slab(request):
    s = _slab(*request.param)
    assert s.compiled
    return s


def _state(slab, A, noise, seed):
    rng = np.random.default_rng(seed)
    return slab.rest @ np.asarray(A, float).T + noise * rng.standard_normal(slab.rest.shape)


# stretch (fibers in tension), compression (fibers compressed), shear out of the plane, rest
DEFORMATIONS = [np.eye(3), [[1.15, 0.0, 0.0], [0.0, 0.9, 0.05], [0.0, 0.0, 0.97]],
                [[0.8, 0.1, 0.0], [-0.05, 0.85, 0.0], [0.1, 0.0, 1.1]],
                [[1.0, 0.0, 0.4], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]]


@pytest.mark.parametrize("A", DEFORMATIONS)
def test_same_energy_gradient_and_stiffness_as_numpy(slab, A):
    x = _state(slab, A, 0.05, 0)
    F = fem.deformation_gradients(slab.ops, x)
    psi, P, C = materials.evaluate(F, slab.params, order=2)
    g0 = fem.scatter_vector(slab.ops, fem.element_forces(slab.ops, P))
    K0 = fem.element_matrices(slab.ops, C)
    U, g = compiled3d.energy_gradient(slab.ops, slab.params, x)
    assert U == pytest.approx(float(psi @ slab.ops.volume), rel=1e-12)
    np.testing.assert_allclose(g, g0, rtol=1e-10, atol=1e-11 * np.abs(g0).max())
    Ke = compiled3d.element_stiffness(slab.ops, slab.params, x, False)
    np.testing.assert_allclose(Ke, K0, rtol=1e-10, atol=1e-11 * np.abs(K0).max())
    U1, g1, Ke1 = compiled3d.energy_gradient_stiffness(slab.ops, slab.params, x, False)
    assert U1 == U and np.array_equal(g1, g) and np.array_equal(Ke1, Ke)


def test_stiffness_is_the_derivative_of_the_gradient(slab):
    """K v against central differences of the compiled gradient (independent of the numpy path)."""
    x = _state(slab, DEFORMATIONS[1], 0.05, 1)
    v = np.random.default_rng(2).standard_normal(x.size)
    h = 1e-6
    gp = compiled3d.energy_gradient(slab.ops, slab.params, x + h * v.reshape(x.shape))[1]
    gm = compiled3d.energy_gradient(slab.ops, slab.params, x - h * v.reshape(x.shape))[1]
    Ke = compiled3d.element_stiffness(slab.ops, slab.params, x, False)
    Kv = fem.packed_times(slab.ops, Ke, v)
    np.testing.assert_allclose(Kv, (gp - gm) / (2 * h), rtol=1e-5, atol=1e-6 * np.abs(Kv).max())
    # the compiled product (`compiled.packed_times`, what Tissue.stiffness_times runs) is numpy's
    np.testing.assert_allclose(slab.stiffness_times(x, v, Ke), Kv, rtol=1e-12, atol=1e-12 * np.abs(Kv).max())
    # a v on a few nodes (a cup's stroke): the product from the elements touching them alone is the same
    local = np.zeros_like(v)
    local[3 * slab.cup_nodes[0][:, None] + np.arange(3)] = 1.0
    assert local.any()
    Kl = fem.packed_times(slab.ops, Ke, local)
    np.testing.assert_allclose(slab.stiffness_times_near(x, local), Kl, rtol=1e-12, atol=1e-12 * np.abs(Kl).max())


@pytest.mark.parametrize("A", DEFORMATIONS[1:])
def test_the_projected_stiffness_is_numpys(slab, A):
    """The loop projects each tangent by the numpy path's rule (`materials.psd`): the same packed Hessians to
    round-off, indefinite tangents included; the gradient of the same pass is the exact one's."""
    x = _state(slab, A, 0.05, 4)
    F = fem.deformation_gradients(slab.ops, x)
    C = materials.evaluate(F, slab.params, order=2)[2]
    Cp = materials.evaluate_projected(F, slab.params)[2]
    indefinite = np.linalg.eigvalsh(C)[:, 0] < -1e-6 * np.abs(C).max(axis=(1, 2))
    assert indefinite.any() or A is DEFORMATIONS[1]  # (stretch alone may leave every tangent definite)
    K0 = fem.element_matrices(slab.ops, Cp)
    Ke = compiled3d.element_stiffness(slab.ops, slab.params, x, True)
    np.testing.assert_allclose(Ke, K0, rtol=1e-8, atol=1e-10 * np.abs(K0).max())
    U, g, Ke1 = compiled3d.energy_gradient_stiffness(slab.ops, slab.params, x, True)
    assert np.array_equal(Ke1, Ke) and np.array_equal(g, compiled3d.energy_gradient(slab.ops, slab.params, x)[1])


def test_inverted_elements_go_to_numpy(slab):
    x = _state(slab, DEFORMATIONS[2], 0.05, 3)
    a, b, c, d = slab.ops.corners[:, 0]
    # an inverted tetrahedron: its first corner mirrored through the plane of the other three (J < 0 well
    # beyond round-off; a collapsed one, J = 0 exactly on paper, is tiny and of either sign in floating point)
    normal = np.cross(x[c] - x[b], x[d] - x[b])
    normal /= np.linalg.norm(normal)
    x[a] -= 2.0 * ((x[a] - x[b]) @ normal) * normal
    assert slab.jacobians(x)[0] < -0.1
    assert compiled3d.energy_gradient(slab.ops, slab.params, x) is None
    assert compiled3d.element_stiffness(slab.ops, slab.params, x, False) is None
    assert compiled3d.element_stiffness(slab.ops, slab.params, x, True) is None
    # the tissue then answers with the numpy path's policy: infinite energy, no crash
    U, _ = slab.energy_gradient(x)
    assert U == np.inf


@pytest.mark.parametrize("A", DEFORMATIONS)
def test_the_jacobians_are_numpys_bit_for_bit(slab, A):
    x = _state(slab, A, 0.05, 3)
    np.testing.assert_array_equal(slab.jacobians(x), materials.jacobian_det(fem.deformation_gradients(slab.ops, x)))
    x[slab.ops.corners[0, 0]] = x[slab.ops.corners[1, 0]]  # a collapsed tetrahedron: J = 0, not skipped
    assert slab.jacobians(x)[0] == pytest.approx(0.0, abs=1e-12)
