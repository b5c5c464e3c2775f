"""Tests of the 3-D material kernels of scissor_cli.mechanics.materials:
closed forms against finite differences, agreement with the 2-D plane-strain
kernels on F = diag(F2, 1), rest state, frame invariance, inversion handling,
the projected tangent, and 3-component fibers in the parameters."""

import warnings

import numpy as np
import pytest

from scissor_cli.mechanics import materials as mat


def test_material_params_accepts_3d_fibers():
    p = mat.material_params("neo_hookean_fiber", [10.0, 20.0], 0.45, 5.0, [[0.0, 3.0, 4.0], [2.0, 0.0, 0.0]])
    assert p.fiber.shape == (2, 3)
    np.testing.assert_allclose(p.fiber, [[0.0, 0.6, 0.8], [1.0, 0.0, 0.0]], rtol=1e-15)
    shared = mat.material_params("neo_hookean_fiber", np.ones(4), 0.3, 1.0, [1.0, 2.0, 2.0])
    np.testing.assert_allclose(shared.fiber, np.tile([1 / 3, 2 / 3, 2 / 3], (4, 1)), rtol=1e-15)
    assert shared.take(np.array([3, 1])).fiber.shape == (2, 3)
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean_fiber", 10.0, 0.3, 1.0, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean_fiber", 10.0, 0.3, 1.0, [[1.0, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError):
        mat.material_params("neo_hookean_fiber", 10.0, 0.3, 1.0, [np.inf, 0.0, 0.0])
    with pytest.raises(ValueError):
        mat.MaterialParams("neo_hookean", np.ones(2), np.ones(2), np.ones(2), np.zeros(2), np.ones((2, 4)))
    with pytest.raises(ValueError):
        mat.MaterialParams("neo_hookean", np.ones(2), np.ones(2), np.ones(2), np.zeros(2), np.ones((3, 3)))
    # A 3-component fiber has no plane-strain meaning: the 2-D kernels refuse it.
    with pytest.raises(ValueError, match=r"\(M, 2\) fibers"):
        mat.evaluate(np.broadcast_to(np.eye(2), (2, 2, 2)), p)
    with pytest.raises(ValueError, match=r"\(M, 2\) fibers"):
        mat.evaluate_projected(np.broadcast_to(np.eye(2), (2, 2, 2)), p)
