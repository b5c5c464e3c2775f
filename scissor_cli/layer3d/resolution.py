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

Each forward case is solved from rest with a factorisation slot of its
own, so its numbers do not depend on what its process solved before. That
lets the ladder run on worker processes (`run_tasks`, `--jobs`): the
finest slab's cases as separate tasks, the candidates beside them in the
same order, the workers stopped once the pick is known — the same pick and
numbers as one process.

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
from scissor_cli.solvers.equilibrium import solve_equilibrium
from scissor_cli.solvers.linear import factorize_free

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
    """The candidates of a scene's slab (planes × z rungs, the configured one first) and their solved positions.

    Plane meshes are meshed once each; a candidate's slab is built and solved
    by `solve_group` (in this process or a worker), and its target positions
    (cases, P, 3) are kept here.
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
        # k -> case -> (positions (P, 3), solve_s, factor_s, tets) or the error
        self.solved: dict[int, dict[int, object]] = {}

    def task(self, k: int, cases: list[int]) -> tuple:
        """`solve_group`'s arguments for candidate k's forward cases `cases` (indices)."""
        c = self.candidates[k]
        spec = replace(self.spec, first_layer_mm=c.first_layer_mm, max_layer_mm=c.max_layer_mm, plane=None)
        return (self.model, spec, self.surfaces[self.grid[k][0]][1], self.points, k,
                [(i, self.cases[i]) for i in cases], len(self.cases) - 1)

    def record(self, k: int, answers: list) -> None:
        self.solved.setdefault(k, {}).update(answers)

    def complete(self, k: int) -> bool:
        return len(self.solved.get(k, {})) == len(self.cases)

    def failure(self, k: int) -> Exception | None:
        return next((a for a in self.solved[k].values() if isinstance(a, Exception)), None)

    def positions(self, k: int) -> np.ndarray:
        """Candidate k's target positions (cases, P, 3) mm; records its timings on the candidate."""
        answers = [self.solved[k][i] for i in range(len(self.cases))]
        factor_s = max(a[2] for a in answers)
        self.candidates[k] = replace(self.candidates[k], solve_s=sum(a[1] for a in answers), factor_s=factor_s,
                                     n_tetrahedra=int(answers[0][3]))
        return np.array([a[0] for a in answers])

    def distance(self, a: int, b: int) -> float:
        """The largest 3-D distance (mm) of a point between solved candidates a and b."""
        return float(np.max(np.linalg.norm(self.positions(a) - self.positions(b), axis=-1), initial=0.0))


def solve_group(model: Tissue, spec: SlabSpec, surface, points: np.ndarray, k: int, cases: list,
                timed_case: int = 0) -> list:
    """One candidate's slab built and solved at some forward cases: [(k, [(case, answer), ...])] (`run_tasks`' item).

    answer: (positions (P, 3) mm, forward solve s, one refactorisation s (at case `timed_case` only, else −1),
    tetrahedra), or
    the BoundaryError / SolverError that stopped it. Each case is solved from rest with its own factorisation
    slot, so a case's numbers do not depend on which cases share its process (`--jobs` changes nothing).
    """
    try:
        slab = build_slab(model.scene, surface, spec, model=model.params.model, element=model.element.name)
    except BoundaryError as exc:
        return [(k, [(i, exc) for i, _ in cases])]
    probe = slab_probe(slab, points) if len(points) else layer_probe(slab, model.mesh)
    n_tets = int(slab.ops.corners.shape[1])
    answers = []
    for i, strokes in cases:
        t0 = time.perf_counter()
        slot: dict = {}
        try:
            x = solve_equilibrium(slab, strokes, tol=SOLVE_TOL, factors=slot).x
        except SolverError as exc:
            answers.append((i, exc))
            continue
        solve_s = time.perf_counter() - t0
        factor_s = -1.0
        if i == timed_case:  # (`_Ladder` times the last case: with --jobs the finest's first is the longest)
            K = slab.stiffness_free(slab.rest, upper=True)
            if "free" not in slot:  # (the solve's symbolic analysis is reused: a refactorisation, as a trial's)
                factorize_free(slab, K, slot)
            t0 = time.perf_counter()
            factorize_free(slab, K, slot)
            factor_s = time.perf_counter() - t0
        answers.append((i, (probe.positions(x), solve_s, factor_s, n_tets)))
    return [(k, answers)]


def in_process(fn, batches):
    """fn(*batch) for each batch in turn, here, lazily: the items of each result (`choose_slab`'s default runner)."""
    for batch in batches:
        yield from fn(*batch)


def choose_slab(model: Tissue, spec: SlabSpec, cases: list[np.ndarray], accuracy_mm: float,
                planes=((1.0, None),), run_tasks=in_process, workers: int = 1) -> SlabChoice:
    """The coarsest candidate whose targets stay within accuracy_mm of the finest slab's (see the module doc).

    cases: the strokes (C,) mm the targets are compared at; planes: the
    in-plane ladder, (in_plane_scale, `SlabSpec.plane`) per rung, the
    configured one first (`layer3d.check.plane_ladder`); the z ladder is
    `ladder`'s. The finest slab failing (a cup that grips nothing, a solve
    that does not converge) raises: it is the configured slab.

    run_tasks(fn, batches) yields the items of fn(*batch) for every batch,
    in any order (`in_process`, or worker processes: `experiments.pool.run_pool`);
    it is closed once the pick is known. With `workers` ≥ 2 the finest
    slab's cases are separate tasks, and the candidates are solved beside
    them, ahead of the finest's answer. The pick and every number are the
    same either way.
    """
    lad = _Ladder(model, spec, cases, planes)
    order = sorted(range(1, len(lad.candidates)), key=lambda k: (lad.candidates[k].n_tetrahedra, k))
    order = [k for k in order if lad.candidates[k].n_tetrahedra < lad.candidates[0].n_tetrahedra]
    every = list(range(len(cases)))
    groups = [(0, [i]) for i in every] if workers > 1 else [(0, every)]
    groups += [(k, every) for k in order]
    measured: set[int] = set()

    def pick() -> int | None:
        """The pick once the answers decide it, else None; the finest slab's failure raises."""
        if not lad.complete(0):
            return None
        if lad.failure(0) is not None:
            raise lad.failure(0)
        for k in order:
            if not lad.complete(k):
                return None
            c = lad.candidates[k]
            if lad.failure(k) is not None:  # (a cup that grips nothing on a coarse plane, say)
                if k not in measured:
                    progress.info(f"slab resolution: in-plane scale {c.in_plane_scale:g}, {c.levels} levels "
                                  f"skipped: {lad.failure(k)}")
                measured.add(k)
                continue
            if k not in measured:
                error = lad.distance(k, 0)  # (records the candidate's timings first)
                c = lad.candidates[k] = replace(lad.candidates[k], error_mm=error, reference=0)
                progress.info(f"slab resolution: in-plane scale {c.in_plane_scale:g}, z {c.first_layer_mm:.3g}–"
                              f"{c.max_layer_mm:.3g} mm, {c.levels} levels, {c.n_tetrahedra} tetrahedra: "
                              f"{c.error_mm:.4f} mm from the finest, factorisation {c.factor_s:.2f} s")
                measured.add(k)
            if lad.candidates[k].error_mm <= accuracy_mm:
                return k
        return 0

    answers = run_tasks(solve_group, [lad.task(k, ks) for k, ks in groups])
    chosen = None
    try:
        for k, solved in answers:
            lad.record(k, solved)
            chosen = pick()
            if chosen is not None:
                break
    finally:
        answers.close()
    lad.positions(0)
    lad.candidates[0] = replace(lad.candidates[0], error_mm=0.0, reference=-1)
    # (candidates solved ahead of the pick but not needed for it keep error −1: they were not compared)
    for k in order:
        if k in lad.solved and k not in measured:
            lad.candidates[k] = replace(lad.candidates[k], solve_s=-1.0, factor_s=-1.0)
    return SlabChoice(float(accuracy_mm), chosen, tuple(lad.candidates))


def exhaustive_errors(model: Tissue, spec: SlabSpec, cases: list[np.ndarray], planes=((1.0, None),)
                      ) -> tuple[list[SlabCandidate], np.ndarray]:
    """Every candidate solved: (candidates, each one's error against the finest (R,) mm). The full ladder, whose
    pick `choose_slab` must make; slow on a fine slab."""
    lad = _Ladder(model, spec, cases, planes)
    every = list(range(len(cases)))
    for k, solved in in_process(solve_group, [lad.task(k, every) for k in range(len(lad.candidates))]):
        lad.record(k, solved)
    true = np.array([lad.distance(k, 0) for k in range(len(lad.candidates))])
    return list(lad.candidates), true
