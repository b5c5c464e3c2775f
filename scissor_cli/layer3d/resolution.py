"""The slab's resolution by accuracy: `layer_check.accuracy_mm` (docs/model.md §13, "Resolution by accuracy").

The slab's cost is its size: every prism layer copies the whole 2-D mesh,
and a sparse Cholesky factor of a 3-D mesh grows faster than its unknowns
(halving the levels or coarsening the plane divides a factorisation's time
several times over; benchmarks/bench_slab_truth.py). A run that only needs its
targets to a tolerance can use a coarser slab, and the slab-truth trials
factor it dozens of times per trial.

Candidates are the product of two ladders, the configured slab (the
finest) first:

* z gradings: the thinnest layer `first_layer_mm` at the layer (default
  the 2-D mesh's finest edge) doubling per rung and the thickest
  (`max_layer_mm`) growing by 1.6;
* in-plane meshes: the slab's 2-D mesh `in_plane_scale` times the
  configured one's, for each of IN_PLANE_SCALES (`tissue.mesh`'s edge
  lengths scaled: still finest at targets, obstacles and cups).

Each candidate solves the forward cases (Newton to 1e-8); its error is the
largest 3-D distance of a target (without targets: of a layer node) from
the finest slab's. The pick is the candidate with the fewest tetrahedra
within `accuracy_mm`, the finest when none other is. The error is not
monotone along either ladder — which nodes a cup grips within its radius
changes with the levels next to the layer and with the side's nodes — so
every candidate is solved, not only until the first miss.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from scissor_cli import progress
from scissor_cli.geometry import graded_levels
from scissor_cli.layer3d.slab import SlabSpec, build_slab, layer_probe, plane_mesh, slab_probe
from scissor_cli.mechanics.tissue import Tissue
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
    """One slab: its 2-D mesh scale and z layers (mm), size, largest target error against the finest (mm), one
    refactorisation (s)."""

    in_plane_scale: float
    first_layer_mm: float
    max_layer_mm: float
    levels: int
    n_tetrahedra: int
    error_mm: float
    factor_s: float
    solve_s: float


@dataclass(frozen=True)
class SlabChoice:
    """What `layer_check.accuracy_mm` picked; `candidates[0]` is the configured (finest) grading."""

    accuracy_mm: float
    pick: int
    candidates: tuple

    @property
    def chosen(self) -> SlabCandidate:
        return self.candidates[self.pick]

    @property
    def speed_up(self) -> float:
        """The finest slab's refactorisation time over the chosen one's."""
        return self.candidates[0].factor_s / self.chosen.factor_s

    def explain(self) -> str:
        c = self.chosen
        return (f"in-plane scale {c.in_plane_scale:g}, z grading {c.first_layer_mm:.3g}–{c.max_layer_mm:.3g} mm "
                f"({c.levels} levels, {c.n_tetrahedra} "
                f"tetrahedra): targets within {c.error_mm:.3f} mm of the finest slab's (accuracy {self.accuracy_mm:g} "
                f"mm), factorisation {self.speed_up:.1f}x faster")


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


def choose_slab(model: Tissue, spec: SlabSpec, cases: list[np.ndarray], accuracy_mm: float,
                planes=((1.0, None),)) -> SlabChoice:
    """Solve the forward cases' strokes (each (C,) mm) on every candidate and pick the smallest within accuracy_mm.

    planes: the in-plane ladder, (in_plane_scale, `SlabSpec.plane`) per rung, the configured one first
    (`layer3d.check.plane_ladder`); the z ladder is `ladder`'s.
    """
    scene, mesh = model.scene, model.mesh
    points = np.array([t.rest for t in scene.targets]).reshape(-1, 2)
    reference, candidates = None, []
    for scale, plane in planes:
        surface = plane_mesh(scene, mesh, replace(spec, plane=plane))  # meshed once for all its z rungs
        for first, largest in ladder(model, spec):
            candidate_spec = replace(spec, first_layer_mm=first, max_layer_mm=largest, plane=None)
            slab = build_slab(scene, surface, candidate_spec, model=model.params.model)
            probe = slab_probe(slab, points) if len(points) else layer_probe(slab, mesh)
            t0 = time.perf_counter()
            positions = np.array([probe.positions(solve_newton(slab, np.asarray(strokes, float), tol=SOLVE_TOL).x)
                                  for strokes in cases])
            solve_s = time.perf_counter() - t0
            reference = positions if reference is None else reference
            error = float(np.max(np.linalg.norm(positions - reference, axis=-1)))
            K = slab.stiffness_free(slab.rest, upper=True)
            slot: dict = {}
            factorize_free(slab, K, slot)
            t0 = time.perf_counter()
            factorize_free(slab, K, slot)
            factor_s = time.perf_counter() - t0
            c = SlabCandidate(float(scale), first, largest, int(slab.mesh.levels_mm.size),
                              int(slab.ops.corners.shape[1]), error, factor_s, solve_s)
            candidates.append(c)
            progress.info(f"slab resolution: in-plane scale {scale:g}, z {first:.3g}–{largest:.3g} mm, {c.levels} levels, "
                 f"{c.n_tetrahedra} tetrahedra: target error {error:.4f} mm, factorisation {factor_s:.2f} s")
    within = [k for k, c in enumerate(candidates) if c.error_mm <= accuracy_mm]
    pick = min(within, key=lambda k: (candidates[k].n_tetrahedra, k))
    return SlabChoice(float(accuracy_mm), pick, tuple(candidates))
