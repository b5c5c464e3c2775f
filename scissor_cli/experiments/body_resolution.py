"""A 3-D scene's mesh picked by accuracy: `tissue.accuracy_mm` (docs/model.md §19, "Mesh").

Candidates are the configured size field (the finest) and coarser ones,
every edge length times each of SCALES. The finest is solved first over
the forward cases (Newton to SOLVE_TOL); then the candidates from the
coarsest up, each meshed, solved and its error measured as the largest
distance of a lesion's centre from the finest mesh's over every case. The
first within `accuracy_mm` is the pick, so only the candidates coarser than
the pick are solved; the finest is the pick when none is within. As with
the slab's ladder (`layer3d.resolution`) no error estimate spares the
finest solve: which skin nodes a cup's patch holds changes from mesh to
mesh, so the error need not fall monotonically with the size.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from scissor_cli import progress
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.mechanics.body_tissue import build_body
from scissor_cli.mesh.body_inputs import mesh_body
from scissor_cli.mesh.probe import probe_points, target_positions
from scissor_cli.scene.body_scene import build_body_scene
from scissor_cli.solvers.equilibrium import solve_equilibrium

#: the candidates' edge lengths over the configured ones, the configured (finest) first
SCALES = (1.0, 4.0, 2.83, 2.0, 1.41)
#: the candidates' forward solves: well below any accuracy a run asks for
SOLVE_TOL = 1e-8


@dataclass(frozen=True)
class BodyCandidate:
    """One mesh: its scale over the configured size field and its size; when solved its error (mm, the largest
    lesion distance from the finest mesh's; the finest's 0) and the time of its mesh and forward solves (s)."""

    scale: float
    n_tetrahedra: int = 0
    error_mm: float = -1.0
    mesh_s: float = -1.0
    solve_s: float = -1.0

    @property
    def solved(self) -> bool:
        return self.solve_s >= 0.0


@dataclass(frozen=True)
class BodyChoice:
    """What `tissue.accuracy_mm` picked; `candidates[0]` is the configured (finest) mesh."""

    accuracy_mm: float
    pick: int
    candidates: tuple

    @property
    def chosen(self) -> BodyCandidate:
        return self.candidates[self.pick]

    def explain(self) -> str:
        c, finest = self.chosen, self.candidates[0]
        return (f"edges × {c.scale:g} ({c.n_tetrahedra} tetrahedra, {finest.n_tetrahedra / c.n_tetrahedra:.1f}x "
                f"fewer than the configured mesh): lesions within {c.error_mm:.3f} mm of the configured mesh's "
                f"(accuracy {self.accuracy_mm:g} mm; {sum(x.solved for x in self.candidates)} of "
                f"{len(self.candidates)} meshes solved)")


def _solve(cfg: BodyConfig, scale: float, cache: Path | None) -> tuple[BodyCandidate, np.ndarray]:
    """A candidate meshed and solved: (its record without the error, lesion positions (cases, K, 3) mm)."""
    t0 = time.perf_counter()
    scene = build_body_scene(cfg)
    mesh = mesh_body(scene, cfg.tissue.mesh, scale, cache)
    tissue = build_body(scene, mesh, element=cfg.tissue.mesh.element)
    t1 = time.perf_counter()
    probe = probe_points(mesh.nodes, mesh.tetrahedra, np.array([t.rest for t in scene.targets]).reshape(-1, 3))
    ends = [target_positions(probe, solve_equilibrium(tissue, scene.strokes_vector(case.strokes),
                                                      tol=SOLVE_TOL).x) for case in cfg.forward]
    return BodyCandidate(scale, mesh.n_elements, mesh_s=t1 - t0, solve_s=time.perf_counter() - t1), np.array(ends)


def choose_body_scale(cfg: BodyConfig, cache: Path | None = None) -> BodyChoice:
    """The coarsest candidate whose lesions stay within `tissue.accuracy_mm` of the configured mesh's."""
    accuracy = cfg.tissue.accuracy_mm
    finest, reference = _solve(cfg, SCALES[0], cache)
    candidates = [replace(finest, error_mm=0.0)] + [BodyCandidate(s) for s in SCALES[1:]]
    progress.info(f"mesh by accuracy: the configured mesh, {finest.n_tetrahedra} tetrahedra, solved in "
                  f"{finest.mesh_s + finest.solve_s:.1f} s")
    for k in range(1, len(SCALES)):  # coarsest first
        record, ends = _solve(cfg, SCALES[k], cache)
        error = float(np.max(np.linalg.norm(ends - reference, axis=-1), initial=0.0))
        candidates[k] = replace(record, error_mm=error)
        progress.info(f"mesh by accuracy: edges × {SCALES[k]:g}, {record.n_tetrahedra} tetrahedra: lesions within "
                      f"{error:.3f} mm")
        if error <= accuracy:
            return BodyChoice(accuracy, k, tuple(candidates))
    return BodyChoice(accuracy, 0, tuple(candidates))
