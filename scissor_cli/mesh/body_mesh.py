"""Tetrahedral meshes of 3-D breast bodies with gmsh (docs/model.md §19).

A body is a dome (a half-spheroid on the platform z = 0) or any closed
triangulated surface (a scan), optionally with a skin shell, holding
inclusions: spheres (lesions, cysts) and tubes (vessels). The mesh is fine
(min_edge_mm) at and inside every inclusion and at the refine patches and
grows with `grading` per mm of distance to max_edge_mm, the 2-D mesher's
rule; a skin shell is meshed at twice its thickness and graded inward the
same way (body_field.py). The dome's regions conform (every region boundary
is a surface of the mesh); a surface body's regions follow the element
centroids. body_gmsh.py builds and meshes the model, body_quality.py checks
the tetrahedra, body_geometry.py holds the numpy geometry.

Inputs and outputs are plain arrays and the dataclasses below; the config,
scene and mechanics layers convert to and from them. The arrays-holding
dataclasses compare by identity (eq=False): equality of numpy arrays has no
single truth value.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from scissor_cli.mesh import body_field, body_geometry, body_gmsh, body_quality
from scissor_cli.mesh.body_field import Features, density_integral
from scissor_cli.mesh.mesh import MeshError

__all__ = ["MESHER_VERSION", "MIN_DIHEDRAL_DEG", "ESTIMATE_FACTOR", "BodyMesh", "BodyShape", "BodySizing", "MeshError",
           "Sphere", "Tube", "body_mesh", "estimate_tetrahedra"]

#: part of every cache key: raise it when a change here changes the meshes made from the same inputs
MESHER_VERSION = 2

#: the smallest dihedral angle a mesh may keep after gmsh's optimisation; below it body_mesh raises MeshError.
#: Measured (benchmarks/bench_body_mesh.py, docs/model.md §19): the example's dome at 10k to 100k tetrahedra
#: keeps 12° and more; of 30 random domes (inclusions, a bent vessel, skin or not) the 29 that meshed kept
#: 4.5° to 14.6° (median 12.6°), and the one refused had 2.0° where its vessel grazed the skin's inner
#: surface at the base. Meshes of scenes where an inclusion nearly touches a surface had 0.2° to 2°. The bound
#: sits in that gap: it refuses the geometric defect (a sliver no optimiser can remove, its four corners on
#: two surfaces a hair apart) and none of the ordinary meshes, whose worst element still has a bounded
#: condition number for the solvers.
MIN_DIHEDRAL_DEG = 3.0

#: real tetrahedra per ∫ w dV / V_regular(h(p)) of the size field (estimate_tetrahedra's docstring)
ESTIMATE_FACTOR = 0.46
#: ... and a skin shell's weight w = max(1, SHELL_FACTOR · h / t) (body_field.density_integral)
SHELL_FACTOR = 1.6

#: an inclusion's edge at and inside it, per mm of its radius, where that is below min_edge_mm: its faceted
#: surface then holds its volume to within 10 % (an inscribed polyhedron of edge h on a ball of radius r falls
#: short by about (h / r)² / 2: the example's 2 mm lesions at 1.5 mm edges were 18 % short;
#: benchmarks/bench_body_mesh.py)
INCLUSION_EDGE_PER_RADIUS = 0.4

#: the edge length in a skin shell, per mm of its thickness (clipped to min_edge..max_edge): a shell
#: two elements across at most, not flat tetrahedra spanning it
SKIN_EDGE_PER_THICKNESS = 2.0

#: coordinates this close to z = 0, relative to the dome's size, lie on its base
_BASE_TOLERANCE = 1e-9


@dataclass(frozen=True, eq=False)
class Sphere:
    """A lesion or a cyst."""

    name: str
    center_mm: np.ndarray  # (3,)
    radius_mm: float


@dataclass(frozen=True, eq=False)
class Tube:
    """A vessel: what lies within radius_mm of a polyline (cylinders along the segments, balls at its points).

    In the dome, the disk is swept along the polyline with its bends rounded
    (body_gmsh.tube_path) and capped with half balls: the same tube but for
    a sliver at the outside of each bend.
    """

    name: str
    points_mm: np.ndarray  # (P, 3), P >= 2
    radius_mm: float


@dataclass(frozen=True, eq=False)
class BodyShape:
    kind: str  # "dome" | "surface"
    radius_mm: float = 0.0  # dome: base radius on the platform z = 0 (centred at the origin)
    height_mm: float = 0.0  # dome: apex height; the dome is x²/a² + y²/a² + z²/h² ≤ 1, z ≥ 0
    surface_nodes: np.ndarray | None = None  # surface: (V, 3) mm, a closed manifold triangulation
    surface_triangles: np.ndarray | None = None  # (T, 3) int, outward orientation
    skin_thickness_mm: float | None = None  # optional skin shell: the outer layer of this thickness (not on the base)


@dataclass(frozen=True, eq=False)
class BodySizing:
    min_edge_mm: float  # at the inclusions' surfaces and inside them, and at the refine patches
    max_edge_mm: float  # far from every feature
    grading: float  # h = clip(min + grading * distance to the nearest feature, min, max)
    refine: tuple = ()  # ((center (3,), radius_mm), ...): cup patches on the skin, fine within the radius


@dataclass(frozen=True, eq=False)
class BodyMesh:
    nodes: np.ndarray  # (N, 3) float64 mm
    tetrahedra: np.ndarray  # (M, 4) int64, every one of positive volume
    region: np.ndarray  # (M,) int64 index into region_names
    region_names: tuple  # ("body", "skin" if a shell, then every inclusion's name in the order given)
    boundary_triangles: np.ndarray  # (S, 3) int64: the body's outer boundary faces, outward normals
    boundary_base: np.ndarray  # (S,) bool: the face lies on the dome's base z = 0 (always False for a surface)
    min_dihedral_deg: float

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_elements(self) -> int:
        return len(self.tetrahedra)


def estimate_tetrahedra(shape: BodyShape, inclusions: tuple, sizing: BodySizing) -> int:
    """The tetrahedron count the mesher will make, estimated before meshing (the element budget is refused on it).

    ESTIMATE_FACTOR × ∫ w dV / V(h(p)) over the body, V(h) = h³/(6√2) the
    volume of the regular tetrahedron of edge h, h(p) the size field the
    mesher hands gmsh and w the skin shell's weight (SHELL_FACTOR · h / t in
    a shell of thickness t, at least 1): a shell thinner than its elements
    holds flat tetrahedra, more per volume. The integral runs on adaptive
    cells (body_field.density_integral; 0.01 to 1.5 s).

    The fit: `python3 benchmarks/bench_body_mesh.py --fit` meshes 24 bodies
    (the example's dome with and without a 1.5 mm skin at gradings 0.15 to
    1.0 and two sizes; an icosphere and a box from surfaces, with and without
    a skin; 3k to 84k tetrahedra) and picks the two factors that minimise the
    worst |log(real / estimate)|: every one of them is within a factor 1.38
    of its estimate (gmsh's HXT makes about half the tetrahedra of regular
    ones of edge h; more where the grading is steep). tests/test_body_mesh.py
    holds four bodies to a factor 2.
    """
    shape, inclusions, sizing = _checked(shape, inclusions, sizing)
    features = _features(shape, inclusions, sizing)
    if shape.kind == "dome":
        a, h = shape.radius_mm, shape.height_mm
        inside = body_geometry.dome_inside(a, h)
        lo, hi = np.array([-a, -a, 0.0]), np.array([a, a, h])
    else:
        inside = body_geometry.surface_inside(shape.surface_nodes, shape.surface_triangles)
        lo, hi = shape.surface_nodes.min(axis=0), shape.surface_nodes.max(axis=0)
    return int(round(ESTIMATE_FACTOR * density_integral(features, inside, lo, hi, SHELL_FACTOR)))


def body_mesh(shape: BodyShape, inclusions: tuple, sizing: BodySizing, cache_dir: Path | None = None) -> BodyMesh:
    """Mesh the body with gmsh (tetrahedra, the size field, gmsh's optimisation), tag regions, check quality.

    With cache_dir, the mesh is cached there as an .npz named by a hash of
    every input (arrays included), the gmsh version and MESHER_VERSION; a
    cached mesh is returned without meshing. MeshError when gmsh fails or the
    smallest dihedral angle is below MIN_DIHEDRAL_DEG.
    """
    shape, inclusions, sizing = _checked(shape, inclusions, sizing)
    names = ("body",) + (("skin",) if shape.skin_thickness_mm else ()) + tuple(inc.name for inc in inclusions)
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"body_mesh_{_cache_key(shape, inclusions, sizing)}.npz"
        cached = _load(path, names)
        if cached is not None:
            return cached
    features = _features(shape, inclusions, sizing)
    expression = features.gmsh_expression()
    if shape.kind == "dome":
        raw = body_gmsh.mesh_dome(shape.radius_mm, shape.height_mm, shape.skin_thickness_mm, inclusions,
                                  expression, features.floor, sizing.max_edge_mm)
    else:
        raw = body_gmsh.mesh_surface(shape.surface_nodes, shape.surface_triangles, expression, features.floor,
                                     sizing.max_edge_mm, shape.skin_thickness_mm)
    mesh = _finished(raw, shape, inclusions, names)
    if path is not None:
        _save(path, mesh)
    return mesh


def _finished(raw: body_gmsh.GmshMesh, shape: BodyShape, inclusions: tuple, names: tuple) -> BodyMesh:
    """Oriented, compactly numbered tetrahedra with regions, the outer boundary and the quality check."""
    nodes, tets = body_quality.compacted(raw.nodes, body_quality.oriented(raw.nodes, raw.tets))
    region = raw.region
    if shape.kind == "surface":
        centroids = nodes[tets].mean(axis=1)
        region = body_geometry.centroid_regions(centroids, inclusions, shape.skin_thickness_mm,
                                                shape.surface_nodes, shape.surface_triangles)
    angles = body_quality.min_dihedral_deg(nodes, tets)
    worst = int(np.argmin(angles))
    if not angles[worst] >= MIN_DIHEDRAL_DEG:
        raise MeshError(_quality_problem(float(angles[worst]), nodes[tets[worst]].mean(axis=0),
                                         names[region[worst]], inclusions))
    boundary = body_quality.boundary_faces(tets)
    if shape.kind == "dome":
        scale = max(shape.radius_mm, shape.height_mm)
        base = np.all(np.abs(nodes[boundary][:, :, 2]) <= _BASE_TOLERANCE * scale, axis=1)
    else:
        base = np.zeros(len(boundary), bool)
    return BodyMesh(nodes=nodes, tetrahedra=tets, region=region.astype(np.int64), region_names=names,
                    boundary_triangles=boundary, boundary_base=base, min_dihedral_deg=float(angles[worst]))


def _quality_problem(angle: float, where: np.ndarray, region: str, inclusions: tuple) -> str:
    """What to say when a tetrahedron is too flat: where it is, what is near, what to change."""
    near = ""
    if inclusions:
        gaps = [abs(float(np.linalg.norm(where - inc.center_mm)) - inc.radius_mm) if isinstance(inc, Sphere) else
                abs(float(body_field.polyline_distance(where[None], inc.points_mm)[0]) - inc.radius_mm)
                for inc in inclusions]
        k = int(np.argmin(gaps))
        near = f", {gaps[k]:.2g} mm from the surface of {inclusions[k].name!r}"
    x, y, z = np.round(where, 2)
    return (f"the body's mesh has a tetrahedron with a dihedral angle of {angle:.3g}° (in {region!r} at x, y, z = "
            f"{x:g}, {y:g}, {z:g} mm{near}), below the bound of {MIN_DIHEDRAL_DEG:g}° after gmsh's optimisation. An "
            f"inclusion that nearly touches the body's surface, its base, the skin's inner surface or another "
            f"inclusion leaves a gap too thin to mesh: move it clear by a few min_edge_mm or let it cross clearly; "
            f"otherwise make min_edge_mm smaller than the smallest inclusion's radius, or lower grading")


def _features(shape: BodyShape, inclusions: tuple, sizing: BodySizing) -> Features:
    """The size field's features: spheres and refine patches as balls, every tube segment as a capsule."""
    centers = [inc.center_mm for inc in inclusions if isinstance(inc, Sphere)] + [c for c, _ in sizing.refine]
    radii = [inc.radius_mm for inc in inclusions if isinstance(inc, Sphere)] + [r for _, r in sizing.refine]
    tubes = [inc for inc in inclusions if isinstance(inc, Tube)]
    seg_a = [t.points_mm[:-1] for t in tubes]
    seg_b = [t.points_mm[1:] for t in tubes]
    seg_r = [np.full(len(t.points_mm) - 1, t.radius_mm) for t in tubes]
    small = [min(sizing.min_edge_mm, INCLUSION_EDGE_PER_RADIUS * inc.radius_mm)
             for inc in inclusions if isinstance(inc, Sphere)]
    ball_edge = np.array(small + [sizing.min_edge_mm] * len(sizing.refine), float)
    seg_edge = (np.concatenate([np.full(len(t.points_mm) - 1, min(sizing.min_edge_mm,
                                                                  INCLUSION_EDGE_PER_RADIUS * t.radius_mm))
                                for t in tubes]) if tubes else np.zeros(0))
    features = Features(ball_center=np.array(centers, float).reshape(-1, 3), ball_radius=np.array(radii, float),
                        seg_a=np.concatenate(seg_a) if tubes else np.zeros((0, 3)),
                        seg_b=np.concatenate(seg_b) if tubes else np.zeros((0, 3)),
                        seg_radius=np.concatenate(seg_r) if tubes else np.zeros(0),
                        min_edge=sizing.min_edge_mm, max_edge=sizing.max_edge_mm, grading=sizing.grading,
                        ball_edge=ball_edge, seg_edge=seg_edge)
    t = shape.skin_thickness_mm
    if not t:
        return features
    skin_edge = float(np.clip(SKIN_EDGE_PER_THICKNESS * t, sizing.min_edge_mm, sizing.max_edge_mm))
    if shape.kind == "dome":
        distance, expression = body_field.spheroid_depth(shape.radius_mm - t, shape.height_mm - t)
    else:
        # the depth matters out to where the skin's term reaches max_edge, and a cell's reach beyond that
        far = t + (sizing.max_edge_mm - skin_edge) / sizing.grading + sizing.max_edge_mm if sizing.grading else t
        depth = []  # built on first use: meshing hands gmsh the expression and never calls it

        def distance(p: np.ndarray) -> np.ndarray:
            if not depth:
                depth.append(body_geometry.surface_depth(shape.surface_nodes, shape.surface_triangles, far))
            return depth[0](p) - t

        expression = f"{body_gmsh.SURFACE_DISTANCE}-({t!r})"
    return replace(features, skin_edge=skin_edge, skin_distance=distance, skin_expression=expression, skin_thickness=t)


def _positive(value, what: str) -> float:
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{what} must be a positive number of mm; got {value}")
    return value


def _point(value, what: str, shape=(3,)) -> np.ndarray:
    array = np.array(value, dtype=np.float64)
    if array.shape[-1:] != shape[-1:] or array.ndim != len(shape) or not np.all(np.isfinite(array)):
        raise ValueError(f"{what} must be finite coordinates of shape {shape}; got shape {array.shape}")
    return array


def _checked(shape: BodyShape, inclusions: tuple, sizing: BodySizing) -> tuple[BodyShape, tuple, BodySizing]:
    """Copies of the inputs with float64/int64 arrays; ValueError for what no caller should pass."""
    skin = None if shape.skin_thickness_mm is None else _positive(shape.skin_thickness_mm, "skin_thickness_mm")
    if shape.kind == "dome":
        a, h = _positive(shape.radius_mm, "the dome's radius_mm"), _positive(shape.height_mm, "the dome's height_mm")
        if skin is not None and skin >= min(a, h):
            raise ValueError(f"the skin ({skin} mm) must be thinner than the dome's radius and height")
        shape = replace(shape, radius_mm=a, height_mm=h, skin_thickness_mm=skin,
                        surface_nodes=None, surface_triangles=None)
    elif shape.kind == "surface":
        if shape.surface_nodes is None or shape.surface_triangles is None:
            raise ValueError("a surface body needs surface_nodes and surface_triangles")
        nodes = _point(shape.surface_nodes, "surface_nodes", (0, 3))
        triangles = np.array(shape.surface_triangles, dtype=np.int64)
        if triangles.ndim != 2 or triangles.shape[1] != 3 or triangles.min() < 0 or triangles.max() >= len(nodes):
            raise ValueError("surface_triangles must be (T, 3) indices into surface_nodes")
        shape = replace(shape, surface_nodes=nodes, surface_triangles=triangles, skin_thickness_mm=skin)
    else:
        raise ValueError(f"a body's kind is 'dome' or 'surface'; got {shape.kind!r}")
    checked = []
    for inc in inclusions:
        if isinstance(inc, Sphere):
            checked.append(Sphere(str(inc.name), _point(inc.center_mm, f"{inc.name}'s center_mm"),
                                  _positive(inc.radius_mm, f"{inc.name}'s radius_mm")))
        elif isinstance(inc, Tube):
            points = _point(inc.points_mm, f"{inc.name}'s points_mm", (0, 3))
            if len(points):  # a repeated point is no segment
                points = points[np.r_[True, np.linalg.norm(np.diff(points, axis=0), axis=1) > 0]]
            if len(points) < 2:
                raise ValueError(f"the tube {inc.name} needs at least two distinct points")
            checked.append(Tube(str(inc.name), points, _positive(inc.radius_mm, f"{inc.name}'s radius_mm")))
        else:
            raise ValueError(f"an inclusion is a Sphere or a Tube; got {type(inc).__name__}")
    names = ["body", "skin"] + [inc.name for inc in checked]
    if len(set(names)) != len(names):
        raise ValueError(f"inclusion names must differ from each other and from 'body' and 'skin'; got "
                         f"{[inc.name for inc in checked]}")
    lo, hi = _positive(sizing.min_edge_mm, "min_edge_mm"), _positive(sizing.max_edge_mm, "max_edge_mm")
    grading = float(sizing.grading)
    if hi < lo or not (np.isfinite(grading) and grading >= 0):
        raise ValueError(f"sizing needs 0 < min_edge_mm <= max_edge_mm and grading >= 0; got {lo}, {hi}, {grading}")
    refine = tuple((_point(c, "a refine patch's center"), float(r)) for c, r in sizing.refine)
    if any(not (np.isfinite(r) and r >= 0) for _, r in refine):
        raise ValueError("a refine patch's radius must be a number of mm >= 0")
    return shape, tuple(checked), BodySizing(lo, hi, grading, refine)


def _cache_key(shape: BodyShape, inclusions: tuple, sizing: BodySizing) -> str:
    """sha256 of every input (arrays by dtype, shape and bytes), gmsh's version, MESHER_VERSION and the constants
    and gmsh options that shape the mesh."""
    import gmsh

    digest = hashlib.sha256()

    def put(*parts) -> None:
        for part in parts:
            if isinstance(part, np.ndarray):
                digest.update(f"{part.dtype.str}{part.shape}".encode())
                digest.update(np.ascontiguousarray(part).tobytes())
            else:
                digest.update(repr(part).encode())
            digest.update(b"\x00")

    put("scissor body mesh", MESHER_VERSION, gmsh.__version__, MIN_DIHEDRAL_DEG, SKIN_EDGE_PER_THICKNESS,
        body_gmsh.TUBE_BEND_RADII, body_gmsh.SURFACE_FEATURE_ANGLE_DEG, sorted(body_gmsh._OPTIONS.items()))
    put(shape.kind, shape.radius_mm, shape.height_mm, shape.skin_thickness_mm)
    if shape.kind == "surface":
        put(shape.surface_nodes, shape.surface_triangles)
    for inc in inclusions:
        put(type(inc).__name__, inc.name, inc.center_mm if isinstance(inc, Sphere) else inc.points_mm, inc.radius_mm)
    put(sizing.min_edge_mm, sizing.max_edge_mm, sizing.grading, len(sizing.refine))
    for center, radius in sizing.refine:
        put(center, radius)
    return digest.hexdigest()[:40]


def _save(path: Path, mesh: BodyMesh) -> None:
    """Write the mesh atomically: a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, nodes=mesh.nodes, tetrahedra=mesh.tetrahedra, region=mesh.region,
                     region_names=np.array(mesh.region_names, dtype=str), boundary_triangles=mesh.boundary_triangles,
                     boundary_base=mesh.boundary_base, min_dihedral_deg=np.float64(mesh.min_dihedral_deg))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _load(path: Path, names: tuple) -> BodyMesh | None:
    """The cached mesh, or None when there is none or it is unreadable (it is then made again)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            mesh = BodyMesh(nodes=data["nodes"], tetrahedra=data["tetrahedra"], region=data["region"],
                            region_names=tuple(str(n) for n in data["region_names"]),
                            boundary_triangles=data["boundary_triangles"], boundary_base=data["boundary_base"],
                            min_dihedral_deg=float(data["min_dihedral_deg"]))
    except (OSError, KeyError, ValueError, EOFError):
        return None
    return mesh if mesh.region_names == names else None
