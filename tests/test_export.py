"""`scissor export`: the files read back with meshio hold what results.h5 holds, in both formats.

A real small run (`--trials 0`) gives the mesh and forward cases; a copy of
it with synthetic `/insertion` and `/layer_check` groups (the paths of
docs/contract.md) gives the time series and the 3-D slab.
"""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path
from xml.etree import ElementTree as ET

import h5py
import meshio
import numpy as np
import pytest

from scissor_cli.output.export import ExportError, export_run

from helpers import ROOT

FORMATS = ["xdmf", "vtu"]


def cli(*args):
    """`scissor ARGS` in a subprocess, as a user runs it."""
    return subprocess.run([sys.executable, "-m", "scissor_cli", *map(str, args)], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})


def invoke(*args):
    """`scissor ARGS` in this process (faster): (exit code, stdout, stderr); any exception but an exit fails."""
    from typer.testing import CliRunner

    from scissor_cli import cli as app

    result = CliRunner().invoke(app.app, list(map(str, args)))
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    return result.exit_code, result.stdout, result.stderr


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A real `simulate --trials 0` of the example scene: mesh, two forward cases, no trials."""
    from scissor_cli.config import load_config
    from scissor_cli.experiments.simulate import run_simulation
    from scissor_cli.output.results_sink import RunDirectory

    cfg = load_config(ROOT / "configs" / "example.yaml")
    cfg = cfg.model_copy(update={"trials": cfg.trials.model_copy(update={"count": 0})})
    directory = tmp_path_factory.mktemp("run")
    run_simulation(cfg, RunDirectory(directory))
    return directory


STRATEGIES = {"T1": ["straight", "rotate"], "T2": ["straight"]}
CUBE = np.array([[0, 0, 0], [100, 0, 0], [100, 60, 0], [0, 60, 0],
                 [0, 0, 10], [100, 0, 10], [100, 60, 10], [0, 60, 10]], float)
TETS = np.array([[0, 1, 3, 4], [1, 2, 3, 6], [1, 4, 5, 6], [3, 4, 6, 7], [1, 3, 4, 6]], np.int64)


@pytest.fixture(scope="module")
def synthetic(run, tmp_path_factory) -> Path:
    """The real run with /insertion (K steps per target and strategy) and /layer_check (a 5-tetra slab, 2 cases)."""
    directory = tmp_path_factory.mktemp("synthetic")
    shutil.copy(run / "results.h5", directory / "results.h5")
    rng = np.random.default_rng(3)
    with h5py.File(directory / "results.h5", "r+") as f:
        n = len(f["mesh/nodes"])
        for i, (target, strategies) in enumerate(STRATEGIES.items()):
            for strategy in strategies:
                k = 3 + i
                g = f.create_group(f"insertion/{target}/{strategy}")
                g["depth_mm"] = np.linspace(0.0, 30.0, k)
                g["tip"] = rng.normal(size=(k, 2))
                g["target"] = rng.normal(size=(k, 2))
                g["needle_force_mN"] = rng.uniform(0, 500, k)
                g["stuck"] = rng.integers(0, 2, k)
                g["slipping"] = rng.integers(0, 2, k)
                g["min_clearance_mm"] = rng.uniform(0, 3, k)
                g["displacement"] = rng.normal(size=(k, n, 2))
        f["layer_check/mesh/nodes"] = CUBE
        f["layer_check/mesh/tetrahedra"] = TETS
        for case in ("push10", "pull8"):
            f[f"layer_check/{case}/displacement"] = rng.normal(size=(len(CUBE), 3))
            for target in ("T1", "T2"):
                f[f"layer_check/{case}/targets/{target}"] = rng.normal(size=3)
    return directory


# ---------------------------------------------------------------- reading back


def check_2d(mesh, f, displacement=None):
    """A 2-D mesh read back: nodes at z = 0, triangles, markers, fiber and E as cell data, the displacement."""
    nodes = f["mesh/nodes"][:]
    np.testing.assert_array_equal(mesh.points[:, :2], nodes)
    np.testing.assert_array_equal(mesh.points[:, 2], 0.0)
    np.testing.assert_array_equal(mesh.cells_dict["triangle"], f["mesh/triangles"][:])
    fixed = np.zeros(len(nodes), int)
    fixed[f["mesh/fixed_nodes"][:]] = 1
    np.testing.assert_array_equal(mesh.point_data["fixed"], fixed)
    for cup in f["cups"]:
        marker = np.zeros(len(nodes), int)
        marker[f[f"cups/{cup}/nodes"][:]] = 1
        np.testing.assert_array_equal(mesh.point_data[f"cup_{cup}"], marker)
    cell = {k: v[0] for k, v in mesh.cell_data.items()}
    np.testing.assert_array_equal(cell["fiber"][:, :2], f["mesh/fiber"][:])
    np.testing.assert_array_equal(cell["fiber"][:, 2], 0.0)
    np.testing.assert_array_equal(cell["E_kPa"], f["mesh/element_E_kPa"][:])
    np.testing.assert_array_equal(cell["obstacle"], f["mesh/element_obstacle"][:])
    expected = {"fixed", *(f"cup_{c}" for c in f["cups"])}
    if displacement is not None:
        check_displacement(mesh.point_data["displacement"], displacement)
        expected.add("displacement")
    assert set(mesh.point_data) == expected


def check_displacement(read, stored):
    assert read.shape == (len(stored), 3)
    np.testing.assert_array_equal(read[:, :2], stored)
    np.testing.assert_array_equal(read[:, 2], 0.0)


def read_series(out: Path, stem: str, fmt: str):
    """(points, cells, [(time, point_data)]) of a time series, through meshio's readers."""
    if fmt == "xdmf":
        with meshio.xdmf.TimeSeriesReader(out / f"{stem}.xdmf") as reader:
            points, cells = reader.read_points_cells()
            steps = [reader.read_data(k)[:2] for k in range(reader.num_steps)]
        return points, cells, steps
    root = ET.parse(out / f"{stem}.pvd").getroot()
    assert root.get("type") == "Collection"
    steps, meshes = [], []
    for ds in root.iter("DataSet"):
        m = meshio.read(out / ds.get("file"))
        meshes.append(m)
        steps.append((float(ds.get("timestep")), m.point_data))
    for m in meshes[1:]:
        np.testing.assert_array_equal(m.points, meshes[0].points)
    return meshes[0].points, meshes[0].cells, steps


def check_export(run_dir: Path, out: Path, fmt: str) -> set[str]:
    """Compare every exported file with results.h5; return the names of the files written."""
    with h5py.File(run_dir / "results.h5") as f:
        check_2d(meshio.read(out / f"mesh.{fmt}"), f)
        for case in f["forward"]:
            check_2d(meshio.read(out / f"forward_{case}.{fmt}"), f, f[f"forward/{case}/displacement"][:])
        for target, g in f.get("insertion", {}).items():
            for strategy, s in g.items():
                stem = f"insertion_{target}_{strategy}"
                points, cells, steps = read_series(out, stem, fmt)
                np.testing.assert_array_equal(points[:, :2], f["mesh/nodes"][:])
                np.testing.assert_array_equal(cells[0].data, f["mesh/triangles"][:])
                disp = s["displacement"][:]
                assert [t for t, _ in steps] == list(range(len(disp)))
                for (_, pd), u in zip(steps, disp):
                    check_displacement(pd["displacement"], u)
                rows = list(csv.DictReader(open(out / f"{stem}.csv")))
                assert [int(r["step"]) for r in rows] == list(range(len(disp)))
                for name in ("depth_mm", "needle_force_mN", "min_clearance_mm"):
                    np.testing.assert_array_equal([float(r[name]) for r in rows], s[name][:])
                for name in ("stuck", "slipping"):
                    assert [int(r[name]) for r in rows] == list(s[name][:])
                for name in ("tip", "target"):
                    got = [[float(r[f"{name}_x_mm"]), float(r[f"{name}_y_mm"])] for r in rows]
                    np.testing.assert_array_equal(got, s[name][:])
        if "layer_check" in f:
            lc = f["layer_check"]
            slab = meshio.read(out / f"layer_check_mesh.{fmt}")
            np.testing.assert_array_equal(slab.points, lc["mesh/nodes"][:])
            np.testing.assert_array_equal(slab.cells_dict["tetra"], lc["mesh/tetrahedra"][:])
            cases = [c for c in lc if c != "mesh"]
            for case in cases:
                m = meshio.read(out / f"layer_check_{case}.{fmt}")
                np.testing.assert_array_equal(m.points, lc["mesh/nodes"][:])
                np.testing.assert_array_equal(m.cells_dict["tetra"], lc["mesh/tetrahedra"][:])
                np.testing.assert_array_equal(m.point_data["displacement"], lc[f"{case}/displacement"][:])
            rows = list(csv.DictReader(open(out / "layer_check_targets.csv")))
            assert len(rows) == sum(len(lc[f"{c}/targets"]) for c in cases)
            for r in rows:
                np.testing.assert_array_equal([float(r[k]) for k in ("x_mm", "y_mm", "z_mm")],
                                              lc[f"{r['case']}/targets/{r['target']}"][:])
    return {p.name for p in out.iterdir()}


# ---------------------------------------------------------------- tests


@pytest.mark.parametrize("fmt", FORMATS)
def test_export_real_run(run, fmt, tmp_path):
    """The CLI on a real run: mesh and forward cases, read back equal; what was written is printed."""
    out = tmp_path / "out"
    proc = cli("export", run, "--format", fmt, "--out", out)
    assert proc.returncode == 0, proc.stderr
    names = check_export(run, out, fmt)
    files = {"mesh", "forward_push10", "forward_pull8"}
    expected = {f"{s}.{fmt}" for s in files} | ({f"{s}.h5" for s in files} if fmt == "xdmf" else set())
    assert names == expected
    for s in files:
        assert str(out / f"{s}.{fmt}") in proc.stdout


def test_export_default_out_and_force(run, tmp_path):
    """Default out is RUN_DIR/export (xdmf); a second export there needs --force."""
    directory = tmp_path / "run"
    shutil.copytree(run, directory)
    assert invoke("export", directory)[0] == 0
    assert (directory / "export" / "forward_push10.xdmf").is_file()
    code, _, stderr = invoke("export", directory)
    assert code == 2 and "--force" in stderr
    assert invoke("export", directory, "--force")[0] == 0


@pytest.mark.parametrize("fmt", FORMATS)
def test_export_insertion_and_layer_check(synthetic, fmt, tmp_path, monkeypatch):
    """Insertion steps as a time series per target and strategy, the 3-D slab per case; nothing in the cwd."""
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)  # meshio's own XDMF time-series writer would put its .h5 here
    out = tmp_path / "out"
    written = export_run(synthetic, out, fmt)
    names = check_export(synthetic, out, fmt)
    assert not any(cwd.iterdir())
    series = [f"insertion_{t}_{s}" for t, ss in STRATEGIES.items() for s in ss]
    ext = "xdmf" if fmt == "xdmf" else "pvd"
    for stem in series:
        assert f"{stem}.{ext}" in names and f"{stem}.csv" in names
        if fmt == "vtu":
            assert (out / stem / f"{stem}_0000.vtu").is_file()
    assert {"layer_check_mesh." + fmt, "layer_check_push10." + fmt, "layer_check_pull8." + fmt,
            "layer_check_targets.csv"} <= names
    assert {w.path.name for w in written} == {n for n in names if not n.endswith(".h5") and (out / n).is_file()}


def test_refused_and_bad_input(run, tmp_path):
    """Exit 2 with one message, no traceback: not complete (unless --partial), bad dir, no file, garbage, bad shape."""
    bad = tmp_path / "failed"
    shutil.copytree(run, bad)
    with h5py.File(bad / "results.h5", "r+") as f:
        f.attrs["status"] = "failed"
        f.attrs["failure"] = "interrupted"
    garbage = tmp_path / "garbage"
    garbage.mkdir()
    (garbage / "results.h5").write_text("not HDF5")
    cases = [
        ((bad,), "--partial"),
        ((tmp_path / "missing",), "not a directory"),
        ((tmp_path,), "no results.h5"),
        ((garbage,), "cannot be read as HDF5"),
        ((run, "--format", "vtk"), "--format"),
    ]
    for args, message in cases:
        code, _, stderr = invoke("export", *args, "--out", tmp_path / "o")
        assert code == 2, (args, stderr)
        assert message in stderr and len(stderr.strip().splitlines()) == 1, stderr
    proc = cli("export", garbage, "--out", tmp_path / "o")  # as a user sees it: one line, no traceback
    assert proc.returncode == 2 and proc.stderr.startswith("error: ") and "Traceback" not in proc.stderr
    assert invoke("export", bad, "--partial", "--out", tmp_path / "p")[0] == 0
    assert not (tmp_path / "o").exists()
    wrong = tmp_path / "wrong"
    shutil.copytree(run, wrong)
    with h5py.File(wrong / "results.h5", "r+") as f:
        del f["forward/push10/displacement"]
        f["forward/push10/displacement"] = np.zeros((3, 2))
    with pytest.raises(ExportError, match="/forward/push10/displacement has shape"):
        export_run(wrong, tmp_path / "w")


def test_unconverged_case_is_flagged(run, tmp_path):
    """A forward case whose solve did not converge (a --partial run) is still exported, and the listing says so."""
    directory = tmp_path / "run"
    shutil.copytree(run, directory)
    with h5py.File(directory / "results.h5", "r+") as f:
        f["forward/pull8"].attrs["converged"] = False
    written = {w.path.name: w.what for w in export_run(directory, tmp_path / "out", "vtu")}
    assert "NOT CONVERGED" in written["forward_pull8.vtu"] and "NOT" not in written["forward_push10.vtu"]


def test_names_made_safe_and_unique(synthetic, tmp_path):
    """A strategy name with a '/'-free but unsafe character, and two names that clash once made safe."""
    directory = tmp_path / "run"
    shutil.copytree(synthetic, directory)
    with h5py.File(directory / "results.h5", "r+") as f:
        f.copy(f["insertion/T1/straight"], f["insertion/T1"], "a b")
        f.copy(f["insertion/T1/straight"], f["insertion/T1"], "a:b")
    names = {w.path.name for w in export_run(directory, tmp_path / "out", "vtu")}
    assert {"insertion_T1_a_b.pvd", "insertion_T1_a_b.csv", "insertion_T1_a_b-2.pvd", "insertion_T1_a_b-2.csv"} <= names
    assert (tmp_path / "out" / "insertion_T1_a_b-2" / "insertion_T1_a_b-2_0000.vtu").is_file()


def test_unwritable_out(run, tmp_path):
    """An --out that cannot be written: exit 2, one message."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ExportError, match="cannot"):
        export_run(run, blocker / "sub")


def test_vtk_reads_the_files(synthetic, tmp_path):
    """Where VTK is installed (not a dependency): its XDMF reader, ParaView's 'XDMF Reader', opens the files,
    time steps included, and its VTU reader the .vtu; the arrays are those of results.h5."""
    pytest.importorskip("vtkmodules.vtkIOXdmf2")
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as Pipeline
    from vtkmodules.vtkIOXdmf2 import vtkXdmfReader
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridReader

    def grid_of(reader):
        out = reader.GetOutputDataObject(0)
        return out.GetBlock(0) if out.IsA("vtkMultiBlockDataSet") else out

    export_run(synthetic, tmp_path / "x", "xdmf")
    export_run(synthetic, tmp_path / "v", "vtu")
    with h5py.File(synthetic / "results.h5") as f:
        push = f["forward/push10/displacement"][:]
        n_triangles = len(f["mesh/triangles"])
        steps = f["insertion/T2/straight/displacement"][:]
    reader = vtkXdmfReader()
    reader.SetFileName(str(tmp_path / "x" / "insertion_T2_straight.xdmf"))
    reader.UpdateInformation()
    assert reader.GetOutputInformation(0).Get(Pipeline.TIME_STEPS()) == tuple(float(k) for k in range(len(steps)))
    reader.UpdateTimeStep(2.0)
    u = vtk_to_numpy(grid_of(reader).GetPointData().GetArray("displacement"))
    np.testing.assert_array_equal(u[:, :2], steps[2])
    for path, r in ((tmp_path / "x" / "forward_push10.xdmf", vtkXdmfReader()),
                    (tmp_path / "v" / "forward_push10.vtu", vtkXMLUnstructuredGridReader())):
        r.SetFileName(str(path))
        r.Update()
        grid = grid_of(r)
        assert grid.GetNumberOfCells() == n_triangles
        np.testing.assert_array_equal(vtk_to_numpy(grid.GetPointData().GetArray("displacement"))[:, :2], push)
        assert grid.GetCellData().GetArray("E_kPa") is not None


@pytest.mark.parametrize("fmt", FORMATS)
def test_export_slab_insertion(synthetic, fmt, tmp_path):
    """An insertion that ran in the slab (tip, target (K, 3), displacement (K, N3, 3)): a series on the slab's mesh."""
    directory = tmp_path / "slab"
    directory.mkdir()
    shutil.copy(synthetic / "results.h5", directory / "results.h5")
    rng = np.random.default_rng(5)
    k = 4
    with h5py.File(directory / "results.h5", "r+") as f:
        del f["insertion"]
        g = f.create_group("insertion/T1/loop")
        g["depth_mm"] = np.linspace(0.0, 3.0, k)
        g["tip"], g["target"] = rng.normal(size=(k, 3)), rng.normal(size=(k, 3))
        g["needle_force_mN"] = rng.uniform(0, 500, k)
        g["displacement"] = disp = rng.normal(size=(k, len(CUBE), 3))
    out = tmp_path / "out"
    export_run(directory, out, fmt)
    points, cells, steps = read_series(out, "insertion_T1_loop", fmt)
    np.testing.assert_array_equal(points, CUBE)
    np.testing.assert_array_equal(cells[0].data, TETS)
    assert [t for t, _ in steps] == list(range(k))
    for (_, pd), u in zip(steps, disp):
        np.testing.assert_array_equal(pd["displacement"], u)
    with h5py.File(directory / "results.h5") as f:
        rows = list(csv.DictReader(open(out / "insertion_T1_loop.csv")))
        for name in ("tip", "target"):
            got = [[float(r[f"{name}_{c}_mm"]) for c in "xyz"] for r in rows]
            np.testing.assert_array_equal(got, f[f"insertion/T1/loop/{name}"][:])
    # 3-D without the slab's mesh is refused with a message
    with h5py.File(directory / "results.h5", "r+") as f:
        del f["layer_check"]
    with pytest.raises(ExportError, match="layer_check"):
        export_run(directory, tmp_path / "out2", fmt)
