"""gmsh for the 3-D body: one quiet, single-threaded, seeded session at a time; the model; tetrahedra out.

The dome is built with the OpenCASCADE kernel: a half-spheroid (a unit
upper hemisphere dilated to semi-axes a, a, h), the skin's inner
half-spheroid and every inclusion (spheres; tubes as a disk swept along the
polyline with rounded bends, capped with half balls), fragmented together
so that every region boundary is a surface of the mesh (conforming
regions). Pieces of an inclusion outside the body are removed.

A surface body is a discrete triangulation: gmsh classifies it into
patches it can reparametrise (t13 of gmsh's tutorials), remeshes them with
the size field and fills the volume; its regions are tagged afterwards by
element centroid (body_geometry.centroid_regions).

gmsh is imported inside the functions, so importing this module does not
load it; gmsh.initialize installs no signal handlers (interruptible=False),
reads no user configuration, and is always finalised.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from scissor_cli.mesh.mesh import MeshError

#: gmsh's element type of the 4-node tetrahedron
_TETRAHEDRON = 4
#: the 3-D algorithm: 10 is HXT, gmsh's parallel Delaunay (run on one thread here)
ALGORITHM_3D = 10
#: a tube's bends are arcs of this many tube radii (body_gmsh.tube_path)
TUBE_BEND_RADII = 2.0
#: in a surface body's size expression, the distance to its surface (a Distance field once gmsh has one)
SURFACE_DISTANCE = "{surface distance}"
#: an angle between surface facets above this is a sharp edge kept when a surface body is reparametrised
SURFACE_FEATURE_ANGLE_DEG = 40.0

_LOCK = threading.Lock()

#: options of every session: the same inputs give the same mesh on every run
_OPTIONS = {
    "General.Terminal": 0,
    "General.NumThreads": 1,
    "Geometry.OCCParallel": 0,
    "Mesh.MaxNumThreads1D": 1,
    "Mesh.MaxNumThreads2D": 1,
    "Mesh.MaxNumThreads3D": 1,
    "Mesh.RandomSeed": 1,
    "Mesh.RandomFactor": 1e-9,
    "Mesh.RandomFactor3D": 1e-12,
    # the size field alone sets the size: no sizes from points, curvature or the boundary
    "Mesh.MeshSizeExtendFromBoundary": 0,
    "Mesh.MeshSizeFromPoints": 0,
    "Mesh.MeshSizeFromCurvature": 0,
    "Mesh.Algorithm": 6,
    "Mesh.Algorithm3D": ALGORITHM_3D,
    "Mesh.ElementOrder": 1,
    "Mesh.Optimize": 1,
    "Mesh.OptimizeNetgen": 0,
}


@dataclass(frozen=True, eq=False)
class GmshMesh:
    """What gmsh made: nodes (N, 3) mm, tetrahedra (M, 4) into them, and each one's region (M,) (0 untagged)."""

    nodes: np.ndarray
    tets: np.ndarray
    region: np.ndarray


@contextmanager
def session(min_edge: float, max_edge: float):
    """gmsh, initialised with the options above and the size bounds, for one mesh; finalised on the way out."""
    import gmsh

    with _LOCK:
        if gmsh.isInitialized():
            raise MeshError("gmsh is already initialised in this process by something else; the body mesher "
                            "needs a session of its own")
        gmsh.initialize(readConfigFiles=False, interruptible=False)
        try:
            for name, value in _OPTIONS.items():
                gmsh.option.setNumber(name, value)
            gmsh.option.setNumber("Mesh.MeshSizeMin", min_edge)
            gmsh.option.setNumber("Mesh.MeshSizeMax", max_edge)
            yield gmsh
        finally:
            gmsh.finalize()


def mesh_dome(radius: float, height: float, skin: float | None, inclusions: tuple, expression: str,
              min_edge: float, max_edge: float) -> GmshMesh:
    """Tetrahedra of the half-spheroid with conforming regions: 0 body, 1 skin (if any), then the inclusions."""
    with session(min_edge, max_edge) as gmsh:
        try:
            region = _dome_model(gmsh, radius, height, skin, inclusions, min_edge)
        except MeshError:
            raise
        except Exception as exc:  # gmsh raises Exception with its last error
            raise MeshError(f"gmsh could not build the dome with its inclusions ({exc}); an inclusion that "
                            f"nearly touches a surface or another inclusion is the usual cause: move it clear or "
                            f"let it cross clearly") from None
        return _generate(gmsh, expression, region)


def _dome_model(gmsh, radius: float, height: float, skin: float | None, inclusions: tuple,
                min_edge: float) -> dict[int, int]:
    """Build and fragment the dome's volumes; the region of every volume left in the body."""
    occ = gmsh.model.occ
    gmsh.model.add("dome")
    dome = _half_spheroid(occ, radius, radius, height)
    tools, owner = [], []
    if skin:
        tools.append((3, _half_spheroid(occ, radius - skin, radius - skin, height - skin)))
        owner.append("inner")
    for k, inclusion in enumerate(inclusions):
        pieces = _inclusion(occ, inclusion, min_edge)
        tools += pieces
        owner += [k] * len(pieces)
    children = occ.fragment([(3, dome)], tools)[1] if tools else [[(3, dome)]]
    in_body = {tag for _, tag in children[0]}
    inner = {tag for piece, who in zip(children[1:], owner) if who == "inner" for _, tag in piece}
    first = 2 if skin else 1
    region = {}
    for piece, who in zip(children[1:], owner):
        for _, tag in piece:
            if who != "inner" and tag in in_body:
                region[tag] = min(region.get(tag, first + who), first + who)
    for tag in in_body - set(region):
        region[tag] = 1 if skin and tag not in inner else 0
    missing = [inc.name for k, inc in enumerate(inclusions) if first + k not in region.values()]
    if missing:
        raise MeshError(f"inclusion(s) {', '.join(missing)} lie wholly outside the dome (or inside an "
                        f"inclusion given before them): nothing of them is left to mesh")
    outside = sorted({(3, tag) for piece in children[1:] for _, tag in piece} - {(3, t) for t in in_body})
    if outside:
        occ.remove(outside, recursive=True)
    occ.synchronize()
    return region


def mesh_surface(nodes: np.ndarray, triangles: np.ndarray, expression: str, min_edge: float,
                 max_edge: float, skin: float | None) -> GmshMesh:
    """Tetrahedra filling a closed, outward triangulation, its surface remeshed with the size field; regions 0.

    With a skin, SURFACE_DISTANCE in the expression becomes a Distance field
    to the surface: the distance to points sampled on it no farther apart
    than half the skin's thickness.
    """
    with session(min_edge, max_edge) as gmsh:
        gmsh.model.add("surface")
        surface = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, surface, np.arange(1, len(nodes) + 1), nodes.ravel())
        gmsh.model.mesh.addElementsByType(surface, 2, [], (triangles + 1).ravel())
        try:
            gmsh.model.mesh.classifySurfaces(np.radians(SURFACE_FEATURE_ANGLE_DEG), True, True, np.pi)
            gmsh.model.mesh.createGeometry()
        except Exception as exc:  # gmsh raises Exception with its last error
            raise MeshError(f"gmsh could not rebuild a geometry from the body's surface ({exc}); the surface may "
                            f"be too coarse or too ragged: smooth or refine it") from None
        surfaces = [tag for _, tag in gmsh.model.getEntities(2)]
        volume = gmsh.model.geo.addVolume([gmsh.model.geo.addSurfaceLoop(surfaces)])
        gmsh.model.geo.synchronize()
        if skin:
            field = gmsh.model.mesh.field.add("Distance")
            gmsh.model.mesh.field.setNumbers(field, "SurfacesList", surfaces)
            size = float(np.linalg.norm(np.ptp(nodes, axis=0)))
            gmsh.model.mesh.field.setNumber(field, "Sampling", int(np.ceil(size / (0.5 * skin))))
            expression = expression.replace(SURFACE_DISTANCE, f"F{field}")
        return _generate(gmsh, expression, {volume: 0})


def _half_spheroid(occ, a: float, b: float, c: float) -> int:
    """The solid x²/a² + y²/b² + z²/c² ≤ 1, z ≥ 0: a unit upper hemisphere (flat base) dilated."""
    tag = occ.addSphere(0.0, 0.0, 0.0, 1.0, angle1=0.0, angle2=np.pi / 2)
    occ.dilate([(3, tag)], 0.0, 0.0, 0.0, a, b, c)
    return tag


def _inclusion(occ, inclusion, min_edge: float) -> list[tuple[int, int]]:
    """The inclusion as OCC volumes: a sphere, or a tube (a disk swept along tube_path, half balls on both ends)."""
    if hasattr(inclusion, "center_mm"):
        return [(3, occ.addSphere(*map(float, inclusion.center_mm), float(inclusion.radius_mm)))]
    r = float(inclusion.radius_mm)
    points = inclusion.points_mm
    curves, previous = [], occ.addPoint(*map(float, points[0]))
    for center, end in tube_path(inclusion.name, points, r, min_edge):
        stop = occ.addPoint(*map(float, end))
        if center is None:
            curves.append(occ.addLine(previous, stop))
        else:
            curves.append(occ.addCircleArc(previous, occ.addPoint(*map(float, center)), stop))
        previous = stop
    wire = occ.addWire(curves)
    axis = points[1] - points[0]
    disk = occ.addDisk(*map(float, points[0]), r, r, zAxis=list(map(float, axis / np.linalg.norm(axis))))
    pipe = occ.addPipe([(2, disk)], wire, "DiscreteTrihedron")
    seams = _end_seams(occ, pipe, points[[0, -1]])
    ends = [_cap(occ, points[0], points[0] - points[1], seams[0], r),
            _cap(occ, points[-1], points[-1] - points[-2], seams[1], r)]
    fused, _ = occ.fuse(pipe, ends)
    return fused


def _end_seams(occ, pipe: list, ends: np.ndarray) -> list[np.ndarray]:
    """Where the circle of each of the pipe's two end faces begins (its seam), nearest end first."""
    import gmsh

    occ.synchronize()
    seams = [None, None]
    for _, face in gmsh.model.getBoundary(pipe, oriented=False):
        if gmsh.model.getType(2, face) != "Plane":
            continue
        k = int(np.argmin(np.linalg.norm(ends - np.array(occ.getCenterOfMass(2, face)), axis=1)))
        curve = abs(gmsh.model.getBoundary([(2, face)], oriented=False)[0][1])
        start = gmsh.model.getParametrizationBounds(1, curve)[0]
        seams[k] = np.array(gmsh.model.getValue(1, curve, start))
    if any(seam is None for seam in seams):
        raise MeshError("gmsh made a tube without its two flat end faces")
    return seams


def _cap(occ, center: np.ndarray, outward: np.ndarray, seam: np.ndarray, r: float) -> tuple[int, int]:
    """The half ball of radius r on the pipe's end face at `center`, facing `outward`, its seam on the pipe's.

    Its flat face is the pipe's end face: a whole ball would touch the pipe
    along a circle, two tangent surfaces to intersect, an ill-conditioned
    boolean. And the meridian where OpenCASCADE's sphere closes starts where
    the end face's circle does: anywhere else, the two split the circle
    into an arc of micrometres that the mesh must resolve.
    """
    tag = occ.addSphere(0.0, 0.0, 0.0, r, angle1=0.0, angle2=np.pi / 2)  # its seam starts at +x
    n = outward / np.linalg.norm(outward)
    axis = np.cross([0.0, 0.0, 1.0], n)
    sin, cos = float(np.linalg.norm(axis)), float(n[2])
    if sin > 1e-12:
        k = axis / sin
        angle = float(np.arctan2(sin, cos))
    else:
        k, angle = np.array([1.0, 0.0, 0.0]), (0.0 if cos > 0 else np.pi)
    # turn about z first so that the turn onto n brings +x onto the seam's direction
    toward = _rotated(seam - center, k, -angle)
    occ.rotate([(3, tag)], 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, float(np.arctan2(toward[1], toward[0])))
    if angle:
        occ.rotate([(3, tag)], 0.0, 0.0, 0.0, *map(float, k), angle)
    occ.translate([(3, tag)], *map(float, center))
    return (3, tag)


def _rotated(v: np.ndarray, k: np.ndarray, angle: float) -> np.ndarray:
    """v turned by `angle` about the unit axis k (Rodrigues)."""
    return v * np.cos(angle) + np.cross(k, v) * np.sin(angle) + k * (k @ v) * (1 - np.cos(angle))


def tube_path(name: str, points: np.ndarray, r: float, min_arc: float) -> list[tuple[np.ndarray | None, np.ndarray]]:
    """The tube's axis with its corners rounded, from points[0] on: pieces (None, end) of line, (centre, end) of arc.

    A union of cylinders and balls has, at every bend, two tangent seams
    that pinch the ball's face to a lens as thin as the bend is gentle: the
    surface mesh gets needles and the volume slivers. Sweeping the disk along
    a path whose corners are arcs gives a smooth tube that differs from the
    union only at the outside of each bend. An arc's radius is TUBE_BEND_RADII
    · r, or more where the bend is so gentle that the arc would be shorter
    than `min_arc` (the mesh's smallest edge: a shorter arc is a short edge
    of the geometry, and small elements around it); less where the segments
    are short, but never below the tube's radius, where the sweep would fold.
    """
    u = np.diff(points, axis=0)
    length = np.linalg.norm(u, axis=1)
    u = u / length[:, None]
    pieces = []
    for i in range(1, len(points) - 1):
        turn = float(np.arccos(np.clip(u[i - 1] @ u[i], -1.0, 1.0)))
        if turn < 1e-6:
            continue
        half = np.tan(turn / 2)
        radius = min(max(TUBE_BEND_RADII * r, min_arc / turn), 0.5 * min(length[i - 1], length[i]) / half)
        if radius < 1.01 * r:
            raise MeshError(f"the tube {name} turns by {np.degrees(turn):.0f}° at its point {i}, too sharply for its "
                            f"radius of {r:g} mm with segments of {length[i - 1]:.3g} and {length[i]:.3g} mm: give it "
                            f"longer segments or a gentler bend")
        into, out = points[i] - radius * half * u[i - 1], points[i] + radius * half * u[i]
        bisector = (u[i] - u[i - 1]) / np.linalg.norm(u[i] - u[i - 1])
        pieces += [(None, into), (points[i] + bisector * radius / np.cos(turn / 2), out)]
    return pieces + [(None, points[-1])]


def _generate(gmsh, expression: str, region: dict[int, int]) -> GmshMesh:
    field = gmsh.model.mesh.field.add("MathEval")
    gmsh.model.mesh.field.setString(field, "F", expression)
    gmsh.model.mesh.field.setAsBackgroundMesh(field)
    try:
        gmsh.model.mesh.generate(3)
    except Exception as exc:  # gmsh raises Exception with its last error
        raise MeshError(f"gmsh could not mesh the body ({exc}). Most often two surfaces nearly touch: an "
                        f"inclusion grazing the body's surface, its base, the skin's inner surface or another "
                        f"inclusion by less than about min_edge_mm; move it clear or let it cross clearly, or make "
                        f"min_edge_mm smaller") from None
    tags, coords, _ = gmsh.model.mesh.getNodes(returnParametricCoord=False)
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    tets, where = [], []
    for _, volume in gmsh.model.getEntities(3):  # a handful of volumes: the body, the skin, the inclusions
        types, _, connectivity = gmsh.model.mesh.getElements(3, volume)
        for kind, nodes in zip(types, connectivity):
            if kind != _TETRAHEDRON:
                raise MeshError(f"gmsh made elements of type {kind} besides tetrahedra")
            tets.append(index[nodes.astype(np.int64).reshape(-1, 4)])
            where.append(np.full(len(tets[-1]), region[volume], np.int64))
    if not tets:
        raise MeshError("gmsh made no tetrahedra for the body")
    return GmshMesh(coords.reshape(-1, 3).copy(), np.concatenate(tets), np.concatenate(where))
