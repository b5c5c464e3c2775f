"""A body's outer surface given as a file: a closed triangulation from a scan or a CAD export.

The file is read when the config is validated, so every problem with it is a
config problem (exit 2) and its message says what to fix. What comes back is
a surface the 3-D mesher can fill with tetrahedra: closed (every edge has two
faces), manifold (no edge with three or more faces, one consistent
orientation, no pinched corner), in one piece, free of self-intersections and
of zero-area faces, oriented outward, with the vertices an STL file repeats
merged into one.

meshio reads the formats; it is imported only when a file is read. Its
readers are called one format at a time because `meshio.read` prints and
exits the process on a file it cannot read.
"""

from __future__ import annotations

import contextlib
import io
import warnings
from pathlib import Path

import numpy as np

#: the file types meshio reads that hold a triangulated surface, by suffix
SURFACE_SUFFIXES = (".stl", ".obj", ".ply", ".vtk", ".vtu")
#: more triangles than this is not a breast surface to mesh but a point cloud's raw scan; decimate it first
MAX_TRIANGLES = 1_000_000
#: coordinates are millimetres: a body wider than this is in other units, or not a body
MAX_EXTENT_MM = 1000.0
#: ... and one narrower than this is in metres (or not a body)
MIN_EXTENT_MM = 1.0
#: vertices closer than this fraction of the bounding box's diagonal are one vertex
MERGE_TOLERANCE = 1e-6
#: a face whose height is below this fraction of its longest edge has no area
DEGENERATE_HEIGHT = 1e-6

_READERS = {".stl": "stl", ".obj": "obj", ".ply": "ply", ".vtk": "vtk", ".vtu": "vtu"}


class SurfaceFileError(ValueError):
    """The surface file cannot be read or is not a closed surface of a body; the message says why."""


def read_surface(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 mm and triangles (T, 3) int64 of a checked, outward surface, or SurfaceFileError."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SURFACE_SUFFIXES:
        raise SurfaceFileError(f"a surface file is one of {', '.join(SURFACE_SUFFIXES)}; got '{path.suffix}' "
                               f"({path})")
    if not path.is_file():
        raise SurfaceFileError(f"the surface file {path} does not exist (or is not a file)")
    points, triangles, others = _read_cells(path, _READERS[suffix])
    if len(triangles) == 0:
        held = f"only {', '.join(others)} cells" if others else "no cells"
        raise SurfaceFileError(f"the surface file {path} holds no triangles ({held}); export the surface as a "
                               f"triangle mesh")
    try:
        return checked_surface(points, triangles)
    except SurfaceFileError as exc:
        raise SurfaceFileError(f"the surface in {path}: {exc}") from None


def _read_cells(path: Path, reader: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Points, the triangles of every triangle block, and the names of the other cell types, read by meshio."""
    import meshio

    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()), \
                warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = getattr(meshio, reader).read(str(path))
    except Exception as exc:  # meshio raises whatever its parser meets (ReadError, UnicodeError, ValueError, ...)
        kind = "text" if reader == "obj" else "text or binary"
        raise SurfaceFileError(f"cannot read {path} as a {reader.upper()} file ({kind}): it is damaged or not in "
                               f"that format ({type(exc).__name__})") from None
    triangles = [np.asarray(block.data) for block in mesh.cells if block.type == "triangle"]
    others = sorted({block.type for block in mesh.cells if block.type != "triangle" and len(block.data)})
    faces = [kind for kind in others if kind.startswith(("quad", "polygon"))]
    if triangles and faces:
        raise SurfaceFileError(f"{path} holds {', '.join(faces)} faces as well as triangles; export the surface "
                               f"with triangles only")
    tri = np.concatenate(triangles) if triangles else np.zeros((0, 3), np.int64)
    return np.asarray(mesh.points), tri, others


def checked_surface(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The checks of `read_surface` on arrays: merged, checked, oriented outward; SurfaceFileError otherwise."""
    points = np.asarray(points)
    triangles = np.asarray(triangles)
    if points.ndim != 2 or points.shape[1] != 3 or points.dtype.kind not in "fiu":
        raise SurfaceFileError(f"vertices must be 3-D points (x, y, z in mm); got an array of shape {points.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or triangles.dtype.kind not in "iu" or len(triangles) == 0:
        raise SurfaceFileError(f"faces must be triangles (three vertex indices each); got an array of shape "
                               f"{triangles.shape}")
    points = points.astype(np.float64)
    triangles = triangles.astype(np.int64)
    if not np.all(np.isfinite(points)):
        raise SurfaceFileError(f"{int(np.sum(~np.all(np.isfinite(points), axis=1)))} vertices have coordinates "
                               f"that are not finite numbers (NaN or infinity)")
    if len(triangles) > MAX_TRIANGLES:
        raise SurfaceFileError(f"{len(triangles)} triangles is more than the {MAX_TRIANGLES} a body surface may "
                               f"have; decimate the scan first")
    if triangles.min() < 0 or triangles.max() >= len(points):
        raise SurfaceFileError(f"faces name vertices {triangles.min()}..{triangles.max()} but there are "
                               f"{len(points)} vertices")
    used = points[np.unique(triangles)]
    extent = float(np.max(np.ptp(used, axis=0)))
    if extent > MAX_EXTENT_MM:
        raise SurfaceFileError(f"the surface spans {extent:.6g} mm, more than {MAX_EXTENT_MM:g} mm: coordinates are "
                               f"read as millimetres (is the file in micrometres, or not a body?)")
    if extent < MIN_EXTENT_MM:
        raise SurfaceFileError(f"the surface spans only {extent:.3g} mm: coordinates are read as millimetres (is "
                               f"the file in metres?)")
    diagonal = float(np.linalg.norm(np.ptp(used, axis=0)))
    points, triangles = merge_vertices(points, triangles, MERGE_TOLERANCE * diagonal)
    _check_areas(points, triangles)
    _check_edges(triangles)
    _check_self_intersections(points, triangles)
    _check_one_piece(points, triangles)
    p = points[triangles]
    volume = np.sum(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2]))) / 6.0
    if volume < 0:
        triangles = triangles[:, [0, 2, 1]]
    return points, triangles


def merge_vertices(points: np.ndarray, triangles: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices within tol of each other (transitively) made one; unused vertices dropped, order of first use kept."""
    used, inverse = np.unique(triangles, return_inverse=True)
    triangles = inverse.reshape(-1, 3)
    points = points[used]
    # bit-identical repeats (what STL stores) first: cheap and exact
    points, inverse = np.unique(points, axis=0, return_inverse=True)
    triangles = inverse.reshape(-1)[triangles]
    i, j = overlapping_boxes(points - tol / 2, points + tol / 2, points - tol / 2, points + tol / 2)
    close = (i < j) & (np.linalg.norm(points[i] - points[j], axis=1) <= tol)
    labels = connected_labels(len(points), i[close], j[close])
    keep, inverse = np.unique(labels, return_inverse=True)
    return points[keep], inverse[triangles]


def _check_areas(points: np.ndarray, triangles: np.ndarray) -> None:
    p = points[triangles]
    twice_area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    longest = np.max(np.linalg.norm(p - p[:, [1, 2, 0]], axis=2), axis=1)
    # a face whose height is a millionth of its longest edge is a line: float32 rounding (STL) leaves more
    bad = ~(twice_area > DEGENERATE_HEIGHT * longest**2)
    if np.any(bad):
        raise SurfaceFileError(f"{int(bad.sum())} of {len(triangles)} triangles are degenerate: zero area "
                               f"(repeated or collinear corners); repair the surface (remove degenerate faces)")


def _edge_keys(triangles: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Undirected (3T,) and directed (3T,) integer keys of the triangles' edges, in the order (01, 12, 20)."""
    a = triangles.reshape(-1)
    b = triangles[:, [1, 2, 0]].reshape(-1)
    return np.minimum(a, b) * n + np.maximum(a, b), a * n + b


def _check_edges(triangles: np.ndarray) -> None:
    n = int(triangles.max()) + 1
    undirected, directed = _edge_keys(triangles, n)
    _, count = np.unique(undirected, return_counts=True)
    problems = []
    if np.any(count > 2):
        problems.append(f"the surface is non-manifold: {int(np.sum(count > 2))} edges have more than two faces; "
                        f"each edge of a body's surface must join exactly two")
    if np.any(count == 1):
        problems.append(f"the surface is open: {int(np.sum(count == 1))} boundary edges have one face only (a "
                        f"hole); a body's surface must be closed (watertight)")
    if problems:
        raise SurfaceFileError("; ".join(problems))
    _, count = np.unique(directed, return_counts=True)
    if np.any(count > 1):
        raise SurfaceFileError(f"the surface is non-manifold: its faces are not consistently oriented "
                               f"({int(np.sum(count > 1))} edges run the same way in both their faces); "
                               f"re-orient the faces (or the surface is inside out in parts)")


def _check_one_piece(points: np.ndarray, triangles: np.ndarray) -> None:
    n = len(points)
    labels = connected_labels(n, triangles[:, [0, 1, 2]].reshape(-1), triangles[:, [1, 2, 0]].reshape(-1))
    pieces = len(np.unique(labels))
    if pieces > 1:
        raise SurfaceFileError(f"the surface is in {pieces} separate pieces; a body is one closed surface")
    edges = len(triangles) * 3 // 2
    euler = n - edges + len(triangles)
    if euler > 2 or euler % 2:
        raise SurfaceFileError(f"the surface is non-manifold at a vertex (Euler characteristic {euler}: two "
                               f"sheets meet at a single corner); separate them")


def _check_self_intersections(points: np.ndarray, triangles: np.ndarray) -> None:
    p = points[triangles]
    lo, hi = p.min(axis=1), p.max(axis=1)
    i, j = overlapping_boxes(lo, hi, lo, hi)
    keep = i < j
    i, j = i[keep], j[keep]
    # triangles that share a corner or an edge are neighbours on the surface, not a crossing
    shared = np.any(triangles[i][:, :, None] == triangles[j][:, None, :], axis=(1, 2))
    i, j = i[~shared], j[~shared]
    hit = triangles_intersect(p[i], p[j])
    if np.any(hit):
        k = int(np.argmax(hit))
        where = np.round(p[i[k]].mean(axis=0), 3)
        raise SurfaceFileError(f"the surface is self-intersecting: {int(hit.sum())} pairs of non-adjacent "
                               f"triangles cross each other (one near x, y, z = {where[0]:g}, {where[1]:g}, "
                               f"{where[2]:g} mm); repair the surface")


def overlapping_boxes(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray,
                      cell: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) of the boxes of set a and set b (D-dimensional, lo/hi (n, D)) that overlap, edges included.

    A uniform grid sorts the boxes into cells (the broad phase): boxes are
    paired only when they share a cell, then tested exactly. The cell is the
    larger of the median box size and what keeps the cell entries within a
    few times the number of boxes, so a few long boxes do not blow up memory.
    """
    if len(lo_a) == 0 or len(lo_b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo_all = np.minimum(lo_a.min(axis=0), lo_b.min(axis=0))
    span = np.maximum(hi_a.max(axis=0), hi_b.max(axis=0)) - lo_all
    if cell is None:
        sizes = np.concatenate([(hi_a - lo_a).max(axis=1), (hi_b - lo_b).max(axis=1)])
        cell = float(np.median(sizes))
    cell = max(cell, float(span.max()) / 2**20, 1e-300)
    budget = 16 * (len(lo_a) + len(lo_b)) + 10**6
    while True:
        ca, cb = _cells(lo_a, hi_a, lo_all, cell), _cells(lo_b, hi_b, lo_all, cell)
        if np.prod(ca[1], axis=1).sum() + np.prod(cb[1], axis=1).sum() <= budget:
            break
        cell *= 2.0
    dims = np.floor(span / cell).astype(np.int64) + 1
    ka, ia = _cell_entries(*ca, dims)
    kb, ib = _cell_entries(*cb, dims)
    order = np.argsort(kb, kind="stable")
    kb, ib = kb[order], ib[order]
    start, stop = np.searchsorted(kb, ka, "left"), np.searchsorted(kb, ka, "right")
    count = stop - start
    pa = np.repeat(ia, count)
    offsets = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    pb = ib[np.repeat(start, count) + offsets]
    overlap = np.all((lo_a[pa] <= hi_b[pb]) & (lo_b[pb] <= hi_a[pa]), axis=1)
    key, pa, pb = np.repeat(ka, count)[overlap], pa[overlap], pb[overlap]
    # two boxes share several cells; the pair is kept in the one that holds the corner of their overlap
    corner = np.floor((np.maximum(lo_a[pa], lo_b[pb]) - lo_all) / cell).astype(np.int64)
    own = np.zeros(len(pa), np.int64)
    for axis in range(len(dims)):
        own = own * dims[axis] + corner[:, axis]
    keep = own == key
    return pa[keep], pb[keep]


def _cells(lo: np.ndarray, hi: np.ndarray, origin: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """First cell (n, D) and number of cells per axis (n, D) each box covers."""
    first = np.floor((lo - origin) / cell).astype(np.int64)
    last = np.floor((hi - origin) / cell).astype(np.int64)
    return first, last - first + 1


def _cell_entries(first: np.ndarray, count: np.ndarray, dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cell key, box index) for every cell of every box."""
    total = np.prod(count, axis=1)
    box = np.repeat(np.arange(len(first)), total)
    local = np.arange(total.sum()) - np.repeat(np.cumsum(total) - total, total)
    key = np.zeros(len(box), np.int64)
    stride = np.ones(len(box), np.int64)
    for axis in range(first.shape[1]):  # D axes, each vectorised over all entries
        c = count[box, axis]
        key = key * dims[axis] + first[box, axis] + (local // stride) % c
        stride = stride * c
    return key, box


def connected_labels(n: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Component label (n,) of every vertex of the graph with edges (i, j): the smallest vertex of its component."""
    labels = np.arange(n)
    while True:
        li, lj = labels[i], labels[j]
        low = np.minimum(li, lj)
        hooked = labels.copy()
        np.minimum.at(hooked, li, low)  # hook each edge's larger root onto the smaller
        np.minimum.at(hooked, lj, low)
        while True:  # pointer jumping: every vertex points at its root
            jumped = hooked[hooked]
            if np.array_equal(jumped, hooked):
                break
            hooked = jumped
        if np.array_equal(hooked, labels):
            return labels
        labels = hooked


def triangles_intersect(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Whether triangle p[k] (K, 3, 3) and q[k] touch or cross (Möller's interval test; coplanar pairs in 2-D)."""
    scale = np.maximum(np.ptp(p.reshape(-1, 9), axis=1), np.ptp(q.reshape(-1, 9), axis=1))[:, None]
    n_q = np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0])
    n_p = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    dp = _plane_distances(p, q[:, 0], n_q, scale)  # p's corners against q's plane
    dq = _plane_distances(q, p[:, 0], n_p, scale)
    apart = np.all(dp > 0, axis=1) | np.all(dp < 0, axis=1) | np.all(dq > 0, axis=1) | np.all(dq < 0, axis=1)
    coplanar = np.all(dp == 0, axis=1)
    out = np.zeros(len(p), bool)
    cross = ~apart & ~coplanar
    if np.any(cross):
        line = np.cross(n_p[cross], n_q[cross])
        axis = np.argmax(np.abs(line), axis=1)
        rows = np.arange(int(cross.sum()))
        lo_p, hi_p = _interval(p[cross][rows, :, axis], dp[cross])
        lo_q, hi_q = _interval(q[cross][rows, :, axis], dq[cross])
        out[cross] = (lo_p <= hi_q) & (lo_q <= hi_p)
    both = ~apart & coplanar
    if np.any(both):
        out[both] = _coplanar_overlap(p[both], q[both], n_q[both])
    return out


def _plane_distances(t: np.ndarray, origin: np.ndarray, normal: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Signed distances (K, 3) of t's corners from the plane; those within round-off of it are exactly 0."""
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    d = np.einsum("kij,kj->ki", t - origin[:, None], normal) / np.where(length > 0, length, 1.0)
    return np.where(np.abs(d) <= 1e-12 * scale, 0.0, d)


def _interval(coord: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where a triangle (corner coordinates along the line's axis (K, 3), plane distances d) meets the other plane.

    The ends are where edges cross the plane (corners on opposite sides) and
    the corners that lie on it.
    """
    lo, hi = np.full(len(d), np.inf), np.full(len(d), -np.inf)
    for a in range(3):  # three corners and the three edges from them, each vectorised over all pairs
        b = (a + 1) % 3
        da, db = d[:, a], d[:, b]
        crosses = da * db < 0
        at = coord[:, a] + (coord[:, b] - coord[:, a]) * da / np.where(crosses, da - db, 1.0)
        for value, valid in ((at, crosses), (coord[:, a], da == 0)):
            lo = np.where(valid, np.minimum(lo, value), lo)
            hi = np.where(valid, np.maximum(hi, value), hi)
    return lo, hi


def _coplanar_overlap(p: np.ndarray, q: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Whether coplanar triangles p, q (K, 3, 3) overlap, in the plane that drops the normal's largest axis."""
    drop = np.argmax(np.abs(normal), axis=1)
    keep = np.broadcast_to(np.array([[1, 2], [0, 2], [0, 1]])[drop][:, None, :], (len(p), 3, 2))
    p2, q2 = np.take_along_axis(p, keep, axis=2), np.take_along_axis(q, keep, axis=2)
    hit = np.zeros(len(p), bool)
    for a in range(3):  # nine edge pairs, each vectorised over all triangle pairs
        for b in range(3):
            hit |= _segments_cross(p2[:, a], p2[:, (a + 1) % 3], q2[:, b], q2[:, (b + 1) % 3])
    return hit | _inside_2d(p2[:, 0], q2) | _inside_2d(q2[:, 0], p2)


def _orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


def _segments_cross(a, b, c, d) -> np.ndarray:
    o1, o2, o3, o4 = _orient(a, b, c), _orient(a, b, d), _orient(c, d, a), _orient(c, d, b)
    return (o1 * o2 <= 0) & (o3 * o4 <= 0) & ~((o1 == 0) & (o2 == 0))


def _inside_2d(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    s = [_orient(t[:, k], t[:, (k + 1) % 3], x) for k in range(3)]
    return (np.minimum.reduce(s) >= 0) | (np.maximum.reduce(s) <= 0)
