"""`scissor export`: a run's results.h5 as files ParaView opens (XDMF or VTU, through meshio).

What is written, and the file names, are in docs/contract.md#export:

* `mesh`: the 2-D rest mesh, nodes lifted to z = 0, with the node markers
  (`fixed`, `cup_<cup>`) as point data and `fiber`, `E_kPa` (and `obstacle`)
  as cell data; a 3-D scene's body: its tetrahedra, with `region` (the
  index into /mesh's `regions`) as cell data too;
* `forward_<case>`: the same mesh with the case's `displacement` (N, 3) mm,
  z = 0, for Warp By Vector;
* `insertion_<target>_<strategy>`: a time series over the insertion steps
  (time = step index) with `displacement` per step, and a CSV of the
  per-step numbers (depth, tip, target, needle force, ...);
* `layer_check_mesh`, `layer_check_<case>`: the 3-D slab (tetrahedra) and
  each case's `displacement`, with `layer_check_targets.csv`.

XDMF files keep their arrays in an `.h5` file of the same stem beside them;
a VTU time series is a numbered `.vtu` per step in a folder of the series'
name, collected by a `.pvd` file.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path
from xml.etree import ElementTree as ET

import h5py
import numpy as np

from scissor_cli.mesh.mesh import meshio_cell_type

FORMATS = ("xdmf", "vtu")
#: the per-step arrays of /insertion/<target>/<strategy>/ that go into its CSV, in column order
INSERTION_STEP_ARRAYS = ("depth_mm", "tip", "target", "needle_force_mN", "stuck", "slipping", "min_clearance_mm")


class ExportError(ValueError):
    """A run cannot be exported (missing, unreadable, incomplete, or malformed)."""


@dataclass
class Written:
    """One file (or series) the export wrote, and what it holds."""

    path: Path
    what: str


@dataclass
class Insertion:
    target: str
    strategy: str
    displacement: np.ndarray  # (K, N, 2) mm on the layer's mesh, or (K, N3, 3) on the slab's (slab truth)
    steps: dict[str, np.ndarray]  # name -> (K,), (K, 2) or, in the slab, (K, 3)
    slab: bool = False  # the insertion ran in the 3-D slab of /layer_check/mesh


@dataclass
class LayerCheck:
    nodes: np.ndarray  # (N3, 3) mm
    tetrahedra: np.ndarray  # (M3, 4)
    displacement: dict[str, np.ndarray]  # case -> (N3, 3) mm
    targets: dict[str, dict[str, np.ndarray]]  # case -> target -> (3,) mm


@dataclass
class RunData:
    """What export reads from results.h5 (docs/contract.md#contract-paths)."""

    nodes: np.ndarray  # (N, d) mm: d = 2 (a layer) or 3 (a body)
    triangles: np.ndarray  # (M, 3) triangles, or in a body (M, 4) tetrahedra
    point_data: dict[str, np.ndarray]  # markers, (N,)
    cell_data: dict[str, np.ndarray]  # (M,) or (M, 3)
    forward: dict[str, np.ndarray] = field(default_factory=dict)  # case -> (N, d) mm
    unconverged: set[str] = field(default_factory=set)  # forward cases whose solve did not converge
    insertion: list[Insertion] = field(default_factory=list)
    layer_check: LayerCheck | None = None


# ---------------------------------------------------------------- reading


def open_run(run_dir: Path, partial: bool = False) -> Path:
    """results.h5 of a run directory that may be exported, else ExportError (the reason, one line)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ExportError(f"{run_dir}: not a directory (give a scissor run directory)")
    path = run_dir / "results.h5"
    if not path.is_file():
        raise ExportError(f"{run_dir}: no results.h5 (is this a scissor run directory?)")
    try:
        with h5py.File(path, "r") as f:
            status = str(f.attrs.get("status", "unknown"))
            reason = str(f.attrs.get("failure", ""))
    except OSError as exc:
        raise ExportError(f"{path}: cannot be read as HDF5 ({exc})") from None
    if status != "complete" and not partial:
        raise ExportError(f"{path}: status is {status!r}, not 'complete'" + (f" ({reason})" if reason else "")
                          + "; finish it with 'scissor simulate --resume' or pass --partial")
    return path


def read_run(path: Path) -> RunData:
    """The mesh, forward cases, insertion series and 3-D slab of one results.h5."""
    try:
        with h5py.File(path, "r") as f:
            return _read(f, path)
    except ExportError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise ExportError(f"{path}: cannot be exported: {exc}") from None


def _array(f: h5py.File, name: str, shape: tuple, path: Path, dtype=np.float64) -> np.ndarray:
    """Dataset `name` with the given shape (None: any length), else ExportError naming it."""
    if name not in f or not isinstance(f[name], h5py.Dataset):
        raise ExportError(f"{path}: no dataset /{name}")
    a = f[name][()]
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
        raise ExportError(f"{path}: /{name} has shape {a.shape}, expected {want}")
    if a.dtype.kind not in "iufb":
        raise ExportError(f"{path}: /{name} is not numeric ({a.dtype})")
    return a if dtype is None else np.asarray(a, dtype=dtype)


def _read(f: h5py.File, path: Path) -> RunData:
    d = 3 if "mesh/tetrahedra" in f else 2  # a 3-D scene's body, or a 2-D layer
    nodes = _array(f, "mesh/nodes", (None, d), path)
    n = len(nodes)
    cells_name = "mesh/tetrahedra" if d == 3 else "mesh/triangles"
    triangles = _array(f, cells_name, (None, d + 1), path, np.int64)
    m = len(triangles)
    if m and (triangles.min() < 0 or triangles.max() >= n):
        raise ExportError(f"{path}: /{cells_name} index a node outside 0..{n - 1}")
    fixed = np.zeros(n, np.int32)
    if "mesh/fixed_nodes" in f:
        fixed[_array(f, "mesh/fixed_nodes", (None,), path, np.int64)] = 1
    point_data = {"fixed": fixed}
    for cup in f.get("cups", {}):
        marker = np.zeros(n, np.int32)
        marker[_array(f, f"cups/{cup}/nodes", (None,), path, np.int64)] = 1
        point_data[f"cup_{cup}"] = marker
    cell_data = {}
    if "mesh/fiber" in f:
        fiber = _array(f, "mesh/fiber", (m, d), path)
        cell_data["fiber"] = fiber if d == 3 else _lift(fiber)
    if "mesh/region" in f:
        cell_data["region"] = _array(f, "mesh/region", (m,), path, np.int32)
    if "mesh/element_E_kPa" in f:
        cell_data["E_kPa"] = _array(f, "mesh/element_E_kPa", (m,), path)
    if "mesh/element_obstacle" in f:
        cell_data["obstacle"] = _array(f, "mesh/element_obstacle", (m,), path, np.int32)
    data = RunData(nodes, triangles, point_data, cell_data)
    for case in f.get("forward", {}):
        data.forward[case] = _array(f, f"forward/{case}/displacement", (n, d), path)
        if not f[f"forward/{case}"].attrs.get("converged", True):
            data.unconverged.add(case)
    if "layer_check" in f:
        data.layer_check = _read_layer_check(f, path)
    for target, g in f.get("insertion", {}).items():
        for strategy in g:
            data.insertion.append(_read_insertion(f, path, target, strategy, n, data.layer_check, body=d == 3))
    return data


def _read_insertion(f: h5py.File, path: Path, target: str, strategy: str, n: int,
                    layer_check: "LayerCheck | None", body: bool = False) -> Insertion:
    """One insertion: on the run's mesh, the layer's (K, N, 2) or a body's (K, N, 3), or on the slab's (K, N3, 3)
    when a layer's ran in the slab."""
    base = f"insertion/{target}/{strategy}"
    slab = (not body and f"{base}/displacement" in f and np.ndim(f[f"{base}/displacement"]) == 3
            and f[f"{base}/displacement"].shape[2] == 3)
    if slab and layer_check is None:
        raise ExportError(f"{path}: /{base}/displacement is 3-D but there is no /layer_check/mesh to show it on")
    d = 3 if slab or body else 2
    disp = _array(f, f"{base}/displacement", (None, len(layer_check.nodes) if slab else n, d), path)
    k = len(disp)
    steps = {}
    for name in INSERTION_STEP_ARRAYS:
        if f"{base}/{name}" in f:
            width = (d,) if np.ndim(f[f"{base}/{name}"]) == 2 else ()
            steps[name] = _array(f, f"{base}/{name}", (k, *width), path, dtype=None)
    return Insertion(target, strategy, disp, steps, slab)


def _read_layer_check(f: h5py.File, path: Path) -> LayerCheck:
    nodes = _array(f, "layer_check/mesh/nodes", (None, 3), path)
    tets = _array(f, "layer_check/mesh/tetrahedra", (None, 4), path, np.int64)
    if len(tets) and (tets.min() < 0 or tets.max() >= len(nodes)):
        raise ExportError(f"{path}: /layer_check/mesh/tetrahedra index a node outside 0..{len(nodes) - 1}")
    check = LayerCheck(nodes, tets, {}, {})
    for case, g in f["layer_check"].items():
        if case == "mesh" or not isinstance(g, h5py.Group):
            continue
        check.displacement[case] = _array(f, f"layer_check/{case}/displacement", (len(nodes), 3), path)
        check.targets[case] = {t: _array(f, f"layer_check/{case}/targets/{t}", (3,), path)
                               for t in g.get("targets", {})}
    return check


def _lift(v: np.ndarray) -> np.ndarray:
    """(n, 2) -> (n, 3) with z = 0: ParaView warps and glyphs by 3-component vectors."""
    return np.column_stack([v, np.zeros(len(v))])


# ---------------------------------------------------------------- writing


def export_run(run_dir: Path, out_dir: Path, fmt: str = "xdmf", partial: bool = False) -> list[Written]:
    """Write the run's mesh, forward cases, insertion series and 3-D slab into out_dir; return what was written."""
    if fmt not in FORMATS:
        raise ExportError(f"--format: must be 'xdmf' or 'vtu'; got {fmt!r}")
    data = read_run(open_run(run_dir, partial))
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ExportError(f"--out {out_dir}: cannot create it ({exc.strerror})") from None
    writer = _Writer(out_dir, fmt)
    try:
        _write(data, writer)
    except OSError as exc:
        raise ExportError(f"--out {out_dir}: cannot write {exc.filename or 'there'}: "
                          f"{exc.strerror or exc}") from None
    return writer.written


def _write(data: RunData, writer: "_Writer") -> None:
    body = data.nodes.shape[1] == 3
    points = data.nodes if body else _lift(data.nodes)
    cells = _cells(data.nodes, data.triangles)
    nn, ne = len(data.nodes), len(data.triangles)
    writer.mesh("mesh", points, cells, data.point_data, data.cell_data,
                f"{'3-D body' if body else '2-D'} rest mesh, {nn} nodes, {ne} {'tetrahedra' if body else 'triangles'};"
                f" point data {', '.join(data.point_data)}; cell data {', '.join(data.cell_data) or 'none'}")
    for case, u in data.forward.items():
        writer.mesh(f"forward_{case}", points, cells, {"displacement": u if body else _lift(u), **data.point_data},
                    data.cell_data,
                    f"forward case {case}: displacement (max |u| {_max_norm(u):.3g} mm)"
                    + (" -- NOT CONVERGED" if case in data.unconverged else ""))
    for ins in data.insertion:
        name = f"insertion_{ins.target}_{ins.strategy}"
        k = len(ins.displacement)
        if ins.slab:  # _read checked the slab's mesh is there
            lc = data.layer_check
            stem = writer.series(name, lc.nodes, _cells(lc.nodes, lc.tetrahedra),
                                 [{"displacement": u} for u in ins.displacement],
                                 f"insertion {ins.target} / {ins.strategy} in the 3-D slab: {k} step(s), "
                                 "displacement per step (time = step)")
        else:
            stem = writer.series(name, points, cells, [{"displacement": u if body else _lift(u)}
                                                       for u in ins.displacement],
                                 f"insertion {ins.target} / {ins.strategy}: {k} step(s), displacement per step "
                                 "(time = step)")
        writer.table(f"{stem}.csv", *_step_table(ins), f"insertion {ins.target} / {ins.strategy}: per-step numbers")
    if data.layer_check is not None:
        lc = data.layer_check
        tets = _cells(lc.nodes, lc.tetrahedra)
        writer.mesh("layer_check_mesh", lc.nodes, tets, {}, {},
                    f"3-D slab, {len(lc.nodes)} nodes, {len(lc.tetrahedra)} tetrahedra")
        for case, u in lc.displacement.items():
            writer.mesh(f"layer_check_{case}", lc.nodes, tets, {"displacement": u}, {},
                        f"3-D slab, case {case}: displacement (max |u| {_max_norm(u):.3g} mm)")
        rows = [[case, t, *p] for case, ts in lc.targets.items() for t, p in ts.items()]
        if rows:
            writer.table("layer_check_targets.csv", ["case", "target", "x_mm", "y_mm", "z_mm"], rows,
                         "3-D slab: deformed target positions per case")


def _cells(nodes: np.ndarray, cells: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """meshio's cell block of simplices (M, n) on nodes (N, d), named by d and n."""
    return [(meshio_cell_type(nodes.shape[1], cells.shape[1]), cells)]


def _max_norm(u: np.ndarray) -> float:
    return float(np.linalg.norm(u, axis=1).max()) if len(u) else 0.0


def _step_table(ins: Insertion) -> tuple[list[str], list[list]]:
    header, columns = ["step"], [np.arange(len(ins.displacement))]
    for name, a in ins.steps.items():
        if a.ndim == 2:
            axes = "xyz"[:a.shape[1]]
            header += [f"{name}_{c}_mm" for c in axes]
            columns += [a[:, i] for i in range(len(axes))]
        else:
            header.append(name)
            columns.append(a)
    rows = [[_cell(c[i]) for c in columns] for i in range(len(ins.displacement))]
    return header, rows


def _cell(v) -> object:
    return np.asarray(v).item()  # a Python int or float: csv writes ints without a decimal point


def safe_name(name: str) -> str:
    """A file-name stem from a results.h5 name: anything but letters, digits, '_', '.', '+', '-' becomes '_'."""
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", name) or "_"


class _Writer:
    """Writes meshes, time series and tables into one directory, in one format, and lists them."""

    def __init__(self, out_dir: Path, fmt: str):
        self.out_dir, self.fmt = out_dir, fmt
        self.written: list[Written] = []
        self._stems: set[str] = set()

    def _stem(self, name: str) -> str:
        stem, i = safe_name(name), 2
        while stem.lower() in self._stems:  # two names that differ only in unsafe characters or case
            stem, i = f"{safe_name(name)}-{i}", i + 1
        self._stems.add(stem.lower())
        return stem

    def mesh(self, name: str, points, cells, point_data: dict, cell_data: dict, what: str) -> None:
        import meshio

        path = self.out_dir / f"{self._stem(name)}.{self.fmt}"
        mesh = meshio.Mesh(points, cells, point_data=point_data,
                           cell_data={k: [v] for k, v in cell_data.items()})
        meshio.write(path, mesh, file_format=self.fmt)
        self.written.append(Written(path, what))

    def series(self, name: str, points, cells, steps: list[dict], what: str) -> str:
        """A time series (time = step index); returns the stem its files got."""
        stem = self._stem(name)
        if self.fmt == "xdmf":
            path = self.out_dir / f"{stem}.xdmf"
            with _TimeSeriesWriter(path) as w:
                w.write_points_cells(points, cells)
                for k, point_data in enumerate(steps):
                    w.write_data(float(k), point_data=point_data)
        else:
            import meshio

            folder = self.out_dir / stem
            folder.mkdir(exist_ok=True)
            collection = ET.Element("Collection")
            for k, point_data in enumerate(steps):
                step = folder / f"{stem}_{k:04d}.vtu"
                meshio.write(step, meshio.Mesh(points, cells, point_data=point_data), file_format="vtu")
                ET.SubElement(collection, "DataSet", timestep=str(k), group="", part="0",
                              file=f"{stem}/{step.name}")
            path = self.out_dir / f"{stem}.pvd"
            root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
            root.append(collection)
            ET.indent(root)
            ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)
        self.written.append(Written(path, what))
        return stem

    def table(self, name: str, header: list[str], rows: list[list], what: str) -> None:
        path = self.out_dir / name
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(header)
            w.writerows(rows)
        self.written.append(Written(path, what))


def _time_series_writer():
    from meshio.xdmf import TimeSeriesWriter

    class Writer(TimeSeriesWriter):
        """meshio 5.3 puts the .h5 in the working directory (nschloe/meshio#1351), where the .xdmf
        does not find it; this one puts it beside the .xdmf, which names it by its base name."""

        def __enter__(self):
            self.h5_filename = str(self.filename.with_suffix(".h5"))
            self.h5_file = h5py.File(self.h5_filename, "w")
            return self

    return Writer


def _TimeSeriesWriter(path: Path):  # noqa: N802 - a class made on first use, so importing this module stays light
    return _time_series_writer()(path, data_format="HDF")
