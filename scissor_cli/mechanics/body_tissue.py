"""The 3-D body as a `Tissue`: its tetrahedra, regions' materials, held base and cup patches (docs/model.md §19).

The same `Tissue` of dimension 3 as the slab (`layer3d.slab`): P1
tetrahedra, the §3 energies with a 3×3 F, every dof of a held or gripped
node a Dirichlet dof, solved by the one Newton (`solvers.equilibrium`).

* Materials by region: the body E; the skin shell `skin_E_kPa`; a lesion
  or an obstacle E × its stiffness_factor. ν, η and the model are the
  scene's everywhere.
* Fibers: uniform — (cos θ, sin θ, 0), θ = material.fiber_angle_deg in the
  platform's plane; radial — from each element's centroid towards the
  body's apex.
* Held: the dome's base (the nodes of its faces on z = 0), or a surface
  body's boundary nodes on its held planes.
* A cup grips the skin nodes nearest its contact (the nearest skin point
  to where the scene put it) whose shares of the skin add up to its area
  π r² (`cup_patch`), and moves them rigidly along its axis.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.mechanics import fem, materials
from scissor_cli.mechanics.patch import PATCH_AREA_LIMIT, nearest_patch
from scissor_cli.mechanics.tissue import BoundaryError, Tissue, tissue_from_boundary
from scissor_cli.mesh.body_mesh import BodyMesh
from scissor_cli.scene.body_scene import BodyScene

#: a boundary node lies on a held plane when it is this close to it (× the body's size)
PLANE_TOL = 1e-6


def region_E(scene: BodyScene, mesh: BodyMesh) -> np.ndarray:
    """Young's modulus (M,) kPa of every tetrahedron, by its region."""
    E = scene.material.E_kPa
    by_name = {"body": E, "skin": scene.skin_E_kPa if scene.skin_E_kPa is not None else E}
    by_name.update({t.name: E * t.stiffness_factor for t in scene.targets})
    by_name.update({o.name: E * o.stiffness_factor for o in scene.obstacles})
    per_region = np.array([by_name[name] for name in mesh.region_names], float)
    return per_region[mesh.region]


def body_fibers(scene: BodyScene, mesh: BodyMesh) -> np.ndarray:
    """Unit fiber directions (M, 3) in the reference frame (uniform, or radial to the apex)."""
    m = mesh.n_elements
    if scene.fibers == "uniform":
        a = scene.material.fiber_angle_rad
        return np.tile([np.cos(a), np.sin(a), 0.0], (m, 1))
    centroids = mesh.nodes[mesh.tetrahedra].mean(axis=1)
    to_apex = scene.apex - centroids
    length = np.linalg.norm(to_apex, axis=1, keepdims=True)
    return np.where(length > 1e-9, to_apex / np.maximum(length, 1e-300), np.array([0.0, 0.0, 1.0]))


def held_nodes(scene: BodyScene, mesh: BodyMesh) -> np.ndarray:
    """Nodes (F,) held still: the dome's base, or the boundary nodes on a surface body's held planes."""
    if scene.shape == "dome":
        return np.unique(mesh.boundary_triangles[mesh.boundary_base])
    boundary = np.unique(mesh.boundary_triangles)
    tol = PLANE_TOL * float(np.ptp(mesh.nodes, axis=0).max())
    on = np.zeros(boundary.size, bool)
    for point, normal in scene.held_planes:
        on |= np.abs((mesh.nodes[boundary] - point) @ normal) <= tol
    return boundary[on]


def skin_nodes(scene: BodyScene, mesh: BodyMesh, held: np.ndarray) -> np.ndarray:
    """The boundary nodes (S,) a cup may grip: those of the boundary not held."""
    boundary = np.unique(mesh.boundary_triangles)
    return np.setdiff1d(boundary, held)


def skin_areas(mesh: BodyMesh, skin: np.ndarray) -> np.ndarray:
    """Each skin node's share of the skin (S,) mm²: a third of the area of every skin face it is a corner of
    (the faces not on the held base), for the nodes `skin` (S,)."""
    faces = mesh.boundary_triangles[~mesh.boundary_base]
    corners = mesh.nodes[faces]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    per_node = np.bincount(faces.ravel(), weights=np.repeat(area / 3.0, 3), minlength=mesh.n_nodes)
    return per_node[skin]


def cup_patch(mesh: BodyMesh, skin: np.ndarray, contact: np.ndarray, radius_mm: float) -> np.ndarray:
    """The skin nodes (P,) a cup of radius_mm at `contact` (3,) mm grips: the nearest ones to the contact whose
    skin shares (`skin_areas`) add up closest to the cup's area π r², the nearest node at least
    (`patch.nearest_patch`). Empty when even the nearest node's share exceeds PATCH_AREA_LIMIT × π r² (the
    mesh is too coarse at the cup)."""
    return nearest_patch(skin, mesh.nodes[skin], skin_areas(mesh, skin), contact, np.pi * radius_mm**2)


def build_body(scene: BodyScene, mesh: BodyMesh, model: str | None = None, *, element: str) -> Tissue:
    """The body tissue (dim 3) of a scene on its mesh; `model` overrides the material model; `element` "p1" or
    "nodal" (docs/model.md §21; no default here: a config's `tissue.mesh.element` has the one). BoundaryError
    when nothing is held or a cup is smaller than the mesh at it (`cup_patch`)."""
    m = scene.material
    model = model or m.model
    element_E = region_E(scene, mesh)
    fiber = body_fibers(scene, mesh)
    params = materials.material_params(model, element_E, m.nu, m.eta_kPa if model == "neo_hookean_fiber" else 0.0,
                                       fiber, m.tension_only)
    fixed = held_nodes(scene, mesh)
    if fixed.size == 0:
        raise BoundaryError("no mesh node lies on the body's held face(s)")
    skin = skin_nodes(scene, mesh, fixed)
    cup_nodes = []
    for cup in scene.cups:
        nodes = cup_patch(mesh, skin, cup.contact, cup.radius_mm)
        if nodes.size == 0:
            raise BoundaryError(f"cup {cup.name!r} (radius {cup.radius_mm:g} mm at "
                                f"{np.round(cup.contact, 3).tolist()}) is smaller than the mesh there: its nearest "
                                f"skin node alone stands for more than {PATCH_AREA_LIMIT:g}× the cup's area; refine "
                                "tissue.mesh at the cup")
        for other, prev in zip(scene.cups, cup_nodes):
            if np.intersect1d(nodes, prev).size:
                raise BoundaryError(f"cups {other.name!r} and {cup.name!r} grip the same skin nodes")
        cup_nodes.append(np.sort(nodes))
    held = np.unique(np.concatenate([fixed, *cup_nodes])) if cup_nodes else fixed
    dirichlet = np.sort((3 * held[:, None] + np.arange(3)).ravel()).astype(np.int64)
    ops = fem.simplex_operators(mesh.nodes, mesh.tetrahedra)
    axes = np.array([c.axis for c in scene.cups], float).reshape(-1, 3)
    return tissue_from_boundary(scene, mesh, ops, (element_E, fiber, params), fixed, cup_nodes, axes, dirichlet,
                                element)
