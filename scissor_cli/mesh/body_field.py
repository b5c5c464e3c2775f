"""The size field of a 3-D body: h(p) in numpy and as gmsh's MathEval expression, from one list of features.

h(p) = clip(min_edge + grading · d(p), min_edge, max_edge), where d is the
distance to the nearest feature and 0 inside one. The features are balls
(spheres, refine patches) and capsules (every segment of a tube with its
radius: cylinders with balls at the joints and ends). A skin shell adds a
second term of the same form, min with the first: edge skin_edge in the
shell, growing by the same grading with the depth below it, so a thin shell
is not filled with flat tetrahedra. The mesher hands gmsh the expression;
`estimate_tetrahedra` integrates the same h(p), so the element budget is
refused on the size field that makes the mesh.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: the volume of a regular tetrahedron of edge h is h³ times this
REGULAR_TET_VOLUME = 1.0 / (6.0 * np.sqrt(2.0))


@dataclass(frozen=True, eq=False)
class Features:
    """What the mesh is fine at: balls (centre, radius) and capsules (segment a-b, radius), all mm."""

    ball_center: np.ndarray  # (B, 3)
    ball_radius: np.ndarray  # (B,)
    seg_a: np.ndarray  # (S, 3)
    seg_b: np.ndarray  # (S, 3)
    seg_radius: np.ndarray  # (S,)
    min_edge: float
    max_edge: float
    grading: float
    #: each feature's own edge at and inside it (B,), (S,); None: min_edge for all. A small inclusion asks for
    #: edges below min_edge so that its faceted surface holds its volume (`body_mesh.INCLUSION_EDGE_PER_RADIUS`)
    ball_edge: np.ndarray | None = None
    seg_edge: np.ndarray | None = None
    #: the skin term: its edge length, its signed distance (negative in the shell; 1-Lipschitz) in numpy and
    #: as a MathEval expression of x, y, z (and of other fields F<n>)
    skin_edge: float | None = None
    skin_distance: Callable[[np.ndarray], np.ndarray] | None = None
    skin_expression: str | None = None
    skin_thickness: float | None = None

    def distance(self, p: np.ndarray) -> np.ndarray:
        """Distance (K,) from points (K, 3) to the nearest feature, 0 inside one, inf with no features."""
        return np.maximum(self.signed_distance(p), 0.0)

    def signed_distance(self, p: np.ndarray) -> np.ndarray:
        """Like `distance`, but negative inside a feature (a 1-Lipschitz lower bound of the depth there)."""
        d = np.full(len(p), np.inf)
        for lo in range(0, len(p), 8192):  # chunks bound the (K, B) and (K, S) temporaries
            chunk = p[lo:lo + 8192]
            best = d[lo:lo + 8192]
            if len(self.ball_radius):
                ball = np.linalg.norm(chunk[:, None] - self.ball_center[None], axis=2) - self.ball_radius
                best = np.minimum(best, ball.min(axis=1))
            if len(self.seg_radius):
                seg = segment_distance(chunk, self.seg_a, self.seg_b) - self.seg_radius
                best = np.minimum(best, seg.min(axis=1))
            d[lo:lo + 8192] = best
        return d

    @property
    def edges(self) -> np.ndarray:
        """Every feature's own edge (B + S,) mm, balls first."""
        n = len(self.ball_radius) + len(self.seg_radius)
        if self.ball_edge is None and self.seg_edge is None:
            return np.full(n, self.min_edge)
        return np.concatenate([self.ball_edge if self.ball_edge is not None else np.full(len(self.ball_radius),
                                                                                          self.min_edge),
                               self.seg_edge if self.seg_edge is not None else np.full(len(self.seg_radius),
                                                                                        self.min_edge)])

    @property
    def floor(self) -> float:
        """The smallest edge the field asks for anywhere (mm)."""
        return float(min(self.min_edge, np.min(self.edges, initial=self.min_edge)))

    def _feature_distances(self, p: np.ndarray) -> np.ndarray:
        """Signed distances (K, B + S) from points (K, 3) to every feature, negative inside."""
        parts = []
        if len(self.ball_radius):
            parts.append(np.linalg.norm(p[:, None] - self.ball_center[None], axis=2) - self.ball_radius)
        if len(self.seg_radius):
            parts.append(segment_distance(p, self.seg_a, self.seg_b) - self.seg_radius)
        return np.concatenate(parts, axis=1) if parts else np.zeros((len(p), 0))

    def _features_term(self, p: np.ndarray, shift: float = 0.0) -> np.ndarray:
        """min over the features of clip(edge_f + grading · max(d_f + shift, 0), floor, max_edge) (K,); without
        features the field's far size (min_edge everywhere when nothing grows)."""
        out = np.full(len(p), self.min_edge if self.grading == 0 else self.max_edge)
        edges = self.edges
        for lo in range(0, len(p), 8192):  # chunks bound the (K, F) temporaries
            d = self._feature_distances(p[lo:lo + 8192])
            if d.shape[1]:
                out[lo:lo + 8192] = self.graded(edges[None, :], np.maximum(d + shift, 0.0)).min(axis=1)
        return out

    def edge_length(self, p: np.ndarray) -> np.ndarray:
        """The target edge length h (K,) in mm at points (K, 3)."""
        p = np.atleast_2d(p)
        h = np.minimum(self._features_term(p), self.max_edge)
        if self.skin_edge is not None:
            h = np.minimum(h, self.graded(self.skin_edge, np.maximum(self.skin_distance(p), 0.0)))
        return h

    def graded(self, base, d: np.ndarray) -> np.ndarray:
        """clip(base + grading · d, floor, max_edge) for distances d >= 0 (inf: no feature)."""
        grown = self.grading * np.minimum(d, 1e30) if self.grading > 0 else np.zeros_like(d)
        return np.clip(base + grown, self.floor, self.max_edge)

    def edge_range(self, p: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """Bounds (K,), (K,) of h over the balls of radius `reach` around points p: each term is exact where it
        is flat (inside its feature, or beyond its graded zone) and moves by at most grading · reach elsewhere."""
        lo = np.minimum(self._features_term(p, -reach), self.max_edge)
        hi = np.minimum(self._features_term(p, reach), self.max_edge)
        if self.skin_edge is not None:
            lo_s, hi_s = self._term_range(self.skin_edge, self.skin_distance(p), reach)
            lo, hi = np.minimum(lo, lo_s), np.minimum(hi, hi_s)
        return lo, hi

    def _term_range(self, base: float, d: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        return self.graded(base, np.maximum(d - reach, 0.0)), self.graded(base, np.maximum(d + reach, 0.0))

    def gmsh_expression(self) -> str:
        """h(p) as a MathEval expression of x, y, z: the same formula as `edge_length`.

        Every number is written in parentheses: mathex parses "x--5" as an
        error, and a parse error in a MathEval field aborts the process.
        """
        terms = [f"Sqrt({_sq('x', c[0])}+{_sq('y', c[1])}+{_sq('z', c[2])})-{_num(r)}"
                 for c, r in zip(self.ball_center, self.ball_radius)]
        for a, b, r in zip(self.seg_a, self.seg_b, self.seg_radius):
            u = b - a
            t = (f"Max(0,Min(1,((x-{_num(a[0])})*{_num(u[0])}+(y-{_num(a[1])})*{_num(u[1])}"
                 f"+(z-{_num(a[2])})*{_num(u[2])})/{_num(float(u @ u))}))")
            gaps = [f"({axis}-{_num(a[k])}-{t}*{_num(u[k])})^2" for k, axis in enumerate("xyz")]
            terms.append(f"Sqrt({'+'.join(gaps)})-{_num(r)}")
        edges = self.edges
        if terms and np.all(edges == edges[0]):  # one edge: grade the nearest feature's distance
            h = self._graded_expression(float(edges[0]), f"Min({','.join(terms)})")
        elif terms:
            h = f"Min({','.join(self._graded_expression(float(e), d) for e, d in zip(edges, terms))})"
        else:
            h = self._graded_expression(self.min_edge, None)
        if self.skin_edge is not None:
            h = f"Min({h},{self._graded_expression(self.skin_edge, self.skin_expression)})"
        return h

    def _graded_expression(self, base: float, distance: str | None) -> str:
        if distance is None:  # no feature: the far size, or the base size everywhere when nothing grows
            return _num(base if self.grading == 0 else self.max_edge)
        grown = f"{_num(base)}+{_num(self.grading)}*Max(0,{distance})"
        return f"Min({_num(self.max_edge)},Max({_num(self.floor)},{grown}))"


def _num(value: float) -> str:
    return f"({float(value)!r})"


def _sq(axis: str, c: float) -> str:
    return f"({axis}-{_num(c)})^2"


def segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (K, S) from points (K, 3) to segments a-b (S, 3)."""
    u = b - a
    length2 = np.maximum(np.sum(u * u, axis=1), 1e-300)
    w = p[:, None] - a[None]
    t = np.clip(np.einsum("ksj,sj->ks", w, u) / length2, 0.0, 1.0)
    return np.linalg.norm(w - t[..., None] * u[None], axis=2)


def polyline_distance(p: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance (K,) from points (K, 3) to a polyline (P, 3)."""
    return segment_distance(p, points[:-1], points[1:]).min(axis=1)


def density_integral(features: Features, inside, lo: np.ndarray, hi: np.ndarray, shell_factor: float = 0.0,
                     tol: float = 0.5) -> float:
    """∫ w(p) dV / V_tet(h(p)) over the body (`inside(points) -> bool`) in the box lo..hi, on adaptive cells.

    w = 1, but max(1, shell_factor · h / t) in a skin shell of thickness t:
    a shell thinner than its elements is filled with flat tetrahedra, more
    of them per volume than regular ones of edge h.

    Cells start at 24 across the box's widest side (no coarser than
    max_edge) and split into eight while h can change across one by more
    than `tol` of its smallest value there (|∇h| <= grading bounds it), so
    the sum sees features far smaller than the box; a cell wholly inside a
    feature or beyond the graded zone, where h is flat, is not split. Each
    leaf counts its volume at its centre's h if its centre is in the body.
    """
    g, h_min, h_max = features.grading, features.floor, features.max_edge
    width = float(np.max(hi - lo))
    cell = min(h_max, width / 24.0)
    n = np.maximum(np.ceil((hi - lo) / cell).astype(int), 1)
    axes = [lo[k] + cell * (np.arange(n[k]) + 0.5) for k in range(3)]
    centers = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    children = 0.25 * np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    total = 0.0
    while len(centers):
        h_lo, h_hi = features.edge_range(centers, 0.5 * np.sqrt(3.0) * cell)
        split = (g > 0) & (h_hi - h_lo > tol * h_lo) & (cell > h_min / 8)
        points = centers[~split]
        points = points[inside(points)]
        if len(points):
            h = features.edge_length(points)
            weight = np.ones(len(points))
            if features.skin_thickness:
                shell = features.skin_distance(points) < 0
                weight[shell] = np.maximum(1.0, shell_factor * h[shell] / features.skin_thickness)
            total += float(np.sum(weight * cell**3 / (REGULAR_TET_VOLUME * h**3)))
        centers = (centers[split][:, None] + cell * children[None]).reshape(-1, 3)
        cell /= 2.0
    return total


def spheroid_depth(a: float, c: float) -> tuple[Callable[[np.ndarray], np.ndarray], str]:
    """Depth below the half-spheroid E: x²/a² + y²/a² + z²/c² <= 1, negative outside, in numpy and MathEval.

    m·(1 − ρ), ρ = √(x²/a² + y²/a² + z²/c²), m = min(a, c): exact on the
    shorter axis, an underestimate elsewhere (ρE grown by (1 − ρ)m stays in
    E, which is convex and holds the ball of radius m), and 1-Lipschitz
    (|∇ρ| <= 1/m), as the size field's distances must be.
    """
    m = min(a, c)

    def depth(p: np.ndarray) -> np.ndarray:
        return m * (1.0 - np.sqrt((p[:, 0] ** 2 + p[:, 1] ** 2) / a**2 + p[:, 2] ** 2 / c**2))

    return depth, f"{_num(m)}*(1-Sqrt((x^2+y^2)/{_num(a * a)}+z^2/{_num(c * c)}))"
