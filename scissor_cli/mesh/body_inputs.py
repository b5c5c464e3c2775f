"""A 3-D scene's mesh: what the mesher takes of the scene, and the mesh at a scale (docs/model.md §19, "Mesh").

The scene's lesions and obstacles become the mesher's inclusions (each a
tagged region), its cup patches the size field's refine patches, and its
`tissue.mesh` section the sizing (the edge bounds × `scale` × the ladder's scale).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scissor_cli.config.body_checks import DomeSurface
from scissor_cli.config.body_mesh_file import read_body_mesh_arrays
from scissor_cli.config.body_sections import BodyMeshConfig
from scissor_cli.mesh import body_quality
from scissor_cli.mesh.body_mesh import BodyMesh, BodyShape, BodySizing, Sphere, Tube, body_mesh
from scissor_cli.scene.body_scene import BodyScene


def body_shape(scene: BodyScene) -> BodyShape:
    """The body's shape as the mesher takes it."""
    s = scene.surface
    if isinstance(s, DomeSurface):
        return BodyShape("dome", radius_mm=s.radius_mm, height_mm=s.height_mm,
                         skin_thickness_mm=scene.skin_thickness_mm)
    return BodyShape("surface", surface_nodes=s.nodes, surface_triangles=s.triangles,
                     skin_thickness_mm=scene.skin_thickness_mm)


def inclusions(scene: BodyScene) -> tuple:
    """The lesions (spheres) and obstacles (spheres and tubes), in that order: the mesh's regions after body/skin."""
    out = [Sphere(t.name, np.asarray(t.rest, float), t.radius_mm) for t in scene.targets]
    for o in scene.obstacles:
        out.append(Sphere(o.name, o.points[0], o.radius_mm) if o.kind == "sphere" else
                   Tube(o.name, o.points, o.radius_mm))
    return tuple(out)


def sizing(scene: BodyScene, mesh: BodyMeshConfig, scale: float = 1.0) -> BodySizing:
    """The size field at a scale (the smallest and largest edge × mesh.scale × scale; the grading, edge per mm
    of distance, unscaled: a graded body coarsens far less than the factor), fine at the cups' patches."""
    f = mesh.scale * scale
    return BodySizing(mesh.min_edge_mm * f, mesh.max_edge_mm * f, mesh.grading,
                      tuple((c.contact, c.radius_mm) for c in scene.cups))


def mesh_body(scene: BodyScene, mesh: BodyMeshConfig, scale: float = 1.0, cache: Path | None = None) -> BodyMesh:
    """The scene's tetrahedral mesh at a scale (cached in `cache` when given), or its pinned mesh file."""
    if mesh.file is not None:
        return pinned_body_mesh(mesh.file, scene)
    return body_mesh(body_shape(scene), inclusions(scene), sizing(scene, mesh, scale), cache_dir=cache)


def pinned_body_mesh(path: str | Path, scene: BodyScene) -> BodyMesh:
    """A `BodyMesh` from a mesh file (`config.body_mesh_file`, checked when the config was): its outer faces, which
    lie on the dome's base, and its smallest dihedral angle recomputed from the tetrahedra."""
    nodes, tets, region, names = read_body_mesh_arrays(path)
    faces = body_quality.boundary_faces(tets)
    size = float(np.ptp(nodes, axis=0).max())
    base = (np.all(np.abs(nodes[faces][:, :, 2]) <= 1e-9 * size, axis=1) if scene.shape == "dome"
            else np.zeros(len(faces), bool))
    return BodyMesh(nodes, tets, region, names, faces, base,
                    float(body_quality.min_dihedral_deg(nodes, tets).min()))
