"""The element interface (`mechanics.elements`, docs/model.md §21): every element a class behind one interface.

Each registered element, in 2-D (the layer) and 3-D (its slab): shape
functions that partition unity and reproduce a linear field, a quadrature
that integrates it, gradients that give an affine field's gradient, point
location and probes that carry points back to themselves, meshio's name for
the cell. Then what `Tissue` asks of it: the material it holds, the
pattern it needs, and a new element written as a class beside its kin,
solved by the one equilibrium entry point with no change to `Tissue`.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from scissor_cli.config import parse_config
from scissor_cli.experiments.build import build_model
from scissor_cli.layer3d.slab import SlabSpec, build_slab
from scissor_cli.mechanics import elements, materials
from scissor_cli.mechanics.tissue import tissue_from_boundary
from scissor_cli.mesh.mesh import meshio_cell_type
from scissor_cli.mesh.probe import target_positions
from scissor_cli.solvers.equilibrium import solve_equilibrium
from tests.helpers import example_dict


def _layer(element: str):
    data = example_dict()
    data["material"].update(nu=0.49)
    data["tissue"]["mesh"].update(element=element, scale=4.0)
    data["solver"]["kind"] = "newton"
    return build_model(parse_config(yaml.safe_dump(data), "scene.yaml"), mesh_scale=4.0)[2]


@pytest.fixture(scope="module", params=list(elements.ELEMENTS))
def tissues(request):
    """A coarse layer on the element, and its slab (h = 10 mm, two layers of tetrahedra)."""
    layer = _layer(request.param)
    h = float(layer.scene.thickness_mm)
    spec = SlabSpec(h, 0.5 * h, chest_wall_fixed=True, cup_holds_z=True, max_layer_mm=h / 2, levels_mm=(0.0, 5.0))
    return layer, build_slab(layer.scene, layer.mesh, spec, model=layer.params.model, element=request.param)


def _points_in_cells(tissue, count: int, seed: int = 0):
    """Random cells (K,), barycentric coordinates (K, d + 1) and their rest points (K, d)."""
    rng = np.random.default_rng(seed)
    cells = rng.integers(0, tissue.mesh.n_elements, count)
    bary = rng.dirichlet(np.ones(tissue.dim + 1), count)
    points = np.einsum("kj,kjd->kd", bary, tissue.rest[tissue.ops.triangles[cells]])
    return cells, bary, points


@pytest.mark.parametrize("which", [0, 1], ids=["layer", "slab"])
def test_the_geometry_every_element_answers(tissues, which):
    tissue = tissues[which]
    element, d = tissue.element, tissue.dim
    assert isinstance(element, elements.ELEMENTS[element.name])
    assert element.nodes_per_element == tissue.ops.triangles.shape[1] == d + 1
    assert element.cell_type == ("triangle" if d == 2 else "tetra")
    # the quadrature's weights add to 1 and the shape functions partition unity at its points
    points, weights = element.quadrature()
    assert weights.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(element.shape_functions(points).sum(axis=1), 1.0)
    # an affine field u = A X + b: its nodal values through ∇N give A on every element, and at the quadrature
    # points through N its value there
    rng = np.random.default_rng(1)
    A, b = rng.standard_normal((d, d)), rng.standard_normal(d)
    u = tissue.rest @ A.T + b  # (N, d)
    grads = np.einsum("mad,mai->mid", element.shape_gradients(), u[tissue.ops.triangles])
    np.testing.assert_allclose(grads, np.broadcast_to(A, grads.shape), atol=1e-9 * np.abs(A).max())
    X = np.einsum("qa,mad->mqd", points, tissue.rest[tissue.ops.triangles])
    at_points = np.einsum("qa,mai->mqi", element.shape_functions(points), u[tissue.ops.triangles])
    np.testing.assert_allclose(at_points, X @ A.T + b, atol=1e-9)


@pytest.mark.parametrize("which", [0, 1], ids=["layer", "slab"])
def test_locate_and_probe_carry_points_back_to_themselves(tissues, which):
    tissue = tissues[which]
    cells, bary, points = _points_in_cells(tissue, 40)
    found, coords = tissue.element.locate(tissue.rest, points)
    # a point on a shared face may be found in the neighbour: where it lands is what must hold
    landed = np.einsum("kj,kjd->kd", coords, tissue.rest[tissue.ops.triangles[found]])
    np.testing.assert_allclose(landed, points, atol=1e-9)
    assert coords.min() >= -1e-9
    probe = tissue.element.probe(tissue.rest, points)
    np.testing.assert_allclose(target_positions(probe, tissue.rest), points, atol=1e-9)
    # carried by a deformation: the probe interpolates the element's field, here an affine one exactly
    A = np.eye(tissue.dim) + 0.1 * np.arange(tissue.dim**2).reshape(tissue.dim, tissue.dim) / tissue.dim**2
    np.testing.assert_allclose(target_positions(probe, tissue.rest @ A.T), points @ A.T, atol=1e-9)
    with pytest.raises(ValueError, match="outside"):
        tissue.element.locate(tissue.rest, tissue.rest.max(axis=0)[None] + 10.0)


def test_meshio_names_the_cells_export_writes():
    assert [meshio_cell_type(d, n) for d, n in ((2, 3), (3, 4), (2, 6), (3, 10))] == \
        ["triangle", "tetra", "triangle6", "tetra10"]
    with pytest.raises(ValueError, match="5 nodes"):
        meshio_cell_type(3, 5)


@pytest.mark.parametrize("which", [0, 1], ids=["layer", "slab"])
def test_the_tissue_asks_the_element(tissues, which):
    tissue = tissues[which]
    element = tissue.element
    assert tissue.params is element.params
    # a coupling beyond the elements needs pairs beyond theirs, and only then
    assert (element.extra_pairs(tissue.free_index, upper=True) is None) == element.per_element
    assert element.per_element == (element.name == "p1")
    # another material swaps the element's with the tissue's, and keeps what depends on the mesh alone
    true = tissue.with_material(E_scale=2.0)
    assert type(true.element) is type(element) and true.params is true.element.params
    np.testing.assert_allclose(true.params.mu, 2.0 * tissue.params.mu)
    if isinstance(element, elements.Nodal):
        assert true.element.volume is element.volume
        np.testing.assert_allclose(true.element.kappa, 2.0 * element.kappa)


def test_an_unknown_element_is_refused_naming_the_allowed_ones():
    layer = _layer("p1")
    with pytest.raises(ValueError, match="allowed values: p1, nodal"):
        elements.build("p2", layer.ops, layer.params)


@dataclasses.dataclass(frozen=True)
class _Doubled(elements.P1):
    """A toy element: p1 with every modulus doubled (a new element is a class; `Tissue` is not touched)."""

    name = "doubled"

    @property
    def element_params(self):
        p = self.params
        return materials.MaterialParams(p.model, 2 * p.mu, 2 * p.kappa, 2 * p.lam, 2 * p.eta, p.fiber, p.tension_only)


def test_a_new_element_is_a_class_the_solvers_take_unchanged():
    """A held-only problem's answer does not depend on the moduli' scale: the doubled element gives p1's positions,
    at twice the energy, through `Tissue` and the one equilibrium entry point as they are."""
    layer = _layer("p1")
    doubled = tissue_from_boundary(layer.scene, layer.mesh, layer.ops,
                                   (layer.element_E_kPa, layer.fiber, layer.params), layer.fixed_nodes,
                                   layer.cup_nodes, layer.cup_axes, layer.dirichlet_dofs)
    doubled = dataclasses.replace(doubled, element=_Doubled(layer.ops, layer.params), factor_cache={})
    strokes = np.full(layer.n_cups, 2.0)
    x1 = solve_equilibrium(layer, strokes, method="newton").x
    x2 = solve_equilibrium(doubled, strokes, method="newton").x
    np.testing.assert_allclose(x2, x1, atol=1e-6)
    assert doubled.energy(x2) == pytest.approx(2.0 * layer.energy(x2), rel=1e-9)
