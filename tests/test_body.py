"""A 3-D body end to end (docs/model.md §19): meshed, solved, checked against an independent equilibrium, exported.

The scene: a dome (radius 40, height 25 mm) with a skin shell, two lesions,
a vessel beside one and a cyst, two cups on the skin, two forward cases —
coarse, so the module's one run (through the API in this process: `scissor simulate`'s own `api.run`) takes
seconds. (The body's run as a process: tests/test_golden.py's dome.)
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import yaml

from scissor_cli.config import parse_config
from scissor_cli.experiments.build import body_model
from scissor_cli.mechanics.nodal import ELEMENT_SHARE
from scissor_cli.mesh.probe import target_positions
from scissor_cli.solvers.equilibrium import solve_equilibrium
from scissor_cli.solvers.jacobian import cup_target_jacobian

from figure_checks import assert_png_drawn
from helpers import cli_here, simulate_here, write_scene
from test_cli import run_cli

SCENE = {
    "name": "small-dome",
    "seed": 3,
    "tissue": {"shape": "dome", "radius_mm": 40.0, "height_mm": 25.0, "fixed": ["base"],
               "skin": {"thickness_mm": 2.0, "E_kPa": 40.0}, "mesh": {"max_edge_mm": 8.0, "min_edge_mm": 2.5}},
    "material": {"model": "neo_hookean_fiber", "E_kPa": 10.0, "nu": 0.45, "eta_kPa": 5.0, "fiber_angle_deg": 30.0},
    "cups": [
        {"name": "side", "contact_mm": [0.0, 38.5, 8.0], "radius_mm": 5.0, "stroke_mm": [-10.0, 10.0]},
        {"name": "front", "contact_mm": [38.5, 0.0, 8.0], "radius_mm": 5.0, "stroke_mm": [-10.0, 10.0]},
    ],
    "targets": [
        {"name": "T1", "position_mm": [5.0, 10.0, 10.0], "radius_mm": 3.0, "stiffness_factor": 3.0},
        {"name": "T2", "position_mm": [-10.0, -5.0, 8.0], "radius_mm": 3.0},
    ],
    "obstacles": [
        {"name": "vessel", "tube": {"points_mm": [[12.0, 16.0, 10.0], [30.0, 16.0, 10.0]], "radius_mm": 1.5},
         "stiffness_factor": 3.0},
        {"name": "cyst", "sphere": {"center_mm": [10.0, -15.0, 8.0], "radius_mm": 3.0}},
    ],
    "needle": {"direction": [-1.0, 0.0, 0.0]},
    "solver": {"kind": "newton"},
    "robot": {"layer_origin_mm": [100.0, 215.0, 200.0]},
    "forward": [{"name": "push", "strokes": {"side": 6.0}}, {"name": "both", "strokes": {"side": -4.0, "front": 5.0}}],
    "trials": {"count": 0},
}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("body")
    out = simulate_here(tmp, SCENE)
    return tmp / "run.yaml", out


def _deviatoric_stress(F, mu, eta, fiber):
    """P (M, 3, 3) kPa of Ψ_dev = μ/2 (J^{-2/3} I1 − 3) + η/2 (I4 − 1)² (§3's energy without its volume term)."""
    J = np.linalg.det(F)
    FinvT = np.transpose(np.linalg.inv(F), (0, 2, 1))
    I1 = np.einsum("mij,mij->m", F, F)
    Fa = np.einsum("mij,mj->mi", F, fiber)
    I4 = np.einsum("mi,mi->m", Fa, Fa)
    P = (mu / 2 * J ** (-2 / 3))[:, None, None] * (2 * F - (2 / 3) * I1[:, None, None] * FinvT)
    return P + (2 * eta * (I4 - 1))[:, None, None] * np.einsum("mi,mj->mij", Fa, fiber)


def _independent_gradient(nodes, tets, x, E, nu, eta, fiber, element, share):
    """∇U (N, 3) mN of the §3 energy on linear tetrahedra, written out here from the model's formulas: for `p1`
    Ψ = Ψ_dev + κ/2 (J − 1)² per element; for `nodal` (§21) α Σ_e V_e Ψ_dev(F_e) + (1 − α) Σ_a V_a Ψ_dev(F̄_a) +
    Σ_a V_a κ_a/2 (J_a − 1)², every nodal quantity the rest-volume average over the node's elements (the fiber
    normalised), α = `share`. Each term's force as an element stress (first Piola–Kirchhoff), then nodal forces."""
    X, Y = nodes[tets], x[tets]  # (M, 4, 3)
    Dm = np.transpose(X[:, 1:] - X[:, :1], (0, 2, 1))  # columns are edges
    Ds = np.transpose(Y[:, 1:] - Y[:, :1], (0, 2, 1))
    B = np.linalg.inv(Dm)
    F = Ds @ B
    V = np.abs(np.linalg.det(Dm)) / 6.0
    J = np.linalg.det(F)
    cof = J[:, None, None] * np.transpose(np.linalg.inv(F), (0, 2, 1))
    mu, kappa = E / (2 * (1 + nu)), E / (3 * (1 - 2 * nu))
    if element == "p1":
        P = _deviatoric_stress(F, mu, eta * np.ones_like(E), fiber) + (kappa * (J - 1))[:, None, None] * cof
    else:
        def average(values):  # (M, ...) -> (N, ...): Σ_{e∋a} V_e values_e / (4 V_a)
            out = np.zeros((len(nodes),) + values.shape[1:])
            for a in range(4):
                np.add.at(out, tets[:, a], V.reshape((-1,) + (1,) * (values.ndim - 1)) * values / 4)
            return out / V_a.reshape((-1,) + (1,) * (values.ndim - 1))

        V_a = np.zeros(len(nodes))
        for a in range(4):
            np.add.at(V_a, tets[:, a], V / 4)
        J_a, kappa_a, mu_a = average(J), average(kappa), average(mu)
        fiber_a = average(fiber)
        fiber_a /= np.linalg.norm(fiber_a, axis=1, keepdims=True)
        P_a = (1 - share) * _deviatoric_stress(average(F), mu_a, eta * np.ones_like(mu_a), fiber_a)
        p_a = kappa_a * (J_a - 1)
        P = share * _deviatoric_stress(F, mu, eta * np.ones_like(E), fiber)
        P += P_a[tets].mean(axis=1) + p_a[tets].mean(axis=1)[:, None, None] * cof
    H = V[:, None, None] * P @ np.transpose(B, (0, 2, 1))  # forces on corners 1..3 as columns
    forces = np.concatenate([-H.sum(axis=2, keepdims=True), H], axis=2)  # (M, 3, 4)
    g = np.zeros_like(x)
    for a in range(4):
        np.add.at(g, tets[:, a], forces[:, :, a])
    return g


def test_every_forward_case_is_an_equilibrium_recomputed_from_the_results(run):
    _, out = run
    with h5py.File(out / "results.h5", "r") as f:
        nodes, tets = f["mesh/nodes"][()], f["mesh/tetrahedra"][()]
        E, fiber = f["mesh/element_E_kPa"][()], f["mesh/fiber"][()]
        element = f["mesh"].attrs["element"]
        nu, eta = float(f["material"].attrs["nu"]), float(f["material"].attrs["eta_kPa"])
        held = np.concatenate([f["mesh/fixed_nodes"][()]] + [f[f"cups/{c}/nodes"][()] for c in f["cups"]])
        cases = {c: f[f"forward/{c}/displacement"][()] for c in f["forward"]}
        assert f["mesh"].attrs["min_dihedral_deg"] >= 8.0
        assert f["/"].attrs["status"] == "complete"
    assert set(cases) == {"push", "both"}
    free = np.setdiff1d(np.arange(len(nodes)), held)
    for name, u in cases.items():
        g = _independent_gradient(nodes, tets, nodes + u, E, nu, eta, fiber, element, ELEMENT_SHARE)
        reaction = np.linalg.norm(g[held])
        assert reaction > 1.0  # the cups do push
        assert np.linalg.norm(g[free]) <= 1e-3 * reaction, name


def test_the_base_is_held_and_the_patches_move_rigidly_along_their_axes(run):
    _, out = run
    with h5py.File(out / "results.h5", "r") as f:
        nodes = f["mesh/nodes"][()]
        fixed = f["mesh/fixed_nodes"][()]
        u = f["forward/both/displacement"][()]
        strokes = dict(f["forward/both/strokes"].attrs)
        for cup in ("side", "front"):
            patch, axis = f[f"cups/{cup}/nodes"][()], f[f"cups/{cup}"].attrs["axis"]
            np.testing.assert_allclose(u[patch], np.tile(strokes[cup] * axis, (len(patch), 1)), atol=1e-12)
            contact = f[f"cups/{cup}"].attrs["contact"]
            assert np.all(np.linalg.norm(nodes[patch] - contact, axis=1) <= 5.0 + 1e-9)
    assert np.all(np.abs(nodes[fixed, 2]) < 1e-9) and len(fixed) > 20
    assert np.all(u[fixed] == 0.0)


def test_each_lesion_and_obstacle_is_a_region_of_its_own_volume(run):
    _, out = run
    with h5py.File(out / "results.h5", "r") as f:
        nodes, tets, region = f["mesh/nodes"][()], f["mesh/tetrahedra"][()], f["mesh/region"][()]
        names = [str(n) for n in f["mesh"].attrs["regions"]]
        E = f["mesh/element_E_kPa"][()]
    assert names == ["body", "skin", "T1", "T2", "vessel", "cyst"]
    p = nodes[tets]
    volume = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0
    assert np.all(volume > 0)
    for name, r in (("T1", 3.0), ("T2", 3.0), ("cyst", 3.0)):
        v = volume[region == names.index(name)].sum()
        assert v == pytest.approx(4 / 3 * np.pi * r ** 3, rel=0.10), name
    np.testing.assert_allclose(E[region == names.index("T1")], 30.0)
    np.testing.assert_allclose(E[region == names.index("skin")], 40.0)
    np.testing.assert_allclose(E[region == names.index("body")], 10.0)


def test_the_jacobian_is_the_derivative_of_full_solves(run):
    scene, out = run
    cfg = parse_config(scene.read_text(), str(scene))
    _, mesh, tissue = body_model(cfg)
    probe = tissue.probe(np.array([t.position_mm for t in cfg.targets]))  # the lesions as the run carries them
    J = cup_target_jacobian(tissue, tissue.rest, probe)
    with h5py.File(out / "results.h5", "r") as f:
        stored = np.concatenate([f[f"jacobian/{t}"][()] for t in ("T1", "T2")])
        assert f["jacobian/T1"].shape == (3, 2)
    np.testing.assert_allclose(stored, J, rtol=1e-9, atol=1e-12)  # the run's mesh is this one
    h = 1e-3
    for c in range(2):
        ends = [target_positions(probe, solve_equilibrium(tissue, h * sign * np.eye(2)[c], tol=1e-12).x).ravel()
                for sign in (1.0, -1.0)]
        np.testing.assert_allclose((ends[0] - ends[1]) / (2 * h), J[:, c], rtol=1e-4, atol=1e-6)


@pytest.mark.slow  # (tests/test_golden.py's dome reproduces the same paths' numbers from a file, a superset)
def test_the_same_scene_twice_gives_the_same_mesh_and_numbers(run, tmp_path):
    scene, out = run
    r = run_cli("simulate", scene, "--out", tmp_path / "again", "--quiet")
    assert r.returncode == 0, r.stderr
    with h5py.File(out / "results.h5", "r") as a, h5py.File(tmp_path / "again" / "results.h5", "r") as b:
        for path in ("mesh/nodes", "mesh/tetrahedra", "mesh/region", "forward/push/displacement",
                     "forward/both/targets/T1", "jacobian/T2"):
            assert np.array_equal(a[path][()], b[path][()]), path


def test_figures_and_export_show_the_body(run):
    _, out = run
    for name in ("forward_push.png", "forward_push_3d.png", "forward_both.png"):
        assert_png_drawn(out / name)
    r = cli_here("export", out, "--format", "vtu")
    assert r.exit_code == 0, r.output
    import meshio

    mesh = meshio.read(out / "export" / "forward_push.vtu")
    assert mesh.cells[0].type == "tetra" and mesh.points.shape[1] == 3
    assert "region" in mesh.cell_data and mesh.point_data["displacement"].shape == (len(mesh.points), 3)


def test_a_closed_surface_body_meshes_and_solves(tmp_path):
    """An STL of a box, held on its bottom face, pushed at one side."""
    import meshio

    box = np.array([[0, 0, 0], [40, 0, 0], [40, 30, 0], [0, 30, 0], [0, 0, 20], [40, 0, 20], [40, 30, 20], [0, 30, 20]],
                   float)
    faces = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                      [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    meshio.write(tmp_path / "box.stl", meshio.Mesh(box, [("triangle", faces)]))
    data = {"tissue": {"shape": "surface", "surface_file": "box.stl",
                       "fixed": [{"plane": {"point_mm": [0, 0, 0], "normal": [0, 0, 1]}}],
                       "mesh": {"max_edge_mm": 8.0, "min_edge_mm": 3.0}},
            "cups": [{"name": "cup", "contact_mm": [20.0, 0.0, 12.0], "radius_mm": 5.0}],
            "targets": [{"name": "T", "position_mm": [20.0, 15.0, 10.0], "radius_mm": 3.0}],
            "forward": [{"name": "push", "strokes": {"cup": 4.0}}], "trials": {"count": 0}}
    with h5py.File(simulate_here(tmp_path, data) / "results.h5", "r") as f:
        axis = f["cups/cup"].attrs["axis"]
        np.testing.assert_allclose(axis, [0.0, 1.0, 0.0], atol=1e-9)  # the inward normal of the face y = 0
        moved = f["forward/push/targets/T"][()] - np.array([20.0, 15.0, 10.0])
        assert moved[1] > 0.1  # pushed along +y
        fixed = f["mesh/fixed_nodes"][()]
        assert np.all(f["mesh/nodes"][()][fixed, 2] == 0.0)


def test_a_pinned_mesh_file_is_used_as_it_is(run, tmp_path):
    _, out = run
    with h5py.File(out / "results.h5", "r") as f:
        nodes = f["mesh/nodes"][()]
    data = yaml.safe_load(yaml.safe_dump(SCENE))
    data["tissue"]["mesh"]["file"] = str(out / "results.h5")
    pinned = dict(data, forward=[])  # (the mesh is on test, not the forward cases the fixture's run solved)
    with h5py.File(simulate_here(tmp_path, pinned, name="pinned") / "results.h5", "r") as f:
        assert np.array_equal(f["mesh/nodes"][()], nodes)
    data["targets"] = data["targets"][:1]  # another scene's regions: refused
    r = run_cli("validate", write_scene(tmp_path, data))
    assert r.returncode == 2 and "regions" in r.stderr and "Traceback" not in r.stderr
