"""The layer check's results.h5 group and figure (docs/contract.md, docs/model.md §13).

/layer_check/mesh/nodes (N3, 3) mm and /layer_check/mesh/tetrahedra (M3, 4)
int64 once; per forward case /layer_check/<case>/displacement (N3, 3) mm,
/layer_check/<case>/targets/<target> (3,) mm and the case's attributes.
The figure: the layer's level of the slab against the 2-D layer, in plan
(in-plane) and the out-of-plane displacement there.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from scissor_cli.output.results import ResultsFile


def write_layer_check_mesh(out: ResultsFile, nodes: np.ndarray, tetrahedra: np.ndarray, levels_mm: np.ndarray,
                           layer_level: int) -> None:
    out.dataset("layer_check/mesh/nodes", np.asarray(nodes, float), "mm")
    out.dataset("layer_check/mesh/tetrahedra", np.asarray(tetrahedra, np.int64))
    out.attrs("layer_check/mesh", {"levels_mm": np.asarray(levels_mm, float), "layer_level": int(layer_level)})


def write_layer_check_case(out: ResultsFile, case) -> None:
    """One `layer3d.check.LayerCheckCase`."""
    base = f"layer_check/{case.name}"
    out.dataset(f"{base}/displacement", np.asarray(case.displacement, float), "mm")
    for name, pos in case.targets.items():
        out.dataset(f"{base}/targets/{name}", np.asarray(pos, float), "mm")
    out.attrs(base, {
        "in_plane_diff_mm": float(case.in_plane_diff_mm),
        "in_plane_diff_fraction": float(case.in_plane_diff_fraction),
        "plane_stress_diff_mm": float(case.plane_stress_diff_mm),
        "out_of_plane_mm": float(case.out_of_plane_mm),
        "closer_to": case.closer_to,
        "time_s": float(case.time_s),
        "iterations": int(case.iterations),
    })


def layer_check_figure(title: str, rest_2d: np.ndarray, layer_2d: np.ndarray, layer_3d: np.ndarray,
                       triangles: np.ndarray, targets_rest: dict, targets_2d: dict, targets_3d: dict,
                       targets_stress: dict, layer_z_mm: float) -> Figure:
    """Left: the 2-D layer's deformed mesh and the slab's layer level (mm); right: the slab's u_z there.

    rest_2d, layer_2d (N2, 2) mm; layer_3d (N2, 3) mm; triangles (M2, 3); targets: name -> position;
    layer_z_mm: the layer's rest height in the slab.
    """
    fig = Figure(figsize=(11, 4.6))
    ax, az = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    ax.triplot(layer_2d[:, 0], layer_2d[:, 1], triangles, color="0.6", lw=0.3)
    ax.triplot(layer_3d[:, 0], layer_3d[:, 1], triangles, color="tab:blue", lw=0.3, alpha=0.7)
    ax.plot([], [], color="0.6", label="2-D layer (plane strain)")
    ax.plot([], [], color="tab:blue", label="3-D slab at the layer")
    for k, name in enumerate(targets_rest):
        ax.plot(*targets_rest[name], "o", color="red", ms=4, label="target at rest" if k == 0 else None)
        ax.plot(*targets_2d[name], "s", color="0.3", ms=4, label="2-D layer" if k == 0 else None)
        ax.plot(*targets_3d[name][:2], "o", color="tab:blue", ms=4, label="3-D slab" if k == 0 else None)
        ax.plot(*targets_stress[name], "x", color="tab:orange", ms=5, label="plane stress" if k == 0 else None)
        ax.annotate(name, targets_3d[name][:2], textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.legend(fontsize=7, loc="upper right", frameon=False)
    tpc = az.tripcolor(rest_2d[:, 0], rest_2d[:, 1], triangles, layer_3d[:, 2] - layer_z_mm, shading="gouraud",
                       cmap="coolwarm")
    fig.colorbar(tpc, ax=az, label="out-of-plane displacement u_z (mm)")
    az.set_aspect("equal")
    az.set_xlabel("x (mm)")
    az.set_title("slab at the layer's height", fontsize=9)
    fig.suptitle(title, fontsize=10)
    return fig



#: the columns of the layer-check table of `scissor report`
REPORT_COLUMNS = ["run", "case", "layer_check_in_plane_diff_mm", "layer_check_in_plane_diff_pct", "out_of_plane_mm",
                  "closer_to", "slab_tetrahedra", "time_s", "iterations"]


def layer_check_rows(label: str, f) -> list[dict]:
    """One row per forward case of a results.h5 (open h5py.File) with a /layer_check group."""
    if "layer_check" not in f:
        return []
    g = f["layer_check"]
    n_tets = int(g["mesh/tetrahedra"].shape[0])
    rows = []
    for case, grp in g.items():
        if case == "mesh":
            continue
        a = grp.attrs
        rows.append({"run": label, "case": case, "layer_check_in_plane_diff_mm": float(a["in_plane_diff_mm"]),
                     "layer_check_in_plane_diff_pct": 100.0 * float(a["in_plane_diff_fraction"]),
                     "out_of_plane_mm": float(a["out_of_plane_mm"]), "closer_to": str(a["closer_to"]),
                     "slab_tetrahedra": n_tets, "time_s": float(a["time_s"]), "iterations": int(a["iterations"])})
    return rows
