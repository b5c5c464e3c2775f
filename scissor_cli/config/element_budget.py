"""The element budget: a mesh's triangle count estimated from the config, before meshing.

The mesher (scissor_cli/mesh/mesh.py, docs/model.md §2) aims at the edge
length h(p) = clip(min_edge + grading·d(p), min_edge, max_edge) — d the
distance to the nearest target, cup contact, cup grip end or obstacle
outline, the edges scaled by `tissue.mesh.scale`; h = min_edge everywhere
when `graded` is false. An equilateral triangle of edge h has the area
√3/4·h², so the mesh has about

    N ≈ f(min_angle) · (A_FACTOR · ∫ dA / (√3/4 · h²) + B_FACTOR · ∮ ds / h)

triangles: the area integral over the layer, plus the segments' share
(the outline and both sides of every obstacle outline, where the quality
refinement packs smaller triangles); f = 1 + 0.2 per degree of
`min_angle_deg` above 30 (Triangle's refinement for angles of 31-34° adds
up to 80 % more triangles). The integral is taken on a quadtree of
cells refined until each cell is no larger than the local h, so the fine
zones around small features are resolved without a fine grid everywhere.
A_FACTOR and B_FACTOR are fitted to real meshes; on 33 of them (rectangles,
an ellipse, a polygon, 0 to 32 obstacles, 50 targets, grading 0.001-100,
min_angle 20-33°, uniform meshes, 1 000 to 200 000 triangles)
tests/test_config.py holds real / estimate within a factor 1.5. Only a sliver narrower than the edge length
is off by more: a 2 mm × 300 mm strip at 0.43 (the estimate is high) and 1.40.

A config whose mesh is estimated at more than ELEMENT_BUDGET triangles is
refused before meshing (docs/contract.md, "Config"). So is
`solver.accuracy_mm` when its calibration would mesh beyond the budget: it
meshes the scene at SELECTION_FINEST_LEVEL × the size field (16 times the
elements). The solver study (`study`) skips, with a note, every level
estimated above twice its `max_elements` (which is at most half the budget)
before meshing it, and every level whose mesh has more than `max_elements`.
"""

from __future__ import annotations

import numpy as np

from scissor_cli import geometry
from scissor_cli.config.checks import Problem, obstacle_outline, tissue_outline
from scissor_cli.config.mesh_file import read_mesh_arrays
from scissor_cli.config.sections import MAX_SCALE, MIN_EDGE_MM, Config

#: the most triangles a mesh of any scissor run may have (estimated before meshing). Near it building the
#: tissue and one Newton solve take seconds each and a gigabyte of memory (benchmarks/bench_forward.py):
#: a run of trials there takes hours per target, and every worker process holds its own copy.
ELEMENT_BUDGET = 250_000
#: the most tetrahedra of the layer check's slab (docs/model.md §13), estimated before meshing as
#: 3 × (estimated triangles) × (prism layers of `geometry.graded_levels`): the largest slab whose forward
#: cases still solve in the time of a run (benchmarks/bench_slab.py).
TETRAHEDRA_BUDGET = 300_000
#: the finest and coarsest mesh levels the accuracy selection meshes (experiments/selection.py CANDIDATE_LEVELS)
SELECTION_FINEST_LEVEL = 0.25
SELECTION_COARSEST_LEVEL = 4.0
#: fitted: real count / area integral, and per unit of the boundary integral
A_FACTOR = 1.55
B_FACTOR = 1.55
#: the estimate stops refining once it is this many budgets (the answer is then "at least")
_STOP = 2.0
_EQUILATERAL = np.sqrt(3.0) / 4.0


def _grip_ends(cfg: Config, outline: np.ndarray) -> np.ndarray:
    """Where the cups' grips end on the outline (points at radius_mm from each contact)."""
    a, b = geometry.edges(outline)
    d = b - a
    out = [np.zeros((0, 2))]
    for cup in cfg.cups:
        f = a - np.asarray(cup.contact_mm)
        qa, qb, qc = np.sum(d * d, axis=1), 2 * np.sum(f * d, axis=1), np.sum(f * f, axis=1) - cup.radius_mm**2
        disc = qb * qb - 4 * qa * qc
        ok = (disc >= 0) & (qa > 0)
        for sign in (-1.0, 1.0):
            t = (-qb[ok] + sign * np.sqrt(disc[ok])) / (2 * qa[ok])
            inside = (t >= 0) & (t <= 1)
            out.append(a[ok][inside] + t[inside, None] * d[ok][inside])
    return np.concatenate(out)


def _perimeter(poly: np.ndarray) -> float:
    return float(np.linalg.norm(np.roll(poly, -1, axis=0) - poly, axis=1).sum())


def _sample_closed(poly: np.ndarray, spacing: float) -> np.ndarray:
    """Points along a closed polygon at most `spacing` apart (its vertices included)."""
    a, b = geometry.edges(poly)
    n = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / spacing)).astype(int)
    t = np.concatenate([np.arange(k) / k for k in n])
    start = np.repeat(a, n, axis=0)
    return start + t[:, None] * np.repeat(b - a, n, axis=0)


class _SizeField:
    """h(p) of the mesher from the config's features; distances through a k-d tree of feature samples."""

    def __init__(self, cfg: Config, outline: np.ndarray, obstacles: list[np.ndarray], lo: float, hi: float):
        self.lo, self.hi, self.grading = lo, hi, cfg.tissue.mesh.grading
        points = [np.asarray([t.position_mm for t in cfg.targets], float).reshape(-1, 2),
                  np.asarray([c.contact_mm for c in cfg.cups], float).reshape(-1, 2),
                  _grip_ends(cfg, outline)]
        points += [_sample_closed(o, lo) for o in obstacles]  # within lo/2 of the outline
        from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy.spatial costs every CLI start half a second

        self.tree = cKDTree(np.concatenate(points))

    def __call__(self, p: np.ndarray) -> np.ndarray:
        d, _ = self.tree.query(p)
        return np.clip(self.lo + self.grading * d, self.lo, self.hi)


def _area_integral(outline: np.ndarray, h: _SizeField, stop: float) -> float:
    """∫ dA / (√3/4 h²) over the outline, on cells refined until no cell is larger than h."""
    lo_xy, hi_xy = outline.min(axis=0), outline.max(axis=0)
    c = float(max(hi_xy - lo_xy)) / 16
    nx, ny = (np.maximum(1, np.ceil((hi_xy - lo_xy) / c))).astype(int)
    gx, gy = np.meshgrid(lo_xy[0] + (np.arange(nx) + 0.5) * c, lo_xy[1] + (np.arange(ny) + 0.5) * c)
    centers = np.column_stack([gx.ravel(), gy.ravel()])
    total = 0.0
    quarter = np.array([[-1, -1], [1, -1], [-1, 1], [1, 1]], float) / 4
    while len(centers):
        hc = h(centers)
        inside = _chunked(geometry.points_in_polygon, centers, outline)
        coarse = c > hc
        weight = c * c / (_EQUILATERAL * hc * hc)
        total += float(weight[inside & ~coarse].sum())
        pending = float(weight[inside & coarse].sum())
        if total + pending > stop:
            return total + pending
        # a coarse cell outside the outline by more than its half-diagonal holds no tissue
        keep = coarse.copy()
        outside = np.flatnonzero(coarse & ~inside)
        if len(outside):
            keep[outside[_chunked(geometry.distance_to_boundary, centers[outside], outline) >= 0.71 * c]] = False
        centers = (centers[keep][:, None, :] + c * quarter[None]).reshape(-1, 2)
        c /= 2
    return total


def _chunked(fn, points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """fn(points, poly) in chunks, so its (points, edges) temporaries stay near 16 MB."""
    step = max(1, 2_000_000 // len(poly))
    return np.concatenate([fn(points[i : i + step], poly) for i in range(0, len(points), step)])


def estimate_elements(cfg: Config, scale: float | None = None, graded: bool | None = None) -> int:
    """About how many triangles the mesher makes for cfg (its mesh section, or `scale`/`graded` instead).

    Past _STOP budgets the refinement stops: the answer is then a lower bound, already over budget.
    """
    m = cfg.tissue.mesh
    if m.file is not None and scale is None and graded is None:  # a pinned mesh: count it (checks read it already)
        return len(read_mesh_arrays(m.file)[1])
    s = m.scale if scale is None else scale
    graded = m.graded if graded is None else graded
    lo, hi = m.min_edge_mm * s, max(m.max_edge_mm, m.min_edge_mm) * s
    outline = tissue_outline(cfg.tissue)
    obstacles = [obstacle_outline(o) for o in cfg.obstacles if (o.circle is None) != (o.polygon_mm is None)]
    area = abs(geometry.signed_area(outline))
    boundary_len = _perimeter(outline) + 2 * sum(_perimeter(o) for o in obstacles)
    angle = 1.0 + 0.2 * max(0.0, m.min_angle_deg - 30.0)
    stop = _STOP * ELEMENT_BUDGET / angle
    # lower bounds first: the coarsest possible mesh, the obstacle outlines at the finest edge
    floor = max(A_FACTOR * area / (_EQUILATERAL * hi * hi), B_FACTOR * boundary_len / hi,
                2 * sum(_perimeter(o) for o in obstacles) / lo if graded else 0.0)
    if not graded:
        return int(round(angle * (A_FACTOR * area / (_EQUILATERAL * lo * lo) + B_FACTOR * boundary_len / lo)))
    if floor > stop:
        return int(round(angle * floor))
    h = _SizeField(cfg, outline, obstacles, lo, hi)
    area_part = _area_integral(outline, h, stop / A_FACTOR)
    spacing = max(lo, boundary_len / 200_000)  # a long, jagged outline is sampled at most 200 000 times
    ring = np.concatenate([_sample_closed(outline, spacing)] + [_sample_closed(o, spacing) for o in obstacles])
    step = np.concatenate([_segment_steps(outline, spacing)] + [2 * _segment_steps(o, spacing) for o in obstacles])
    boundary_part = float(np.sum(step / h(ring)))
    return int(round(angle * max(A_FACTOR * area_part + B_FACTOR * boundary_part, floor)))


def _segment_steps(poly: np.ndarray, spacing: float) -> np.ndarray:
    """The arc length each point of _sample_closed(poly, spacing) stands for."""
    a, b = geometry.edges(poly)
    length = np.linalg.norm(b - a, axis=1)
    n = np.maximum(1, np.ceil(length / spacing)).astype(int)
    return np.repeat(length / n, n)


def budget_problems(cfg: Config) -> list[Problem]:
    """The mesh a config asks for, and the finer ones its accuracy selection makes, against the budget."""
    problems: list[Problem] = []
    n = estimate_elements(cfg)
    lc = cfg.layer_check
    if lc is not None and n <= ELEMENT_BUDGET and 0 <= lc.layer_z_mm <= lc.height_mm:
        m = cfg.tissue.mesh
        scale = m.scale * lc.in_plane_scale  # the slab's own 2-D mesh
        n_plane = n if lc.in_plane_scale == 1 else estimate_elements(cfg, scale=scale)
        first = lc.first_layer_mm or m.min_edge_mm * scale
        layers = len(geometry.graded_levels(lc.height_mm, lc.layer_z_mm, min(first, lc.max_layer_mm),
                                            lc.max_layer_mm)[0]) - 1
        tets = 3 * n_plane * layers
        if tets > TETRAHEDRA_BUDGET:
            problems.append((("layer_check",), (
                f"the slab would have about {tets} tetrahedra ({n_plane} triangles × 3 × {layers} prism layers); the "
                f"budget is {TETRAHEDRA_BUDGET} — use a larger max_layer_mm or in_plane_scale, a thinner slab or a "
                f"coarser tissue.mesh")))
    if n > ELEMENT_BUDGET:
        m = cfg.tissue.mesh
        problems.append((("tissue", "mesh"), (
            f"the mesh would have about {n} triangles (min_edge_mm {m.min_edge_mm:g}, max_edge_mm {m.max_edge_mm:g}, "
            f"grading {m.grading:g}, scale {m.scale:g}); the budget is {ELEMENT_BUDGET} — "
            f"use larger edges or more grading")))
    elif cfg.solver.accuracy_mm is not None:
        m = cfg.tissue.mesh
        # the run goes on with the picked level's config, which must validate too (trials re-read it)
        if m.min_edge_mm * m.scale * SELECTION_FINEST_LEVEL < MIN_EDGE_MM * (1 - 1e-12):
            return [(("solver", "accuracy_mm"), (
                f"the accuracy selection meshes down to {SELECTION_FINEST_LEVEL:g} x the size field: min_edge_mm "
                f"× scale × {SELECTION_FINEST_LEVEL:g} = {m.min_edge_mm * m.scale * SELECTION_FINEST_LEVEL:.3g} mm "
                f"is below the finest edge {MIN_EDGE_MM:g} mm; use larger edges or leave accuracy_mm out"))]
        if m.scale * SELECTION_COARSEST_LEVEL > MAX_SCALE:
            return [(("solver", "accuracy_mm"), (
                f"the accuracy selection meshes up to {SELECTION_COARSEST_LEVEL:g} x the size field: scale "
                f"{m.scale:g} × {SELECTION_COARSEST_LEVEL:g} is above the largest scale {MAX_SCALE:g}"))]
        fine = estimate_elements(cfg, scale=cfg.tissue.mesh.scale * SELECTION_FINEST_LEVEL)
        if fine > ELEMENT_BUDGET:
            problems.append((("solver", "accuracy_mm"), (
                f"the accuracy selection also meshes at {SELECTION_FINEST_LEVEL:g} x the size field: about {fine} "
                f"triangles, over the budget of {ELEMENT_BUDGET}; coarsen tissue.mesh (about "
                f"{ELEMENT_BUDGET // 16} triangles at scale 1 fit) or leave accuracy_mm out")))
    return problems
