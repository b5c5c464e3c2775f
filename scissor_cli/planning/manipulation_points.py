"""Manipulation-point plan: where the cups should grip (docs/model.md §7).

Candidates are points spread along the accessible (non-fixed) sides at
`spacing_mm` (arc length), each pushing along the inward normal, far enough
from a fixed side that a cup of the first cup's radius fits.

**Response by adjoint solves.** At the current equilibrium x (the rest
state of the layer with the cups released: their nodes free) with
K = ∇²U(x) exact, a force f_c (2N,) at candidate c moves the free nodes by
K_ff⁻¹ f_c, and target t by S_t K_ff⁻¹ f_c. With one adjoint solve per
target component,

    K_ff λ_t = S_tᵀ   (2 columns per target),   δy_t(c) = λ_tᵀ f_c   (2, P) for all P candidates,

so the response of every target to every candidate costs two
back-substitutions per target. f_c spreads a unit force (1 mN) along the
inward normal over the boundary nodes within the cup radius (hat weights
summing to 1), as a cup grips that stretch.

**Per unit stroke.** A cup is displacement-driven: what counts is the
target motion per mm of stroke. The stroke a unit force produces is the
patch's own compliance u_c = f_cᵀ K_ff⁻¹ f_c, so the response per unit
stroke is δy_t(c) / u_c. u_c needs K_ff⁻¹ f_c for every candidate: one
multi-column back-substitution on the same factorisation (P columns, a
few ms), documented here because it is the one solve beyond the adjoints.

**Ranking.** The needle axis n_t of a target is the best insertion at rest
(`planning.corridor`); the motion that matters is across it (the miss,
docs/model.md §6), m_t ⟂ n_t. A candidate's score for a target is
|m_tᵀ δy_t(c)| / u_c, mm of miss per mm of stroke; the scene's score sums
the targets' scores each divided by its best, so every target counts.

**Verification.** The best `verify` candidates (distinct grips, at least
two radii apart) are each verified by a full nonlinear solve with a cup
gripping there (a new mesh and tissue whose first cup has the candidate's
contact and axis) at a test stroke inside the cup's limits; the predicted
target motion (linear, per unit stroke × stroke) is compared with the
verified one, and a grip whose verified solve fails or whose deformed
scene pushes a target into an obstacle is dropped. The best verified
grips become the first `cups` entries' contact_mm and axis.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import numpy as np

from scissor_cli import geometry
from scissor_cli.config import ManipulationPointsConfig, NeedleConfig
from scissor_cli.mechanics.tissue import Tissue, build_tissue
from scissor_cli.mesh.mesh import Mesh
from scissor_cli.mesh.outlines import deformed_outlines, embed_outlines
from scissor_cli.mesh.probe import TargetProbe, probe_targets, target_positions
from scissor_cli.planning.corridor import candidate_directions, ranked_insertions
from scissor_cli.scene.scene import Scene
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.linear import Factorization, factorize_free

#: Candidates verified by a full nonlinear solve (the best by the linear score).
VERIFY = 3

#: The test stroke of a verification, as a fraction of the cup's largest stroke.
TEST_STROKE_FRACTION = 0.5


@dataclass(frozen=True)
class GripCandidates:
    """Candidate contact points on the accessible sides: points (P, 2) mm, inward normals (P, 2), side (P,)."""

    points: np.ndarray
    normals: np.ndarray
    sides: list[str]

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class TargetResponse:
    """One target's response to every candidate: response (P, 2) mm/mN, per_stroke (P, 2) mm/mm,
    score (P,) mm of miss per mm of stroke, needle axis (2,) and miss direction (2,)."""

    target: str
    response: np.ndarray
    per_stroke: np.ndarray
    score: np.ndarray
    axis: np.ndarray
    miss_direction: np.ndarray
    chosen: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    predicted: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    verified: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))


@dataclass
class GripPlan:
    """The plan: candidates, per-target responses, the chosen candidate indices (cups,), their
    contact points (cups, 2) and axes (cups, 2), the test strokes (cups,) mm, how long the search
    (adjoint + ranking) and the verification took, and notes."""

    candidates: GripCandidates
    targets: list[TargetResponse]
    chosen: np.ndarray
    contacts: np.ndarray
    axes: np.ndarray
    test_strokes: np.ndarray
    compliance: np.ndarray  # (P,) mm/mN
    search_s: float = 0.0
    verify_s: float = 0.0
    notes: list[str] = field(default_factory=list)


def grip_candidates(scene: Scene, sides, spacing_mm: float, radius_mm: float) -> GripCandidates:
    """Points every spacing_mm of arc length along the edges of the named sides of the outline, with their
    inward normals; points closer than radius_mm to a fixed side are left out (the cup would grip it)."""
    poly = scene.outline
    a, b = geometry.edges(poly)
    normals = -geometry.outward_normals(poly)
    mask = np.zeros(len(a), bool)
    names = np.array([""] * len(a), dtype=object)
    for side in sides:
        m = geometry.side_edge_mask(poly, side) & ~mask
        names[m] = side
        mask |= m
    fixed = np.zeros(len(a), bool)
    for side in scene.fixed_sides:
        fixed |= geometry.side_edge_mask(poly, side)
    pts, nrm, sd = [], [], []
    carry = 0.0  # arc length since the last point, across consecutive side edges
    for k in np.flatnonzero(mask):
        length = float(np.linalg.norm(b[k] - a[k]))
        t = np.arange(carry, length, spacing_mm)
        carry = (carry - length) % spacing_mm if len(t) == 0 else spacing_mm - (length - t[-1])
        for s in t:
            pts.append(a[k] + (b[k] - a[k]) * (s / length))
            nrm.append(normals[k])
            sd.append(str(names[k]))
    if not pts:
        return GripCandidates(np.zeros((0, 2)), np.zeros((0, 2)), [])
    pts, nrm = np.array(pts), np.array(nrm)
    keep = np.ones(len(pts), bool)
    if fixed.any():
        d = np.asarray(geometry.point_segment_distance(pts, a[fixed], b[fixed])).reshape(len(pts), -1)
        keep = d.min(axis=1) > radius_mm
    return GripCandidates(pts[keep], nrm[keep], [s for s, k in zip(sd, keep) if k])


def force_vectors(mesh: Mesh, cands: GripCandidates, radius_mm: float) -> np.ndarray:
    """F (2N, P) mN: a unit force along each candidate's inward normal, spread with hat weights over the
    boundary nodes within radius_mm (the nearest boundary node when none is)."""
    nodes = np.unique(mesh.boundary_edges)
    P = len(cands)
    F = np.zeros((2 * mesh.n_nodes, P))
    for c in range(P):
        d = np.linalg.norm(mesh.nodes[nodes] - cands.points[c], axis=1)
        w = np.clip(1.0 - d / radius_mm, 0.0, None)
        if not w.any():
            w[np.argmin(d)] = 1.0
        w /= w.sum()
        hit = nodes[w > 0]
        F[2 * hit, c] = w[w > 0] * cands.normals[c, 0]
        F[2 * hit + 1, c] = w[w > 0] * cands.normals[c, 1]
    return F


def released(tissue: Tissue) -> Tissue:
    """The tissue on the same mesh with every cup released (their nodes free): where candidates push."""
    scene = replace(tissue.scene, cups=())
    return build_tissue(scene, tissue.mesh, element=tissue.element.name)


def needle_axis(scene: Scene, target_rest: np.ndarray, needle_cfg: NeedleConfig) -> np.ndarray:
    """The best insertion's direction (2,) at rest (largest clearance, whether clear or not), else +x."""
    ranked = ranked_insertions(target_rest, [o.outline for o in scene.obstacles], scene.outline,
                               candidate_directions(needle_cfg, scene), needle_cfg)
    return ranked[0].direction if ranked else np.array([1.0, 0.0])


def adjoint_responses(tissue: Tissue, x: np.ndarray, probe: TargetProbe, F: np.ndarray,
                      factor: Optional[Factorization] = None) -> tuple[np.ndarray, np.ndarray, Factorization]:
    """Responses R (K, P, d) mm/mN of the probe's K targets to the forces F (dN, P) mN at the equilibrium x (N, d),
    by one adjoint solve per target component (K_ff λ = S_tᵀ, R = λᵀ F); and the candidates' compliance
    u (P,) mm/mN = f_cᵀ K_ff⁻¹ f_c. d = tissue.dim: the layer's (2) or a body's (3)."""
    d = tissue.dim
    K = tissue.stiffness_free(x, project=False, upper=True)
    factor = factorize_free(tissue, K, {}) if factor is None else factor.refactor(K)
    free = tissue.free_dofs
    n_targets, corners = probe.nodes.shape
    St = np.zeros((d * tissue.mesh.n_nodes, d * n_targets))  # S_tᵀ: one column per target component
    rows = d * probe.nodes[:, :, None] + np.arange(d)  # (K, corners, d)
    cols = np.broadcast_to(d * np.arange(n_targets)[:, None, None] + np.arange(d), rows.shape)
    np.add.at(St, (rows.ravel(), cols.ravel()), np.repeat(probe.bary[:, :, None], d, axis=2).ravel())
    lam = factor.solve(np.ascontiguousarray(St[free])).reshape(len(free), -1)
    Ff = F[free]
    Ff = Ff.toarray() if hasattr(Ff, "toarray") else Ff
    R = (lam.T @ Ff).reshape(n_targets, d, -1).transpose(0, 2, 1)
    u = np.einsum("ip,ip->p", Ff, factor.solve(np.ascontiguousarray(Ff)).reshape(Ff.shape))
    return R, u, factor


#: (contacts (k, 2) mm, axes (k, 2)) → the model with the first k cups gripping there (re-meshed)
GrippedModel = Callable[[np.ndarray, np.ndarray], Tissue]


def plan_grips(mp: ManipulationPointsConfig, needle: NeedleConfig, tissue: Tissue, gripped: GrippedModel,
               verify: int = VERIFY) -> GripPlan:
    """Choose where the first `mp.cups` cups grip (docs/model.md §7).

    `gripped(contacts, axes)` builds the model with the cups there (the
    verification re-meshes with the cup at each verified candidate). Raises
    ValueError when no candidate exists (sides too short for the cup).
    """
    scene = tissue.scene
    n_place = mp.cups
    radius = scene.cups[0].radius_mm if scene.cups else 5.0
    t0 = time.perf_counter()
    cands = grip_candidates(scene, mp.sides, mp.spacing_mm, radius)
    if len(cands) == 0:
        raise ValueError(f"manipulation_points: no candidate on sides {list(mp.sides)} at least {radius:g} mm "
                         f"(the cup radius) from a fixed side")
    free = released(tissue)
    x = free.rest
    targets = np.array([t.rest for t in scene.targets]).reshape(-1, 2)
    F = force_vectors(free.mesh, cands, radius)
    R, u, _ = adjoint_responses(free, x, probe_targets(free.mesh, targets), F)
    per_stroke = R / u[None, :, None]
    responses = []
    total = np.zeros(len(cands))
    for k, t in enumerate(scene.targets):
        n = needle_axis(scene, t.rest, needle)
        m = np.array([-n[1], n[0]])
        score = np.abs(per_stroke[k] @ m)
        responses.append(TargetResponse(t.name, R[k], per_stroke[k], score, n, m))
        total += score / max(score.max(), 1e-300)
    if not scene.targets:
        total = 1.0 / np.maximum(u, 1e-300)  # no targets: the stiffest grips move the layer most per stroke
    search_s = time.perf_counter() - t0
    plan = GripPlan(cands, responses, np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), u,
                    search_s=search_s)
    _verify(tissue.scene.cups[0], plan, total, n_place, radius, gripped, verify)
    return plan


def _distinct(order: np.ndarray, points: np.ndarray, gap: float, count: int) -> list[int]:
    out: list[int] = []
    for c in order:
        if all(np.linalg.norm(points[c] - points[o]) >= gap for o in out):
            out.append(int(c))
        if len(out) == count:
            break
    return out


def _verify(cup0, plan: GripPlan, total: np.ndarray, n_place: int, radius: float, gripped: GrippedModel,
            verify: int) -> None:
    """Full nonlinear solves at the best candidates; fills plan.chosen, contacts, axes and the targets'
    predicted / verified motion."""
    from scissor_cli.solvers.equilibrium import solve_equilibrium  # noqa: PLC0415 - same layer, kept local

    t0 = time.perf_counter()
    cands = plan.candidates
    order = np.argsort(-total, kind="stable")
    pool = _distinct(order, cands.points, 2.0 * radius, max(verify, n_place))
    lo, hi = cup0.stroke_min_mm, cup0.stroke_max_mm
    stroke = float(np.clip(TEST_STROKE_FRACTION * max(abs(lo), abs(hi)), lo, hi))
    verified: dict[int, np.ndarray] = {}
    gains: dict[int, float] = {}
    for c in pool:
        try:
            t = gripped(cands.points[c][None], cands.normals[c][None])
            s = np.zeros(t.n_cups)
            s[0] = stroke
            r = solve_equilibrium(t, s)
        except (SolverError, ValueError) as exc:
            plan.notes.append(f"candidate {cands.points[c].round(2).tolist()} dropped: {exc}")
            continue
        probe = probe_targets(t.mesh, np.array([tr.rest for tr in t.scene.targets]).reshape(-1, 2))
        moved = target_positions(probe, r.x) - target_positions(probe, t.rest)
        obstacles = deformed_outlines(embed_outlines(t.mesh, [o.outline for o in t.scene.obstacles]), r.x)
        y = target_positions(probe, r.x)
        if any(geometry.points_in_polygon(y, o).any() for o in obstacles):
            plan.notes.append(f"candidate {cands.points[c].round(2).tolist()} dropped: a target enters an obstacle")
            continue
        verified[c] = moved
        gains[c] = float(sum(abs(moved[k] @ tr.miss_direction) / max(tr.score.max() * stroke, 1e-300)
                             for k, tr in enumerate(plan.targets))) if plan.targets else total[c]
    ranked = sorted(verified, key=lambda c: -gains[c])
    chosen = _distinct(np.array(ranked + [c for c in order if c not in verified], int), cands.points, 2.0 * radius,
                       n_place)
    plan.chosen = np.array(chosen, int)
    plan.contacts = cands.points[plan.chosen]
    plan.axes = cands.normals[plan.chosen]
    plan.test_strokes = np.full(len(chosen), stroke)
    best = chosen[0]
    for k, tr in enumerate(plan.targets):
        tr.chosen = plan.contacts
        tr.predicted = tr.per_stroke[best] * stroke
        tr.verified = verified[best][k] if best in verified else np.full(2, np.nan)
    plan.verify_s = time.perf_counter() - t0
