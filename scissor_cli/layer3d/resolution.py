"""The slab's resolution by accuracy: `layer_check.accuracy_mm` (docs/model.md §13, §18).

The slab's cost is its size: every prism layer copies the whole 2-D mesh,
and a sparse Cholesky factor of a 3-D mesh grows faster than its unknowns
(halving the levels or coarsening the plane divides a factorisation's time
several times over; benchmarks/bench_slab_truth.py). A run that only needs
its targets to a tolerance can use a coarser slab, and the slab-truth
trials factor it dozens of times per trial.

Candidates are the product of two ladders, the configured slab (the
finest) first:

* z gradings: the thinnest layer `first_layer_mm` at the layer (default
  the 2-D mesh's finest edge) doubling per rung and the thickest
  (`max_layer_mm`) growing by 1.6;
* in-plane meshes: the slab's 2-D mesh `in_plane_scale` times the
  configured one's, for each of IN_PLANE_SCALES (`tissue.mesh`'s edge
  lengths scaled: still finest at targets, obstacles and cups).

Coarse to fine against the finest (`choose_slab`): the configured (finest)
slab is solved first over the forward cases (Newton to SOLVE_TOL); then
the candidates are taken in the order of their tetrahedra (counted from
the plane meshes and the z levels, without building a slab), each solved
and its error measured as the largest 3-D distance of a target (without
targets: of a layer node) from the finest slab's. The first candidate
within `accuracy_mm` is the pick — the one the full ladder, every
candidate solved, picks — having solved the finest and the candidates
coarser than the pick; the finest is the pick when none is.

An estimate that would spare the finest solve — twice a candidate's
distance to its neighbour one rung finer on both ladders, a bound if each
rung halved the error — was tried and dropped: the error is not monotone
along either ladder (which nodes a cup grips within its radius changes
with the levels next to the layer and with the side's nodes), so the
estimate both refused every candidate of the paper's prosthesis scene and
accepted for configs/example_3d.yaml a slab outside its accuracy
(docs/performance.md, "The needle that hits in 3-D"; benchmarks/bench_slab_ladder.py).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from scissor_cli import progress
from scissor_cli.geometry import graded_levels
from scissor_cli.layer3d.slab import SlabSpec, build_slab, layer_probe, plane_mesh, slab_probe
from scissor_cli.mechanics.tissue import BoundaryError, Tissue
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.linear import factorize_free
from scissor_cli.solvers.newton import solve_newton

#: rungs of the z ladder, the configured grading included
RUNGS = 5
#: the in-plane ladder: the slab's 2-D mesh scale over the configured one
IN_PLANE_SCALES = (1.0, 1.5, 2.0, 2.5, 3.0)
#: per rung: the thinnest layer doubles, the thickest grows by this factor
MAX_LAYER_GROWTH = 1.6
#: the candidates' forward solves: well below any accuracy a run asks for
SOLVE_TOL = 1e-8


@dataclass(frozen=True)
class SlabCandidate:
    """One slab: its 2-D mesh scale and z layers (mm), size; when solved, its error (mm: the largest distance of a
    target from the finest slab's, `reference` 0; the finest's is 0), one refactorisation and its forward solves
    (s). An unsolved candidate has error_mm, factor_s and solve_s −1 and reference −1."""

    in_plane_scale: float
    first_layer_mm: float
    max_layer_mm: float
    levels: int
    n_tetrahedra: int
    error_mm: float = -1.0
    factor_s: float = -1.0
    solve_s: float = -1.0
    reference: int = -1

    @property
    def solved(self) -> bool:
        return self.solve_s >= 0.0


@dataclass(frozen=True)
class SlabChoice:
    """What `layer_check.accuracy_mm` picked; `candidates[0]` is the configured (finest) slab."""

    accuracy_mm: float
    pick: int
    candidates: tuple

    @property
    def chosen(self) -> SlabCandidate:
        return self.candidates[self.pick]

    @property
    def size_ratio(self) -> float:
        """The finest slab's tetrahedra over the chosen one's."""
        return self.candidates[0].n_tetrahedra / self.chosen.n_tetrahedra

    @property
    def solved(self) -> int:
        return sum(c.solved for c in self.candidates)

    def explain(self) -> str:
        c = self.chosen
        return (f"in-plane scale {c.in_plane_scale:g}, z grading {c.first_layer_mm:.3g}–{c.max_layer_mm:.3g} mm "
                f"({c.levels} levels, {c.n_tetrahedra} tetrahedra, {self.size_ratio:.1f}x fewer than the finest): "
                f"targets within {c.error_mm:.3f} mm of the finest slab's (accuracy "
                f"{self.accuracy_mm:g} mm; {self.solved} of {len(self.candidates)} candidates solved)")


def ladder(model: Tissue, spec: SlabSpec) -> list[tuple[float, float]]:
    """(first_layer_mm, max_layer_mm) of every rung, the configured grading first; rungs that repeat one are dropped."""
    first = spec.first_layer_mm or float(np.min(model.mesh.edge_lengths()))
    cap = max(spec.height_mm, spec.max_layer_mm)
    rungs: list[tuple[float, float]] = []
    seen: set[int] = set()
    for k in range(RUNGS):
        f = min(first * 2.0 ** k, cap)
        m = min(max(spec.max_layer_mm * MAX_LAYER_GROWTH ** k, f), cap)
        levels = graded_levels(spec.height_mm, spec.layer_z_mm, f, m)[0].size
        if levels not in seen:
            seen.add(levels)
            rungs.append((f, m))
    return rungs


class _Ladder:
    """The candidates of a scene's slab (planes × z rungs, the configured one first) and their solves, on demand.

    Plane meshes are meshed once each; a slab is built and solved only when
    asked for, and its target positions (cases, P, 3) are kept.
    """

    def __init__(self, model: Tissue, spec: SlabSpec, cases: list[np.ndarray], planes):
        self.model, self.spec, self.cases = model, spec, [np.asarray(s, float) for s in cases]
        scene = model.scene
        self.points = np.array([t.rest for t in scene.targets]).reshape(-1, 2)
        self.surfaces = [(float(scale), plane_mesh(scene, model.mesh, replace(spec, plane=plane)))
                         for scale, plane in planes]
        self.rungs = ladder(model, spec)
        self.grid = [(p, z) for p in range(len(self.surfaces)) for z in range(len(self.rungs))]
        self.candidates = []
        for p, z in self.grid:
            scale, surface = self.surfaces[p]
            first, largest = self.rungs[z]
            levels = graded_levels(spec.height_mm, spec.layer_z_mm, first, largest)[0].size
            self.candidates.append(SlabCandidate(scale, first, largest, int(levels),
                                                 3 * surface.n_elements * (int(levels) - 1)))
        self.positions: dict[int, np.ndarray] = {}

    def solve(self, k: int) -> np.ndarray:
        """Candidate k's target positions (cases, P, 3) mm, solved once; records its timings."""
        if k in self.positions:
            return self.positions[k]
        c = self.candidates[k]
        p, z = self.grid[k]
        spec = replace(self.spec, first_layer_mm=c.first_layer_mm, max_layer_mm=c.max_layer_mm, plane=None)
        slab = build_slab(self.model.scene, self.surfaces[p][1], spec, model=self.model.params.model)
        probe = slab_probe(slab, self.points) if len(self.points) else layer_probe(slab, self.model.mesh)
        t0 = time.perf_counter()
        self.positions[k] = np.array([probe.positions(solve_newton(slab, s, tol=SOLVE_TOL).x) for s in self.cases])
        solve_s = time.perf_counter() - t0
        K = slab.stiffness_free(slab.rest, upper=True)
        slot: dict = {}
        factorize_free(slab, K, slot)
        t0 = time.perf_counter()
        factorize_free(slab, K, slot)  # the second: a refactorisation, as a trial's
        self.candidates[k] = replace(c, factor_s=time.perf_counter() - t0, solve_s=solve_s,
                                     n_tetrahedra=int(slab.ops.corners.shape[1]))
        return self.positions[k]

    def distance(self, a: int, b: int) -> float:
        """The largest 3-D distance (mm) of a point between candidates a and b."""
        return float(np.max(np.linalg.norm(self.solve(a) - self.solve(b), axis=-1), initial=0.0))


def choose_slab(model: Tissue, spec: SlabSpec, cases: list[np.ndarray], accuracy_mm: float,
                planes=((1.0, None),)) -> SlabChoice:
    """The coarsest candidate whose targets stay within accuracy_mm of the finest slab's (see the module doc).

    cases: the strokes (C,) mm the targets are compared at; planes: the
    in-plane ladder, (in_plane_scale, `SlabSpec.plane`) per rung, the
    configured one first (`layer3d.check.plane_ladder`); the z ladder is
    `ladder`'s. The finest slab failing (a cup that grips nothing, a solve
    that does not converge) raises: it is the configured slab.
    """
    lad = _Ladder(model, spec, cases, planes)
    order = sorted(range(1, len(lad.candidates)), key=lambda k: (lad.candidates[k].n_tetrahedra, k))
    order = [k for k in order if lad.candidates[k].n_tetrahedra < lad.candidates[0].n_tetrahedra]

    def measured(k: int) -> float | None:
        """Candidate k's error against the finest, recorded; None when k cannot be solved."""
        try:
            error = lad.distance(k, 0)
        except (BoundaryError, SolverError) as exc:  # (a cup that grips nothing on a coarse plane, say)
            c = lad.candidates[k]
            progress.info(f"slab resolution: in-plane scale {c.in_plane_scale:g}, {c.levels} levels skipped: {exc}")
            return None
        c = lad.candidates[k] = replace(lad.candidates[k], error_mm=error, reference=0)
        progress.info(f"slab resolution: in-plane scale {c.in_plane_scale:g}, z {c.first_layer_mm:.3g}–"
                      f"{c.max_layer_mm:.3g} mm, {c.levels} levels, {c.n_tetrahedra} tetrahedra: "
                      f"{error:.4f} mm from the finest, factorisation {c.factor_s:.2f} s")
        return error

    lad.solve(0)  # (raises if the configured slab cannot be solved)
    lad.candidates[0] = replace(lad.candidates[0], error_mm=0.0, reference=-1)
    for k in order:
        error = measured(k)
        if error is not None and error <= accuracy_mm:
            return SlabChoice(float(accuracy_mm), k, tuple(lad.candidates))
    return SlabChoice(float(accuracy_mm), 0, tuple(lad.candidates))


def exhaustive_errors(model: Tissue, spec: SlabSpec, cases: list[np.ndarray], planes=((1.0, None),)
                      ) -> tuple[list[SlabCandidate], np.ndarray]:
    """Every candidate solved: (candidates, each one's error against the finest (R,) mm). The full ladder, whose
    pick `choose_slab` must make; slow on a fine slab."""
    lad = _Ladder(model, spec, cases, planes)
    true = np.array([lad.distance(k, 0) for k in range(len(lad.candidates))])
    return list(lad.candidates), true
