"""Figures of a 3-D scene (docs/contract.md, "Figures"): the section through a lesion, and the body in 3-D.

* The section (Fig. 11's analogue): the plane through the first lesion's
  centre spanned by the first cup's axis and the needle's direction (the
  vertical when they are parallel, or without a cup) — the plane the
  paper's layer is. The tetrahedra it cuts give the tissue's section by
  region, at rest and carried by the displacement (the same material
  points, drawn in the plane's coordinates: motion across the plane is not
  shown), with each lesion's centre before and after.
* The 3-D view: the skin (the body's boundary faces), the lesions, the
  vessels and cysts, the cups' patches and axes, at rest and deformed.

Drawn on `matplotlib.figure.Figure` directly, as `output.figures`.
"""

from __future__ import annotations

import numpy as np
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from scissor_cli.output.figures import OBSTACLE, TISSUE

#: region colours: the body, the skin, lesions, obstacles
SKIN = "#d9a68c"
LESION = "#c0392b"


def section_plane(tissue, needle_direction: np.ndarray | None = None,
                  through: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The section's origin (3,) mm and in-plane unit vectors (2, 3): (u, v) = (cup axis, needle or vertical); the
    plane goes through `through` (default the first lesion's rest centre)."""
    scene = tissue.scene
    if through is not None:
        origin = np.asarray(through, float)
    else:
        origin = scene.targets[0].rest if scene.targets else tissue.mesh.nodes.mean(axis=0)
    u = scene.cups[0].axis if scene.cups else np.array([1.0, 0.0, 0.0])
    u = u / np.linalg.norm(u)
    for v in (needle_direction, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        if v is None:
            continue
        v = v - (v @ u) * u
        if np.linalg.norm(v) > 1e-6:
            return np.asarray(origin, float), np.stack([u, v / np.linalg.norm(v)])
    raise ValueError("no direction spans a plane with the cup's axis")


#: the six edges of a tetrahedron, as corner pairs
_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def cut(nodes: np.ndarray, tetrahedra: np.ndarray, origin: np.ndarray, normal: np.ndarray):
    """The section of tetrahedra (M, 4) of rest nodes (N, 3) by a plane: per cut element its polygon's corners as
    (node a, node b, t) triples — the point a + t (b − a) — (E, 4) each (a triangle repeats its last corner), and
    the elements cut (E,)."""
    s = (nodes - origin) @ normal  # signed distances
    st = s[tetrahedra]  # (M, 4)
    hit = np.flatnonzero((st.min(axis=1) < 0) & (st.max(axis=1) > 0))
    a = tetrahedra[hit][:, _EDGES[:, 0]]  # (E, 6)
    b = tetrahedra[hit][:, _EDGES[:, 1]]
    sa, sb = s[a], s[b]
    crosses = (sa < 0) != (sb < 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(crosses, sa / (sa - sb), np.nan)
    # order each polygon's corners by angle about its centre (in the plane): crossing edges first, by angle
    p = np.where(crosses[..., None], nodes[a] + t[..., None] * (nodes[b] - nodes[a]), np.nan)
    centre = np.nanmean(p, axis=1, keepdims=True)
    basis = _basis(normal)
    rel = p - centre
    angle = np.where(crosses, np.arctan2(rel @ basis[1], rel @ basis[0]), np.inf)
    order = np.argsort(angle, axis=1)[:, :4]
    rows = np.arange(len(hit))[:, None]
    a, b, t, crosses = a[rows, order], b[rows, order], t[rows, order], crosses[rows, order]
    # a triangle (3 crossings): its fourth corner repeats the third
    a[:, 3] = np.where(crosses[:, 3], a[:, 3], a[:, 2])
    b[:, 3] = np.where(crosses[:, 3], b[:, 3], b[:, 2])
    t[:, 3] = np.where(crosses[:, 3], t[:, 3], t[:, 2])
    return a, b, t, hit


def _basis(normal: np.ndarray) -> np.ndarray:
    """Two unit vectors (2, 3) spanning the plane normal to `normal`."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(normal, e1)])


def _region_colours(names: tuple, tissue) -> list[str]:
    targets = {t.name for t in tissue.scene.targets}
    return [SKIN if n == "skin" else LESION if n in targets else TISSUE if n == "body" else OBSTACLE for n in names]


def section_figure(title: str, tissue, x: np.ndarray, targets: dict[str, np.ndarray],
                   needle_direction: np.ndarray | None = None, through: str | None = None) -> Figure:
    """The section through a lesion (`through`, default the first) at rest and deformed (mm in the plane's
    coordinates)."""
    mesh = tissue.mesh
    lesion = next((t for t in tissue.scene.targets if t.name == through), None)
    origin, (u, v) = section_plane(tissue, needle_direction, None if lesion is None else lesion.rest)
    normal = np.cross(u, v)
    a, b, t, hit = cut(mesh.nodes, mesh.tetrahedra, origin, normal)
    colours = np.array(_region_colours(mesh.region_names, tissue))[mesh.region[hit]]
    fig = Figure(figsize=(11, 5.2))
    for k, (positions, label) in enumerate(((mesh.nodes, "at rest"), (x, "deformed"))):
        ax = fig.add_subplot(1, 2, k + 1)
        p = positions[a] + t[..., None] * (positions[b] - positions[a])  # (E, 4, 3)
        plane = np.stack([(p - origin) @ u, (p - origin) @ v], axis=-1)
        ax.add_collection(PolyCollection(plane, facecolors=colours, edgecolors="0.45", linewidths=0.2))
        for c, nodes in enumerate(tissue.cup_nodes):
            q = positions[nodes] - origin
            near = np.abs(q @ normal) <= 2.0  # the patch's nodes near the plane
            ax.plot(q[near] @ u, q[near] @ v, "s", ms=3, color="k", label="cup patch" if c == 0 else None)
        for i, target in enumerate(tissue.scene.targets):
            where = target.rest if k == 0 else targets[target.name]
            ax.plot((where - origin) @ u, (where - origin) @ v, "o" if k == 0 else "*", color="k",
                    ms=6 if k == 0 else 9, label=("lesion" if k == 0 else "lesion moved") if i == 0 else None)
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_xlabel("along the cup's axis (mm)")
        ax.set_ylabel("across, in the section (mm)")
        ax.set_title(label)
        ax.legend(loc="upper right", fontsize=7, framealpha=0.85)  # ("best" searches every cut polygon: seconds)
    named = lesion.name if lesion is not None else (tissue.scene.targets[0].name if tissue.scene.targets else None)
    fig.suptitle(f"{title}\nsection through {named or 'the body'}"
                 f" (regions: {', '.join(mesh.region_names)})", fontsize=10)
    return fig


def view_figure(title: str, tissue, x: np.ndarray, targets: dict[str, np.ndarray]) -> Figure:
    """The body in 3-D at rest and deformed: skin, lesions, obstacles, cup patches and axes (mm)."""
    mesh, scene = tissue.mesh, tissue.scene
    skin = mesh.boundary_triangles[~mesh.boundary_base]
    fig = Figure(figsize=(12, 5.6))
    for k, (positions, label) in enumerate(((mesh.nodes, "at rest"), (x, "deformed"))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(positions[skin], facecolors=SKIN, edgecolors="none", alpha=0.18))
        for name, colour in zip(mesh.region_names, _region_colours(mesh.region_names, tissue)):
            if name in ("body", "skin"):
                continue
            region = np.flatnonzero(mesh.region == mesh.region_names.index(name))
            centres = positions[mesh.tetrahedra[region]].mean(axis=1)
            ax.scatter(*centres.T, s=2, color=colour, alpha=0.5, depthshade=False)
        for i, target in enumerate(scene.targets):
            where = target.rest if k == 0 else targets[target.name]
            ax.scatter(*where, s=30, color="k", marker="o" if k == 0 else "*", label="lesion" if i == 0 else None)
        for c, cup in enumerate(scene.cups):
            patch = positions[tissue.cup_nodes[c]]
            ax.scatter(*patch.T, s=4, color="k", label="cup patch" if c == 0 else None)
            tail = patch.mean(axis=0) - 15.0 * cup.axis
            ax.quiver(*tail, *(12.0 * cup.axis), color="k", arrow_length_ratio=0.3)
        lo, hi = mesh.nodes.min(axis=0), mesh.nodes.max(axis=0)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-6)))
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_zlabel("z (mm)")
        ax.set_title(label)
        ax.legend(loc="upper left", fontsize=7)
    fig.suptitle(title, fontsize=10)
    return fig


def body_figures(title: str, tissue, x: np.ndarray, strokes: dict[str, float], targets: dict[str, np.ndarray],
                 needle_direction: np.ndarray | None = None, through: str | None = None) -> list[Figure]:
    """A forward case's (or a manipulation's) figures: [the section through a lesion, the 3-D view]."""
    moved = ", ".join(f"{k} {v:+g} mm" for k, v in strokes.items())
    head = f"{title} ({moved})" if moved else title
    return [section_figure(head, tissue, x, targets, needle_direction, through), view_figure(head, tissue, x, targets)]


def manipulation_figures(m) -> list[Figure]:
    """A lesion's nominal closed loop (an `experiments.sink.Manipulation` of a body): the section through the lesion
    and the 3-D view, at rest and where the loop left the body, the desired point drawn."""
    closed = m.closed
    x = closed.final_x if closed.final_x is not None else m.tissue.mesh.nodes
    title = (f"{m.tissue.scene.name}: {m.target} moved by the closed loop ({closed.iterations} moves, "
             f"{closed.stop_reason}; miss {closed.miss_mm:.3f} mm)")
    targets = {t.name: (closed.final_position if t.name == m.target else t.rest) for t in m.tissue.scene.targets}
    direction = closed.corridor_direction if np.all(np.isfinite(closed.corridor_direction)) else None
    figs = body_figures(title, m.tissue, x, dict(zip(closed.cup_names, closed.final_strokes)), targets, direction,
                        m.target)
    origin, (u, v) = section_plane(m.tissue, direction, m.target_rest)
    for ax in figs[0].axes[1:]:
        ax.plot((closed.desired - origin) @ u, (closed.desired - origin) @ v, "x", color="k", ms=9, label="desired")
        if np.all(np.isfinite(closed.corridor_entry)):  # the planned needle, entry to the desired point
            line = np.stack([closed.corridor_entry, closed.desired]) - origin
            ax.plot(line @ u, line @ v, "-", color="#2a7f2a", lw=1.6, label="needle (planned)")
        ax.legend(loc="upper right", fontsize=7, framealpha=0.85)  # ("best" searches every cut polygon: seconds)
    return figs
