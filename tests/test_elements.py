"""Elements that do not lock (docs/model.md §21): the averaged nodal volume element `nodal` against `p1`.

The nodal volume term's gradient and tangent against finite differences in
2-D and 3-D (the exact coupling Bᵀ W B assembled into the joined pattern
and applied as a product), the patch test, Newton's quadratic ending, and
locking measured against an independent quadratic solve (scikit-fem's P2,
benchmarks/quadratic_reference.py): on the 2-D example at ν 0.499 `nodal`
is within 3 % of P2 where `p1` is not, and on a 3-D slab its error keeps to
a small fraction of `p1`'s error there against the mixed
(Taylor–Hood) reference, which passes the patch test and does not lock in
3-D, where P2 alone does.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import yaml

from scissor_cli import runtime
from scissor_cli.config import parse_config
from scissor_cli.experiments.build import build_model
from scissor_cli.layer3d.slab import SlabSpec, build_slab
from scissor_cli.mechanics.tissue import build_tissue
from scissor_cli.mesh.probe import probe_points, probe_targets, target_positions
from scissor_cli.solvers.equilibrium import solve_equilibrium
from scissor_cli.solvers.newton import solve_newton
from tests.helpers import benchmark_module, example_dict, rates_above_roundoff


def _cfg(element="nodal", scale=3.0, **material):
    data = example_dict()
    data["material"].update(material)
    data["tissue"]["mesh"].update(element=element, scale=scale)
    data["solver"]["kind"] = "newton"
    return parse_config(yaml.safe_dump(data), "scene.yaml")


def _slab(tissue, element, levels_mm=(0.0, 5.0, 10.0)):
    """The layer's slab held at the chest wall, the cup holding z, on z levels `levels_mm` (h = 10 mm)."""
    h = float(tissue.scene.thickness_mm)
    spec = SlabSpec(h, 0.5 * h, chest_wall_fixed=True, cup_holds_z=True, max_layer_mm=h / 2, levels_mm=levels_mm)
    return build_slab(tissue.scene, tissue.mesh, spec, model=tissue.params.model, element=element)


@pytest.fixture(scope="module", params=["neo_hookean_fiber", "linear"])
def tissues(request):
    """A coarse layer with `nodal` and its slab, of one material model."""
    _, _, layer = build_model(_cfg(model=request.param, nu=0.49, eta_kPa=5.0), mesh_scale=4.0)
    return layer, _slab(layer, "nodal")


def _perturbed(tissue, seed=0):
    rng = np.random.default_rng(seed)
    x = tissue.apply_strokes(tissue.rest, np.array([2.0]))
    return x + 0.02 * rng.standard_normal(x.shape)


@pytest.mark.parametrize("which", [0, 1], ids=["layer", "slab"])
def test_gradient_and_tangent_match_finite_differences(tissues, which):
    tissue = tissues[which]
    x = _perturbed(tissue)
    rng = np.random.default_rng(1)
    v = rng.standard_normal(x.size)
    h = 1e-6
    U, g = tissue.energy_gradient(x)
    up = tissue.energy((x.ravel() + h * v).reshape(x.shape))
    um = tissue.energy((x.ravel() - h * v).reshape(x.shape))
    assert abs((up - um) / (2 * h) - g @ v) <= 1e-6 * max(abs(g @ v), 1e-9) + 1e-9
    assert tissue.energy(x) == pytest.approx(U, rel=1e-12)
    # the tangent: K v against the gradient's central difference; assembled K (full and upper) against K v
    gp = tissue.energy_gradient((x.ravel() + h * v).reshape(x.shape))[1]
    gm = tissue.energy_gradient((x.ravel() - h * v).reshape(x.shape))[1]
    Kv = tissue.stiffness_times(x, v)
    fd = (gp - gm) / (2 * h)
    assert np.abs(Kv - fd).max() <= 1e-5 * np.abs(fd).max()
    free = tissue.free_dofs
    w = np.zeros(x.size)
    w[free] = v[free]
    K = tissue.stiffness_free(x)
    np.testing.assert_allclose(K @ v[free], tissue.stiffness_times(x, w)[free], rtol=0, atol=1e-9 * np.abs(Kv).max())
    upper = tissue.stiffness_free(x, upper=True)
    np.testing.assert_allclose((upper + sp.triu(upper, 1).T) @ v[free], K @ v[free], rtol=0,
                               atol=1e-9 * np.abs(Kv).max())
    # energy_gradient_stiffness hands back the same three
    U2, g2, Ke = tissue.energy_gradient_stiffness(x)
    assert U2 == pytest.approx(U, rel=1e-12)
    np.testing.assert_allclose(tissue.stiffness_times(x, v, Ke), Kv, rtol=0, atol=1e-9 * np.abs(Kv).max())
    # K v from the elements near a cup equals the full product
    u_c = tissue.cup_displacement(0)
    np.testing.assert_allclose(tissue.stiffness_times_near(x, u_c), tissue.stiffness_times(x, u_c), rtol=0,
                               atol=1e-9 * np.abs(Kv).max())


def test_the_compiled_whole_gradient_is_the_term_by_term_one(tissues):
    """In 3-D every term's gradient comes from three compiled passes (`nodal_gradient.energy_gradient`): the same U
    and ∇U as the per-element kernels plus the nodal terms, the same bits on one thread or two; it declines where
    that path owns the policy."""
    slab = tissues[1]
    x = _perturbed(slab)
    whole = slab.element.compiled_energy_gradient(x)
    if slab.params.model == "linear":  # (its constant tangent: the term-by-term path serves)
        assert whole is None
        return
    U, g = whole
    threads = runtime.threads()
    try:
        runtime.set_threads(3 - threads)
        U2, g2 = slab.element.compiled_energy_gradient(x)
    finally:
        runtime.set_threads(threads)
    assert U2 == U and np.array_equal(g2, g)
    U0, g0 = slab.element.add_gradient(x, *slab._kernels.energy_gradient(slab.ops, slab.element_params, x))
    assert U == pytest.approx(U0, rel=1e-12)
    np.testing.assert_allclose(g, g0, rtol=0, atol=1e-11 * np.abs(g0).max())
    inverted = x.copy()
    e = slab.ops.triangles[0]
    inverted[e[0]], inverted[e[1]] = x[e[1]], x[e[0]]
    assert slab.element.compiled_energy_gradient(inverted) is None
    assert slab.energy_gradient(inverted, require_positive_J=True) == (float("inf"), None)
    assert tissues[0].element.compiled_energy_gradient(_perturbed(tissues[0])) is None  # 2-D: term by term


def test_projected_tangent_is_positive_semidefinite(tissues):
    tissue = tissues[0]
    K = tissue.stiffness_free(_perturbed(tissue), project=True).toarray()
    eig = np.linalg.eigvalsh(0.5 * (K + K.T))
    assert eig.min() >= -1e-9 * eig.max()


@pytest.mark.parametrize("which", [0, 1], ids=["layer", "slab"])
def test_patch_test_a_uniform_deformation_is_in_equilibrium(which):
    """x = F X everywhere: every nodal volume is det F times its rest one, so the interior forces cancel and the
    energy is p1's (a homogeneous material: the scene's obstacles take the tissue's stiffness)."""
    data = example_dict()
    for o in data.get("obstacles", []):
        o["stiffness_factor"] = 1.0
    data["tissue"]["mesh"].update(element="nodal", scale=4.0)
    data["solver"]["kind"] = "newton"
    _, _, layer = build_model(parse_config(yaml.safe_dump(data), "scene.yaml"))
    tissue = layer if which == 0 else _slab(layer, "nodal")
    p1 = build_tissue(layer.scene, layer.mesh) if which == 0 else _slab(layer, "p1")
    d = tissue.dim
    F = np.eye(d) + np.array([[0.04, 0.03, -0.02], [-0.01, -0.05, 0.02], [0.02, 0.01, 0.03]])[:d, :d]
    x = tissue.rest @ F.T
    U, g = tissue.energy_gradient(x)
    interior = np.ones(tissue.mesh.n_nodes, bool)
    interior[_boundary_nodes(tissue.ops.triangles)] = False
    gi = g.reshape(-1, d)[interior]
    assert np.abs(gi).max() <= 1e-9 * np.abs(g).max()
    assert U == pytest.approx(p1.energy(x), rel=1e-10)


def _boundary_nodes(cells: np.ndarray) -> np.ndarray:
    """The nodes on faces (edges in 2-D) that belong to one simplex only."""
    n = cells.shape[1]
    faces = np.sort(np.concatenate([np.delete(cells, k, axis=1) for k in range(n)]), axis=1)
    unique, count = np.unique(faces, axis=0, return_counts=True)
    return np.unique(unique[count == 1])


def test_newton_ends_quadratically_on_the_nodal_element():
    _, _, tissue = build_model(_cfg(scale=1.0))
    r = solve_newton(tissue, np.array([10.0]), tol=1e-10)
    assert r.converged and r.residual <= 1e-10
    rates = rates_above_roundoff(r.history)
    assert rates[-1] < 1e-3, r.history
    assert tissue.jacobians(r.x).min() > 0


def _reference():
    return benchmark_module("quadratic_reference")


def _reference_problem(tissue, stroke_mm: float = 1.0) -> tuple[tuple, np.ndarray]:
    """(the quadratic references' arguments, the targets (K, d)) of a tissue's mesh, held nodes and cup pushed
    `stroke_mm`, linear elasticity at its ν; a slab's targets at mid-height."""
    points = np.array([t.rest for t in tissue.scene.targets])
    d = tissue.dim
    if d == 3:
        z = np.full((len(points), 1), 0.5 * float(tissue.scene.thickness_mm))
        points = np.hstack([points[:, :2], z])
    moved = tissue.apply_strokes(tissue.rest, np.array([stroke_mm])) - tissue.rest
    nu = float(tissue.scene.material.nu)
    return (*_reference().mesh_and_held(tissue), moved, tissue.element_E_kPa, nu, points), points


def _lesion_errors(tissues: dict, stroke_mm: float = 1.0, mixed: bool = False) -> dict:
    """{element: |u − u_ref| / |u_ref| (K,)} at the scene's targets for tissues on one mesh with one boundary
    (linear elasticity, the cup pushed `stroke_mm`): one quadratic solve for all of them, P2's or (`mixed`)
    Taylor–Hood's."""
    pytest.importorskip("skfem")
    tissue = next(iter(tissues.values()))
    args, points = _reference_problem(tissue, stroke_mm)
    at = _reference().solve_mixed(*args).at_points if mixed else _reference().solve_p2(*args)[1]
    nodes, cells = tissue.mesh.nodes, tissue.ops.triangles
    probe = probe_targets(tissue.mesh, points) if tissue.dim == 2 else probe_points(nodes, cells, points)
    errors = {}
    for name, t in tissues.items():
        x = solve_equilibrium(t, np.array([stroke_mm]), method="newton").x
        mine = target_positions(probe, x) - points
        errors[name] = np.linalg.norm(mine - at, axis=1) / np.linalg.norm(at, axis=1)
    return errors


@pytest.mark.parametrize("dim", [2, 3])
def test_the_mixed_reference_passes_the_patch_test(dim):
    """Taylor–Hood at ν 0.499 with a uniform strain held on the boundary: the displacement is that linear field
    inside too, and the pressure λ tr ε (a constant), each to round-off."""
    skfem = pytest.importorskip("skfem")
    mesh = (skfem.MeshTri().refined(3) if dim == 2 else skfem.MeshTet().refined(2))
    nodes, cells = mesh.p.T * 20.0, mesh.t.T
    G = np.array([[0.02, -0.01, 0.005], [0.015, -0.03, 0.0], [0.0, 0.01, 0.01]])[:dim, :dim]
    held = np.zeros((len(nodes), dim), bool)
    held[mesh.boundary_nodes()] = True
    inside = np.setdiff1d(np.arange(len(nodes)), mesh.boundary_nodes())
    points = 0.5 * (nodes[cells[:3, 0]] + nodes[cells[:3, 1]])  # edge midpoints of three cells: P2's own nodes
    nu, E = 0.499, 10.0
    solved = _reference().solve_mixed(nodes, cells, held, nodes @ G.T, E, nu, points)
    assert np.allclose(solved.vertices[inside], nodes[inside] @ G.T, atol=1e-9)
    assert np.allclose(solved.at_points, points @ G.T, atol=1e-9)
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    assert np.allclose(solved.pressure, lam * np.trace(G), rtol=1e-7)


def test_the_mixed_reference_does_not_lock_in_3d_where_p2_does():
    """On the slab, from ν 0.49 to 0.4999 a lesion's move under the cup changes by a few per cent with
    Taylor–Hood (the physics: a little less compressible) and by several times that with P2 alone, whose
    10-node tetrahedra lock as ν → 1/2; the Schur complement's iterations do not grow."""
    pytest.importorskip("skfem")
    moves, iterations = {}, {}
    for nu in (0.49, 0.4999):
        _, _, layer = build_model(_cfg(scale=3.0, model="linear", nu=nu))
        args, _ = _reference_problem(_slab(layer, "p1"))  # two layers of tetrahedra: P2 locks the more
        mixed = _reference().solve_mixed(*args)
        moves["mixed", nu] = np.linalg.norm(mixed.at_points, axis=1)
        moves["p2", nu] = np.linalg.norm(_reference().solve_p2(*args)[1], axis=1)
        iterations[nu] = mixed.iterations
    change = {k: np.max(np.abs(moves[k, 0.4999] / moves[k, 0.49] - 1)) for k in ("mixed", "p2")}
    assert change["mixed"] < 0.05, change
    assert change["p2"] > 2 * change["mixed"], change
    assert iterations[0.4999] <= iterations[0.49] + 10, iterations


def test_nodal_does_not_lock_on_the_2d_example_at_nu_0499():
    """The 2-D example at ν 0.499, a 1 mm push: `nodal` within 3 % of quadratic triangles on the same mesh."""
    _, _, nodal = build_model(_cfg(scale=1.0, model="linear", nu=0.499))
    errors = _lesion_errors({"nodal": nodal, "p1": build_tissue(nodal.scene, nodal.mesh)})
    err_nodal, err_p1 = errors["nodal"], errors["p1"]
    assert err_nodal.max() < 0.03, err_nodal
    assert err_p1.max() > 0.10, err_p1  # the locking it removes


def test_nodal_removes_most_of_the_locking_on_a_slab():
    """Linear tetrahedra lock: their error against the mixed (Taylor–Hood) reference on the same slab grows with
    ν to several times the move at ν 0.499 (the slab held at its chest wall). The nodal element's stays within
    a few per cent at a compressible ν and a small fraction of p1's at ν 0.499, where on a slab this coarse it
    grows too (a mesh of few nodes cannot free every volume mode). Against P2 alone the comparison would
    mislead: 10-node tetrahedra lock at ν 0.499 themselves."""
    errs = {}
    for nu in (0.3, 0.499):
        _, _, layer = build_model(_cfg(scale=3.0, model="linear", nu=nu))
        levels = (0.0, 2.5, 5.0, 7.5, 10.0)
        for element, e in _lesion_errors({e: _slab(layer, e, levels) for e in ("p1", "nodal")}, mixed=True).items():
            errs[element, nu] = e.max()
    assert errs["nodal", 0.3] < 0.05, errs
    assert errs["p1", 0.499] > errs["p1", 0.3] + 0.5, errs
    assert errs["nodal", 0.499] < 0.2, errs
    assert errs["nodal", 0.499] < 0.1 * errs["p1", 0.499], errs


@pytest.mark.parametrize("dim", [2, 3])
def test_pressure_hessians_in_closed_form_equal_gt_q_g(dim):
    """The compiled p̄ ∂²v_e/∂x² equals V p̄ Gᵀ Q(F) G assembled from ∂²det F/∂F² by the reference element matrices."""
    from scissor_cli.mechanics import fem, nodal

    rng = np.random.default_rng(3)
    nodes = np.vstack([np.zeros(dim), np.eye(dim)]) + 0.1 * rng.random((dim + 1, dim))
    cells = np.arange(dim + 1)[None, :]
    ops = fem.simplex_operators(nodes, cells)
    if ops.volume[0] < 0:  # (positively oriented by construction; kept as a guard)
        pytest.skip("negative orientation")
    F = np.eye(dim)[None] + 0.3 * rng.standard_normal((1, dim, dim))
    pressure = np.array([2.5])
    state = nodal.NodalState(np.ones(dim + 1), np.zeros(dim + 1), pressure, np.zeros((1, dim + 1, dim)))
    got = nodal.element_hessians(ops, F, state, linear=False)
    want = fem.element_matrices(ops, nodal.det_hessian(F), scale=ops.volume * pressure)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
