"""A 3-D scene's mesh, and with `element: auto` its element, picked by accuracy: `tissue.accuracy_mm`
(docs/model.md §19, "Mesh"; §21).

Candidates are the configured size field (the finest) and coarser ones,
the smallest and largest edge times each of SCALES (the grading kept). The reference is solved first over
the forward cases (Newton to SOLVE_TOL): the configured mesh on the scene's
element, or with `auto` on `nodal`, the element that converges (p1 locks:
measured against itself it would leave out its own locking error). Then the
candidates from the coarsest up, each meshed, solved and its error measured
as the largest distance of a lesion's centre from the reference's over
every case. The first within `accuracy_mm` is the pick, so only the
candidates coarser than the pick are solved; the configured mesh is the
pick when none is within. With `auto` the element comes first: `p1` (the
cheaper: a sparser factor) when its configured mesh is within the accuracy
of the reference, else `nodal`; then that element's ladder. As with the
slab's ladder (`layer3d.resolution`) no error estimate spares the finest
solve. A coarser candidate that cannot be built (a cup smaller than the mesh at
it) or solved is skipped, with its reason recorded; the configured mesh must
build and solve (the run stops there otherwise).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from scissor_cli import progress
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.mechanics.body_tissue import build_body
from scissor_cli.mechanics.tissue import BoundaryError
from scissor_cli.mesh.body_inputs import mesh_body
from scissor_cli.mesh.probe import target_positions
from scissor_cli.scene.body_scene import build_body_scene
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.equilibrium import solve_equilibrium

#: the candidates' edge lengths over the configured ones, the configured (finest) first
SCALES = (1.0, 4.0, 2.83, 2.0, 1.41)
#: the candidates' forward solves: well below any accuracy a run asks for
SOLVE_TOL = 1e-8


@dataclass(frozen=True)
class BodyCandidate:
    """One mesh and element: its scale over the configured size field and its size; when solved its error (mm,
    the largest lesion distance from the reference's; the reference's 0) and the time of its mesh and forward
    solves (s); `skipped`: why it could not be built or solved ("" otherwise)."""

    scale: float
    element: str = "p1"
    n_tetrahedra: int = 0
    error_mm: float = -1.0
    mesh_s: float = -1.0
    solve_s: float = -1.0
    skipped: str = ""

    @property
    def solved(self) -> bool:
        return self.solve_s >= 0.0


@dataclass(frozen=True)
class BodyChoice:
    """What `tissue.accuracy_mm` picked; `candidates[0]` is the reference (the configured mesh); `element` the
    element the run computes on (the pick's)."""

    accuracy_mm: float
    pick: int
    candidates: tuple

    @property
    def chosen(self) -> BodyCandidate:
        return self.candidates[self.pick]

    @property
    def element(self) -> str:
        return self.chosen.element

    def explain(self) -> str:
        c, reference = self.chosen, self.candidates[0]
        return (f"{c.element}, edges × {c.scale:g} ({c.n_tetrahedra} tetrahedra, "
                f"{reference.n_tetrahedra / c.n_tetrahedra:.1f}x fewer than the configured mesh): lesions within "
                f"{c.error_mm:.3f} mm of the configured mesh's on {reference.element} (accuracy "
                f"{self.accuracy_mm:g} mm; {sum(x.solved for x in self.candidates)} of {len(self.candidates)} "
                "candidates solved)")


def _solve(cfg: BodyConfig, scale: float, element: str, cache: Path | None) -> tuple[BodyCandidate, np.ndarray]:
    """A candidate meshed and solved: (its record without the error, lesion positions (cases, K, 3) mm)."""
    t0 = time.perf_counter()
    scene = build_body_scene(cfg)
    mesh = mesh_body(scene, cfg.tissue.mesh, scale, cache)
    tissue = build_body(scene, mesh, element=element)
    t1 = time.perf_counter()
    probe = tissue.probe(np.array([t.rest for t in scene.targets]).reshape(-1, 3))
    ends = [target_positions(probe, solve_equilibrium(tissue, scene.strokes_vector(case.strokes),
                                                      tol=SOLVE_TOL).x) for case in cfg.forward]
    return (BodyCandidate(scale, element, mesh.n_elements, mesh_s=t1 - t0, solve_s=time.perf_counter() - t1),
            np.array(ends))


def _error(ends: np.ndarray, reference: np.ndarray) -> float:
    return float(np.max(np.linalg.norm(ends - reference, axis=-1), initial=0.0))


def choose_body_scale(cfg: BodyConfig, cache: Path | None = None) -> BodyChoice:
    """The cheapest candidate whose lesions stay within `tissue.accuracy_mm` of the reference's: the coarsest
    mesh of the scene's element, or with `element: auto` of p1 when p1 meets the accuracy on the configured
    mesh, else of nodal (the module's docstring)."""
    accuracy = cfg.tissue.accuracy_mm
    auto = cfg.tissue.mesh.element == "auto"
    first = "nodal" if auto else cfg.tissue.mesh.element
    finest, reference = _solve(cfg, SCALES[0], first, cache)
    candidates = [replace(finest, error_mm=0.0)]
    progress.info(f"mesh by accuracy: the configured mesh on {first}, {finest.n_tetrahedra} tetrahedra, solved in "
                  f"{finest.mesh_s + finest.solve_s:.1f} s")
    element = first
    if auto:  # the cheaper element where it meets the accuracy on the configured mesh
        try:
            record, ends = _solve(cfg, SCALES[0], "p1", cache)
        except SolverError as exc:  # (the mesh built on nodal: it builds on p1)
            candidates.append(BodyCandidate(SCALES[0], "p1", skipped=str(exc)))
            progress.info(f"mesh by accuracy: the configured mesh on p1: skipped ({exc})")
        else:
            candidates.append(replace(record, error_mm=_error(ends, reference)))
            progress.info(f"mesh by accuracy: the configured mesh on p1: lesions within "
                          f"{candidates[-1].error_mm:.3f} mm")
            if candidates[-1].error_mm <= accuracy:
                element = "p1"
    fallback = len(candidates) - 1 if element == "p1" else 0  # the element's configured mesh
    ladder = len(candidates)
    candidates += [BodyCandidate(s, element) for s in SCALES[1:]]
    for k in range(ladder, len(candidates)):  # coarsest first
        try:
            record, ends = _solve(cfg, candidates[k].scale, element, cache)
        except (BoundaryError, SolverError) as exc:
            candidates[k] = replace(candidates[k], skipped=str(exc))
            progress.info(f"mesh by accuracy: {element}, edges × {candidates[k].scale:g}: skipped ({exc})")
            continue
        candidates[k] = replace(record, error_mm=_error(ends, reference))
        progress.info(f"mesh by accuracy: {element}, edges × {record.scale:g}, {record.n_tetrahedra} tetrahedra: "
                      f"lesions within {candidates[k].error_mm:.3f} mm")
        if candidates[k].error_mm <= accuracy:
            return BodyChoice(accuracy, k, tuple(candidates))
    return BodyChoice(accuracy, fallback, tuple(candidates))


def resolved_by_accuracy(cfg: BodyConfig, cache: Path | None = None) -> tuple[BodyConfig, BodyChoice | None]:
    """The config a run computes on, and what `tissue.accuracy_mm` picked (None without it: cfg itself).

    The pick's element is the truth's and the model's (`tissue.mesh.element`), its scale the model's body
    (`controller.mesh_scale`; the trials' truth stays the configured mesh, docs/model.md §19, "Control"), and
    the accuracy is dropped: the config a run records, so its trials and `--resume` rebuild what ran.
    """
    if cfg.tissue.accuracy_mm is None:
        return cfg, None
    choice = choose_body_scale(cfg, cache)
    mesh = cfg.tissue.mesh.model_copy(update={"element": choice.element})
    return cfg.model_copy(update={
        "tissue": cfg.tissue.model_copy(update={"accuracy_mm": None, "mesh": mesh}),
        "controller": cfg.controller.model_copy(update={"mesh_scale": choice.chosen.scale})}), choice
