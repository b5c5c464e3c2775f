"""The 3-D slab as a `Tissue`: extruded mesh, the §3 energies with 3x3 F, its boundary (docs/model.md §13).

The slab is the layer's outline extruded over the height H (z from 0, the
chest wall, to H). It is a `mechanics.Tissue` of dimension 3, so the one
Newton solver (`solvers.equilibrium`) solves it unchanged.

Boundary:
* the 2-D fixed sides become fixed faces (every level of their nodes);
* `chest_wall_fixed`: the face z = 0 is held;
* a cup grips the free side-surface nodes nearest its contact point at the
  layer's height (3-D distance) whose shares of the side surface add up to
  its disc, π r² within the slab's height (`side_patch`, as the body's cups:
  `mechanics.patch`), and moves them along its in-plane axis;
  `cup_holds_z` also holds them vertically (else z is free there);
* for the checks only: `grip_full_height` grips the cup's 2-D nodes at
  every level, `hold_z` holds the out-of-plane displacement everywhere.

Material: the scene's model and constants per element (obstacles' factors
follow the triangle a tetrahedron came from); fibers (cos θ, sin θ, 0), in
the layer's plane.

In-plane resolution (`SlabSpec.plane`): the slab extrudes the layer's own
2-D mesh, or a coarser mesh of the same scene (`layer_check.in_plane_scale`:
every edge length of `tissue.mesh` times the scale, still fine at targets,
obstacles and cups). The layer's nodes are then points of the slab like
the targets: `layer_probe` carries them (exactly the slab's layer nodes
when the slab extrudes the layer's mesh).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from scissor_cli.geometry import graded_levels
from scissor_cli.layer3d.extrude import SlabMesh, extrude
from scissor_cli.mechanics import fem
from scissor_cli.mechanics.patch import PATCH_AREA_LIMIT, disc_area_in_strip, nearest_patch
from scissor_cli.mechanics.tissue import BoundaryError, Tissue, scene_material, tissue_from_boundary
from scissor_cli.mesh.mesh import Mesh, build_mesh
from scissor_cli.mesh.probe import probe_targets
from scissor_cli.scene.scene import Scene


@dataclass(frozen=True)
class SlabSpec:
    """What `layer_check` asks for (mm), plus the check-only options (docs/model.md §13)."""

    height_mm: float
    layer_z_mm: float
    chest_wall_fixed: bool = True
    cup_holds_z: bool = True
    max_layer_mm: float = 5.0
    #: the thinnest prism layer, at the simulated layer (default: the 2-D mesh's finest edge)
    first_layer_mm: float | None = None
    grip_full_height: bool = False
    hold_z: bool = False
    #: explicit z levels (L,) instead of the graded ones (tests, the one-layer plane-stress slab)
    levels_mm: tuple | None = None
    #: the slab's own 2-D mesh, `mesh.build_mesh`'s (min_edge_mm, max_edge_mm, min_angle_deg, grading, graded);
    #: None: the layer's mesh
    plane: tuple | None = None


def plane_mesh(scene: Scene, mesh: Mesh, spec: SlabSpec) -> Mesh:
    """The 2-D mesh the slab extrudes: the layer's `mesh`, or the scene meshed as `spec.plane` says."""
    if spec.plane is None:
        return mesh
    min_edge, max_edge, min_angle, grading, graded = spec.plane
    return build_mesh(scene, min_edge, max_edge, min_angle, grading, graded)


def slab_mesh(mesh: Mesh, spec: SlabSpec) -> SlabMesh:
    """The extruded mesh of a 2-D mesh (the slab's plane: `plane_mesh`) for a slab spec."""
    if spec.levels_mm is not None:
        levels = np.asarray(spec.levels_mm, float)
        layer = int(np.argmin(np.abs(levels - spec.layer_z_mm)))
    else:
        first = spec.first_layer_mm or float(np.min(mesh.edge_lengths()))
        levels, layer = graded_levels(spec.height_mm, spec.layer_z_mm, first, spec.max_layer_mm)
    return replace(extrude(mesh.nodes, mesh.triangles, mesh.element_obstacle, levels, layer), plane=mesh)


def build_slab(scene: Scene, mesh: Mesh, spec: SlabSpec, model: str | None = None, element: str = "p1") -> Tissue:
    """The slab tissue (dim 3) of a scene and its layer's 2-D mesh; BoundaryError if a cup grips nothing.
    `element`: the layer's ("p1" or "nodal", docs/model.md §21)."""
    mesh = plane_mesh(scene, mesh, spec)
    sm = slab_mesh(mesh, spec)
    element_E, fiber, params = scene_material(scene, sm.element_obstacle, model)
    fixed2 = mesh.boundary_nodes_on_sides(scene.fixed_sides)
    if len(fixed2) == 0:
        raise BoundaryError(f"no mesh node lies on the fixed side(s) {list(scene.fixed_sides)}")
    fixed = sm.column(fixed2)
    if spec.chest_wall_fixed:
        fixed = np.union1d(fixed, sm.node(0, np.arange(sm.n_nodes_2d)))
    cup_nodes = []
    for cup in scene.cups:
        if spec.grip_full_height:
            nodes = np.setdiff1d(sm.column(mesh.boundary_nodes_near(cup.contact, cup.radius_mm)), fixed)
        else:
            nodes = side_patch(sm, fixed, cup.contact, cup.radius_mm)
        if len(nodes) == 0:
            raise BoundaryError(f"cup {cup.name!r} (radius {cup.radius_mm:g} mm) grips no free side-surface node of "
                                f"the slab: its nearest one alone stands for more than {PATCH_AREA_LIMIT:g}× the "
                                "cup's area; refine the slab at the cup (tissue.mesh, layer_check.max_layer_mm)")
        for other, prev in zip(scene.cups, cup_nodes):  # (a node held by two cups would move by both strokes)
            if np.intersect1d(nodes, prev).size:
                raise BoundaryError(f"cups {other.name!r} and {cup.name!r} grip the same side-surface nodes of the "
                                    "slab: move them apart or shrink radius_mm")
        cup_nodes.append(np.sort(nodes))
    grip = np.unique(np.concatenate(cup_nodes)) if cup_nodes else np.zeros(0, np.int64)
    dirichlet = [3 * fixed, 3 * fixed + 1, 3 * fixed + 2, 3 * grip, 3 * grip + 1]
    if spec.cup_holds_z:
        dirichlet.append(3 * grip + 2)
    if spec.hold_z:
        dirichlet.append(3 * np.arange(sm.n_nodes) + 2)
    dirichlet = np.unique(np.concatenate(dirichlet)).astype(np.int64)
    ops = fem.simplex_operators(sm.nodes, sm.triangles)
    axes = np.zeros((len(scene.cups), 3))
    if len(scene.cups):
        axes[:, :2] = np.array([c.axis for c in scene.cups])
    return tissue_from_boundary(scene, sm, ops, (element_E, fiber, params), fixed, cup_nodes, axes, dirichlet,
                                element)


def side_shares(sm: SlabMesh) -> tuple[np.ndarray, np.ndarray]:
    """The side surface's nodes (S,) and each one's share of it (S,) mm²: half the boundary edges at its 2-D
    vertex times half the prism layers at its level (the side faces are the boundary edges extruded)."""
    plane = sm.plane
    edges = plane.boundary_edges
    length = np.linalg.norm(plane.nodes[edges[:, 0]] - plane.nodes[edges[:, 1]], axis=1)
    along = np.bincount(edges.ravel(), weights=np.repeat(0.5 * length, 2), minlength=sm.n_nodes_2d)
    layers = np.diff(sm.levels_mm)
    up = np.zeros(sm.levels_mm.size)
    up[:-1] += 0.5 * layers
    up[1:] += 0.5 * layers
    vertices = np.unique(edges)
    surface = sm.column(vertices)  # level by level, each level's vertices in `vertices`' order
    level = surface // sm.n_nodes_2d
    return surface, along[surface - level * sm.n_nodes_2d] * up[level]


def side_patch(sm: SlabMesh, fixed: np.ndarray, contact: np.ndarray, radius_mm: float) -> np.ndarray:
    """The free side-surface nodes (P,) a cup of radius_mm at its 2-D contact (2,) mm grips: those nearest the
    contact at the layer's height whose shares (`side_shares`) add up closest to the cup's disc within the
    slab's height (`patch.nearest_patch`); empty when the mesh is too coarse there."""
    surface, shares = side_shares(sm)
    free = ~np.isin(surface, fixed)
    z_layer = float(sm.levels_mm[sm.layer_level])
    centre = np.array([contact[0], contact[1], z_layer])
    area = disc_area_in_strip(radius_mm, z_layer - float(sm.levels_mm[0]), float(sm.levels_mm[-1]) - z_layer)
    return nearest_patch(surface[free], sm.nodes[surface[free]], shares[free], centre, area)


@dataclass(frozen=True)
class SlabProbe:
    """Points of the layer carried by the slab: the 2-D probe's weights on the layer level's nodes.

    The layer's triangles at its level are faces of tetrahedra, so P1
    interpolation there is exactly the 2-D weights. nodes (K, 3) 3-D node
    indices, bary (K, 3).
    """

    nodes: np.ndarray
    bary: np.ndarray

    def positions(self, x: np.ndarray) -> np.ndarray:
        """Deformed points (K, 3) mm for slab positions x (N3, 3)."""
        return np.einsum("kj,kjd->kd", self.bary, np.asarray(x, float)[self.nodes])

    def response(self, D: np.ndarray) -> np.ndarray:
        """The points' response (K, 3, C) to nodal vectors D (3 N3, C) (e.g. the tangent response to the strokes)."""
        D3 = np.asarray(D, float).reshape(-1, 3, D.shape[1])
        return np.einsum("kj,kjdc->kdc", self.bary, D3[self.nodes])


def slab_probe(slab: Tissue, points: np.ndarray) -> SlabProbe:
    """The slab probe of rest points (K, 2) mm of the layer (ValueError if one lies outside it)."""
    probe = probe_targets(slab.mesh.plane, points)
    return SlabProbe(slab.mesh.node(slab.mesh.layer_level, probe.nodes), probe.bary)


def layer_probe(slab: Tissue, mesh: Mesh) -> SlabProbe:
    """The nodes (N2,) of the layer's 2-D `mesh` as points of the slab: exactly the slab's layer nodes (weights
    1, 0, 0) when the slab extrudes that mesh, else each node by its triangle of the slab's plane."""
    sm: SlabMesh = slab.mesh
    if sm.plane is mesh:
        n = mesh.n_nodes
        nodes = np.repeat(sm.layer_nodes[:, None], 3, axis=1)
        return SlabProbe(nodes, np.column_stack([np.ones(n), np.zeros(n), np.zeros(n)]))
    return slab_probe(slab, mesh.nodes)
