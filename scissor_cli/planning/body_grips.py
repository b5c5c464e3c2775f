"""Where the cups grip a body: candidate patches on the skin, ranked by adjoint solves (docs/model.md §20, §7).

The layer's manipulation-point plan (`planning.manipulation_points`) over a
body's skin:

* **Candidates.** The skin's mesh nodes within `manipulation_points.skin`
  (a ball: centre, radius), thinned to one per cube of `spacing_mm` (the
  node nearest the cube's centre), each pushing along the skin's inward
  normal there; a node nearer the held base than the cup's radius is left
  out (its patch would grip held nodes). Every candidate is a skin node:
  each patch lies on the surface.
* **Response.** On the body with its cups released, at rest, a unit force
  (1 mN) along a candidate's normal spread with hat weights over the skin
  nodes within the cup's radius moves lesion t by R_t(c) (3,) mm/mN: one
  adjoint solve per lesion component for every candidate at once
  (`manipulation_points.adjoint_responses`), and per mm of stroke
  G_t(c) = R_t(c) / u_c with the patch's own compliance u_c.
* **What N cups must control.** The miss across lesion t's needle (the
  configured `needle.direction` n) has two components, Q_tᵀ G_t with Q_t
  (3, 2) an orthonormal basis across n; three cups or more control the 3-D
  position, G_t itself. A set S of N cups is scored by the k-th singular
  value of the lesion's matrix over S (k = min(N, 2) across the needle,
  3 for three cups or more): mm of motion per mm of stroke in the direction
  the set moves the lesion worst. Each lesion's value is divided by the
  best single candidate's response to it, and the set's score is the
  smallest over the lesions, so every lesion counts. One cup: every
  candidate; two: every pair; more: the best pair, then greedily the
  candidate that raises the score most. Patches of one set are at least
  two cup radii apart (they must not grip the same nodes). A lesion with
  a configured `desired_mm` must be moved there: a set whose least-squares
  strokes for that move (linear, from G) exceed the cups' stroke limit
  ranks behind every set within it. The force-loaded patch is softer than
  a cup's rigid grip, so G underestimates a cup's motion (the verification
  shows by how much) and the strokes are overestimated: the limit is kept
  on the safe side.
* **Verification.** The caller re-meshes the body with the chosen cups
  (`gripped`) and each is verified by a full nonlinear solve at half its
  largest stroke: its predicted (linear) motion of every lesion against
  the solved one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from scissor_cli.config.body_checks import skin_normals
from scissor_cli.mechanics.body_tissue import build_body, held_nodes, skin_nodes
from scissor_cli.mechanics.tissue import BoundaryError, Tissue
from scissor_cli.mesh.probe import target_positions
from scissor_cli.planning.manipulation_points import TEST_STROKE_FRACTION, adjoint_responses
from scissor_cli.solvers.equilibrium import solve_equilibrium

#: a set whose strokes for the configured moves exceed the limit ranks behind every set within it: its score / this
INFEASIBLE = 1.0e3

#: (contacts (k, 3) mm, axes (k, 3)) → the body with its first k cups gripping there (re-meshed)
GrippedBody = Callable[[np.ndarray, np.ndarray], Tissue]


@dataclass(frozen=True)
class SkinCandidates:
    """Candidate grips: skin nodes (P,) of the mesh, their points (P, 3) mm and inward unit normals (P, 3)."""

    nodes: np.ndarray
    points: np.ndarray
    normals: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class BodyGripPlan:
    """The plan: the candidates, the per-stroke responses G (T, P, 3) mm/mm of the T lesions, the needle axes
    (T, 3), each candidate's score as a single cup (P,), the chosen candidates (N,), their contacts and axes
    (N, 3), the set's score, the test strokes (N,) mm with the predicted and verified motion of every lesion
    (N, T, 3) mm, and the search's and verification's seconds."""

    candidates: SkinCandidates
    targets: list[str]
    per_stroke: np.ndarray
    axes_needle: np.ndarray
    single_score: np.ndarray
    chosen: np.ndarray
    score: float
    controls: str  # "the miss across the needle" | "the 3-D position"
    search_s: float
    test_strokes: np.ndarray = field(default_factory=lambda: np.zeros(0))
    predicted: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))
    verified: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))
    verify_s: float = 0.0

    @property
    def contacts(self) -> np.ndarray:
        return self.candidates.points[self.chosen]

    @property
    def axes(self) -> np.ndarray:
        return self.candidates.normals[self.chosen]


def skin_candidates(tissue: Tissue, center_mm, radius_mm: float, spacing_mm: float,
                    cup_radius_mm: float) -> SkinCandidates:
    """The candidate grips of the module docstring on a body tissue's mesh (none: an empty set)."""
    scene, mesh = tissue.scene, tissue.mesh
    skin = skin_nodes(scene, mesh, held_nodes(scene, mesh))
    p = mesh.nodes[skin]
    inside = np.linalg.norm(p - np.asarray(center_mm, float), axis=1) <= radius_mm
    inside &= np.asarray(scene.surface.to_held(p)) > cup_radius_mm
    skin, p = skin[inside], p[inside]
    if len(skin) == 0:
        return SkinCandidates(np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)))
    cube = np.floor(p / spacing_mm).astype(np.int64)
    off_centre = np.linalg.norm(p - (cube + 0.5) * spacing_mm, axis=1)
    _, cell = np.unique(cube, axis=0, return_inverse=True)
    order = np.lexsort((off_centre, cell.ravel()))  # by cube, nearest its centre first
    first = order[np.r_[True, np.diff(cell.ravel()[order]) != 0]]
    first.sort()
    points = p[first]
    return SkinCandidates(skin[first], points, -skin_normals(scene.surface, points))


def skin_forces(tissue: Tissue, cands: SkinCandidates, cup_radius_mm: float) -> np.ndarray:
    """F (3N, P) mN: a unit force along each candidate's inward normal, spread with hat weights over the skin
    nodes within cup_radius_mm of it (the candidate is a skin node, so at least itself)."""
    scene, mesh = tissue.scene, tissue.mesh
    skin = skin_nodes(scene, mesh, held_nodes(scene, mesh))
    pairs = cKDTree(cands.points).sparse_distance_matrix(cKDTree(mesh.nodes[skin]), cup_radius_mm,
                                                         output_type="ndarray")
    c, s, dist = pairs["i"], pairs["j"], pairs["v"]
    # each candidate's own node, at distance 0, which a sparse distance matrix may leave out
    own_c, own_s = np.arange(len(cands)), np.searchsorted(skin, cands.nodes)
    c, s = np.r_[c, own_c], np.r_[s, own_s]
    dist = np.r_[dist, np.zeros(len(own_c))]
    key = np.unique(c * len(skin) + s, return_index=True)[1]  # each (candidate, node) once
    c, s, dist = c[key], s[key], dist[key]
    w = np.clip(1.0 - dist / cup_radius_mm, 0.0, None)
    w = w / np.bincount(c, weights=w, minlength=len(cands))[c]
    F = np.zeros((3 * mesh.n_nodes, len(cands)))
    for k in range(3):
        np.add.at(F, (3 * skin[s] + k, c), w * cands.normals[c, k])
    return F


def released_body(tissue: Tissue) -> Tissue:
    """The body on the same mesh with every cup released (their nodes free)."""
    return build_body(replace(tissue.scene, cups=()), tissue.mesh, element=tissue.element.name)


def across(direction) -> np.ndarray:
    """Q (3, 2): an orthonormal basis of the plane across a needle direction (3,)."""
    n = np.asarray(direction, float) / np.linalg.norm(direction)
    helper = np.eye(3)[np.argmin(np.abs(n))]
    a = np.cross(n, helper)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(n, a)], axis=1)


def set_scores(M: np.ndarray, sets: np.ndarray, k: int, needed: np.ndarray | None = None,
               limit_mm: float = np.inf) -> np.ndarray:
    """Scores (S,) of candidate sets (S, N): min over lesions of the k-th singular value of M[t][:, set] divided by
    the lesion's best single response.

    M (T, m, P) mm/mm: each lesion's per-stroke response in the m components the cups must control. needed (T, m)
    mm: the move each lesion must make there (NaN rows: not known); a set whose least-squares strokes for a known
    move exceed limit_mm is kept only behind every set that stays within it (its score / INFEASIBLE)."""
    best = np.maximum(np.linalg.norm(M, axis=1).max(axis=1), 1e-300)  # (T,)
    sub = np.moveaxis(M[:, :, sets], 2, 0)  # (S, T, m, N)
    sigma = np.linalg.svd(sub / best[None, :, None, None], compute_uv=False)  # (S, T, min(m, N))
    score = (sigma[:, :, k - 1] if sigma.shape[2] >= k else np.zeros(sigma.shape[:2])).min(axis=1)
    if needed is None or not np.isfinite(limit_mm):
        return score
    known = np.all(np.isfinite(needed), axis=1)
    if not known.any():
        return score
    strokes = np.linalg.pinv(sub[:, known]) @ needed[known][None, :, :, None]  # (S, T', N, 1)
    within = np.all(np.abs(strokes[..., 0]) <= limit_mm, axis=(1, 2))
    return np.where(within, score, score / INFEASIBLE)


def choose(M: np.ndarray, points: np.ndarray, n_cups: int, gap_mm: float, k: int, needed: np.ndarray | None = None,
           limit_mm: float = np.inf) -> tuple[np.ndarray, float]:
    """The chosen candidates (n_cups,) and their score (`set_scores`): every one or pair, then greedily."""
    P = M.shape[2]
    far = np.linalg.norm(points[:, None] - points[None], axis=2) >= gap_mm  # (P, P)
    if n_cups == 1:
        scores = set_scores(M, np.arange(P)[:, None], 1, needed, limit_mm)
        best = int(np.argmax(scores))
        return np.array([best]), float(scores[best])
    i, j = np.triu_indices(P, 1)
    pairs = np.column_stack([i, j])[far[i, j]]
    if len(pairs) == 0:
        raise BoundaryError(f"manipulation_points: no {n_cups} candidates on the skin are two cup radii "
                            f"({gap_mm:g} mm) apart: widen manipulation_points.skin or lower spacing_mm")
    scores = set_scores(M, pairs, min(k, 2), needed, limit_mm)
    chosen, score = list(pairs[int(np.argmax(scores))]), float(scores.max())
    while len(chosen) < n_cups:
        free = np.flatnonzero(np.all(far[chosen], axis=0))
        free = free[~np.isin(free, chosen)]
        if len(free) == 0:
            raise BoundaryError(f"manipulation_points: no {n_cups} candidates on the skin are two cup radii "
                                f"({gap_mm:g} mm) apart: widen manipulation_points.skin or lower spacing_mm")
        sets = np.column_stack([np.tile(chosen, (len(free), 1)), free])
        scores = set_scores(M, sets, k, needed, limit_mm)
        chosen.append(int(free[np.argmax(scores)]))
        score = float(scores.max())
    return np.array(chosen, int), score


def plan_body_grips(tissue: Tissue, center_mm, radius_mm: float, spacing_mm: float, n_cups: int,
                    needle_direction, cup_radius_mm: float, stroke_limit_mm: float = np.inf) -> BodyGripPlan:
    """Rank the skin's candidate grips for the body's lesions and choose `n_cups` (module docstring);
    stroke_limit_mm: the largest stroke the cups to place share (a lesion's configured move must stay within it).

    BoundaryError (the run exits 2) when the region holds no candidate or too few far enough apart.
    """
    t0 = time.perf_counter()
    cands = skin_candidates(tissue, center_mm, radius_mm, spacing_mm, cup_radius_mm)
    if len(cands) < n_cups:
        raise BoundaryError(
            f"manipulation_points.skin: {len(cands)} candidate grip(s) on the skin within {radius_mm:g} mm of "
            f"{np.round(np.asarray(center_mm, float), 2).tolist()} (at least {cup_radius_mm:g} mm from the held "
            f"base), fewer than the {n_cups} cups to place: move or widen the region")
    free = released_body(tissue)
    lesions = tissue.scene.targets
    rest = np.array([t.rest for t in lesions], float).reshape(-1, 3)
    probe = free.probe(rest)
    R, u, _ = adjoint_responses(free, free.rest, probe, skin_forces(free, cands, cup_radius_mm))
    G = R / u[None, :, None]  # (T, P, 3) mm per mm of stroke
    Q = across(needle_direction)
    k = 3 if n_cups >= 3 else n_cups
    M = np.einsum("tpi,ij->tjp", G, Q) if k < 3 else np.transpose(G, (0, 2, 1))  # (T, m, P)
    moves = np.array([np.full(3, np.nan) if t.desired is None else t.desired - t.rest for t in lesions]).reshape(-1, 3)
    needed = moves @ Q if k < 3 else moves
    single = set_scores(M, np.arange(len(cands))[:, None], 1)
    chosen, score = choose(M, cands.points, n_cups, 2.0 * cup_radius_mm, k, needed, stroke_limit_mm)
    n = np.asarray(needle_direction, float) / np.linalg.norm(needle_direction)
    return BodyGripPlan(cands, [t.name for t in lesions], G, np.tile(n, (len(lesions), 1)), single, chosen, score,
                        "the 3-D position" if k == 3 else "the miss across the needle", time.perf_counter() - t0)


def verify(plan: BodyGripPlan, gripped: GrippedBody, stroke_limits: np.ndarray) -> Tissue:
    """Each chosen cup's full nonlinear solve at TEST_STROKE_FRACTION of its largest stroke on the re-meshed body
    (the others at 0): fills plan.test_strokes, predicted and verified (N, T, 3) mm; returns the body.

    stroke_limits (N, 2) mm: the chosen cups' [min, max] strokes.
    """
    t0 = time.perf_counter()
    body = gripped(plan.contacts, plan.axes)
    probe = body.probe(np.array([t.rest for t in body.scene.targets], float).reshape(-1, 3))
    lo, hi = np.asarray(stroke_limits, float).T
    plan.test_strokes = np.clip(TEST_STROKE_FRACTION * np.maximum(np.abs(lo), np.abs(hi)), lo, hi)
    plan.predicted = np.stack([plan.per_stroke[:, c] * s for c, s in zip(plan.chosen, plan.test_strokes)])
    moved = []
    for i, s in enumerate(plan.test_strokes):
        strokes = np.zeros(body.n_cups)
        strokes[i] = s
        x = solve_equilibrium(body, strokes).x
        moved.append(target_positions(probe, x) - target_positions(probe, body.rest))
    plan.verified = np.stack(moved)
    plan.verify_s = time.perf_counter() - t0
    return body
