"""Model only what a scene needs: pick element, mesh, model and solver for an accuracy budget (docs/model.md §9).

With `solver.accuracy_mm` set, `simulate` first calibrates on the scene
itself, cheaply, and then runs with the cheapest setting predicted to keep
the targets' error within the budget:

* discretisation, per element (`tissue.mesh.element`: p1 or nodal, or
  with `auto` both, docs/model.md §21): Newton with the richest model on
  the size field scaled ×4, ×2 and ×1; the observed order q of the
  successive changes of the target positions gives a Richardson estimate
  of each level's error, e(L) = d · L^q / (2^q − 1), d the change between
  levels 2 and 1 (a locking element converges slowly: its changes, and so
  its estimate, stay large);
* model: at level 2 on the first element, the distance of each simpler
  model's targets from the richest model's (taken as independent of the
  mesh and the element);
* solver: at level 2 on p1, ADMM's distance from Newton at each tolerance
  (ADMM needs every term per element: not on nodal);
* cost: per element, the measured times at levels 4, 2, 1, with the element
  count of every candidate level (meshing is cheap) and a power law in
  elements fitted to the measurements.

The predicted error of a candidate is the sum of the three; the pick is
the cheapest candidate whose prediction is within SAFETY × budget. The
case studied is the forward case with the largest stroke (or the cups'
largest stroke when the scene has none): the hardest the scene asks for.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config import Config
from scissor_cli.experiments.build import scene_of
from scissor_cli.mechanics.tissue import build_tissue
from scissor_cli.mesh.mesh import mesh_for_config
from scissor_cli.mesh.probe import probe_targets, target_positions
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.equilibrium import solve_equilibrium

SAFETY = 0.7
CALIBRATION_LEVELS = (4.0, 2.0, 1.0)
CANDIDATE_LEVELS = (4.0, 2.0, 1.0, 0.5, 0.25)
MODELS = ("linear", "neo_hookean", "neo_hookean_fiber")
#: the elements a `tissue.mesh.element` lets the selection choose among
ELEMENT_CHOICES = {"p1": ("p1",), "nodal": ("nodal",), "auto": ("p1", "nodal")}
ADMM_TOLERANCES = (1e-2, 1e-3, 1e-4, 1e-5)
ORDER_RANGE = (0.3, 2.0)


@dataclass
class Candidate:
    element: str  # "p1" | "nodal"
    level: float
    model: str
    solver: str  # "newton" | "admm"
    tolerance: float  # the solver's tolerance (Newton: its reference 1e-10)
    n_elements: int
    predicted_error_mm: float
    predicted_time_s: float


@dataclass
class Selection:
    accuracy_mm: float
    pick: Optional[Candidate]
    meets_budget: bool
    order: dict[str, float]  # per element
    discretisation_mm: dict[str, dict[float, float]]  # per element, per level
    model_mm: dict[str, float]
    solver_mm: dict[float, float]
    calibration_s: float
    case: str
    candidates: list[Candidate] = field(default_factory=list)

    def explain(self) -> str:
        p = self.pick
        head = (f"accuracy {self.accuracy_mm:g} mm: picked {p.solver}"
                + (f" (tol {p.tolerance:g})" if p.solver == "admm" else "")
                + f", {p.model}, element {p.element}, mesh level {p.level:g} ({p.n_elements} elements); predicted "
                f"error {p.predicted_error_mm:.3g} mm = mesh {self.discretisation_mm[p.element][p.level]:.3g} + model "
                f"{self.model_mm[p.model]:.3g}"
                + (f" + solver {self.solver_mm[p.tolerance]:.3g}" if p.solver == "admm" else "")
                + f", predicted {p.predicted_time_s * 1e3:.0f} ms per solve")
        why = (f"; the cheapest of {len(self.candidates)} settings within {SAFETY:g} x the budget "
               f"(calibrated on case {self.case!r} in {self.calibration_s:.1f} s, "
               "observed mesh order " + ", ".join(f"{q:.2f} ({e})" for e, q in self.order.items()) + ")")
        if not self.meets_budget:
            why = f"; NO setting is predicted to meet the budget: this is the most accurate one{why}"
        return head + why

    def for_budget(self, accuracy_mm: float) -> "Selection":
        """The same calibration, choosing for another budget."""
        pick, meets = choose(self.candidates, accuracy_mm)
        return replace(self, accuracy_mm=accuracy_mm, pick=pick, meets_budget=meets)

    def apply(self, cfg: Config) -> Config:
        """The config that runs with the picked element, mesh level, model and solver, the accuracy dropped (what
        the run records, so its trials and `--resume` rebuild what ran)."""
        p = self.pick
        tolerance = p.tolerance if p.solver == "admm" else cfg.solver.tolerance
        solver = cfg.solver.model_copy(update={"kind": p.solver, "tolerance": tolerance, "accuracy_mm": None})
        return _at_level(cfg, p.level, p.element).model_copy(update={
            "material": cfg.material.model_copy(update={"model": p.model}),
            "solver": solver,
        })


def _at_level(cfg: Config, level: float, element: str | None = None) -> Config:
    update = {"scale": cfg.tissue.mesh.scale * level}
    if element is not None:
        update["element"] = element
    mesh = cfg.tissue.mesh.model_copy(update=update)
    return cfg.model_copy(update={"tissue": cfg.tissue.model_copy(update={"mesh": mesh})})


def resolved_by_selection(cfg: Config) -> tuple[Config, Optional["Selection"]]:
    """The config a run computes on, and what `solver.accuracy_mm` picked (None without it: cfg itself)."""
    if cfg.solver.accuracy_mm is None:
        return cfg, None
    selection = select(cfg, cfg.solver.accuracy_mm)
    return selection.apply(cfg), selection


def hardest_case(cfg: Config, scene) -> tuple[str, np.ndarray]:
    if cfg.forward:
        case = max(cfg.forward, key=lambda c: float(np.abs(scene.strokes_vector(c.strokes)).max(initial=0.0)))
        return case.name, scene.strokes_vector(case.strokes)
    strokes = np.array([c.stroke_max_mm if abs(c.stroke_max_mm) >= abs(c.stroke_min_mm) else c.stroke_min_mm
                        for c in scene.cups])
    return "largest stroke", strokes


def _timed(fn, repeats: int = 1):
    """fn's result and its fastest wall time (s) over `repeats` calls.

    Newton's calibration solves take a few ms; the first call on a new
    tissue also pays one-off work (the symbolic factorisation, first-touch
    memory) that a run's many later solves do not: timed once, it would make the
    cost law predict many times a solve's real cost.
    """
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def _admm_or_unconverged(tissue, strokes: np.ndarray, tol: float):
    """ADMM's equilibrium at tolerance tol; not converged (this tolerance is out of reach), its last iterate."""
    try:
        return solve_equilibrium(tissue, strokes, method="admm", tol=tol, max_iter=5000)
    except SolverError as exc:
        return exc.result


def select(cfg: Config, accuracy_mm: float) -> Selection:
    """Calibrate on the scene and pick the cheapest setting predicted to meet accuracy_mm."""
    t_start = time.perf_counter()
    scene = scene_of(cfg)
    if not scene.targets:
        raise ValueError("solver.accuracy_mm needs at least one target to measure the error at")
    case, strokes = hardest_case(cfg, scene)
    rest = np.array([t.rest for t in scene.targets])
    # Each level is built from the config it would run with (a circle's outline follows the mesh scale).
    scenes = {L: scene_of(_at_level(cfg, L)) for L in CANDIDATE_LEVELS}
    meshes = {L: mesh_for_config(scenes[L], _at_level(cfg, L).tissue.mesh) for L in CANDIDATE_LEVELS}
    n = {L: m.n_elements for L, m in meshes.items()}

    elements = ELEMENT_CHOICES[cfg.tissue.mesh.element]
    positions, q, disc, newton_time = {}, {}, {}, {}
    for element in elements:
        positions[element], q[element], disc[element], newton_time[element] = _calibrate(
            element, scenes, meshes, rest, strokes)
    newton_cost = {element: _cost_law(n, times) for element, times in newton_time.items()}
    first = elements[0]

    probe2 = probe_targets(meshes[2.0], rest)
    reference2 = positions[first][2.0]
    # the richest model at level 2 is the calibration's own solve: the others are measured against it
    model_err, model_time = {MODELS[-1]: 0.0}, {MODELS[-1]: 1.0}
    for model in MODELS[:-1]:
        tissue = build_tissue(scenes[2.0], meshes[2.0], model=model, element=first)
        r, t = _timed(partial(solve_equilibrium, tissue, strokes), repeats=2)
        model_err[model] = float(np.linalg.norm(target_positions(probe2, r.x) - reference2, axis=1).max())
        model_time[model] = t / newton_time[first][2.0]  # relative cost of the model
    solver_err, admm_time = {}, {}
    if "p1" in elements:
        tissue2 = build_tissue(scenes[2.0], meshes[2.0], model="neo_hookean_fiber")
        for tol in ADMM_TOLERANCES:
            r, t = _timed(partial(_admm_or_unconverged, tissue2, strokes, tol))
            ok = r is not None and r.converged
            solver_err[tol] = (float(np.linalg.norm(target_positions(probe2, r.x) - positions["p1"][2.0],
                                                    axis=1).max()) if ok else np.inf)
            admm_time[tol] = t / newton_time["p1"][2.0]  # relative to Newton at the same level

    candidates = []
    for element in elements:
        for L in CANDIDATE_LEVELS:
            for model in MODELS:
                base_t = newton_cost[element](L) * model_time[model]
                error = disc[element][L] + model_err[model]
                candidates.append(Candidate(element, L, model, "newton", 1e-10, n[L], error, base_t))
                if element != "p1":
                    continue  # ADMM's local step is one element's energy (docs/model.md §21)
                for tol in ADMM_TOLERANCES:
                    candidates.append(Candidate(element, L, model, "admm", tol, n[L], error + solver_err[tol],
                                                base_t * admm_time[tol]))
    pick, meets = choose(candidates, accuracy_mm)
    sel = Selection(accuracy_mm, pick, meets, q, disc, model_err, solver_err, time.perf_counter() - t_start, case,
                    candidates)
    progress.info(sel.explain())
    return sel


def _calibrate(element: str, scenes: dict, meshes: dict, rest: np.ndarray, strokes: np.ndarray):
    """One element's calibration: the targets (T, 2) mm at each calibration level (richest model, Newton), the
    observed order, each candidate level's Richardson error (mm) and the solves' times (s) per level."""
    positions, newton_time = {}, {}
    for L in CALIBRATION_LEVELS:
        tissue = build_tissue(scenes[L], meshes[L], model="neo_hookean_fiber", element=element)
        r, t = _timed(partial(solve_equilibrium, tissue, strokes), repeats=2)
        positions[L], newton_time[L] = target_positions(probe_targets(meshes[L], rest), r.x), t
    d1 = float(np.linalg.norm(positions[4.0] - positions[2.0], axis=1).max())
    d2 = float(np.linalg.norm(positions[2.0] - positions[1.0], axis=1).max())
    q = float(np.clip(np.log2(d1 / d2) if d2 > 0 and d1 > 0 else ORDER_RANGE[1], *ORDER_RANGE))
    disc = {L: d2 * L**q / (2**q - 1) for L in CANDIDATE_LEVELS}
    return positions, q, disc, newton_time


def _cost_law(n: dict, newton_time: dict):
    """Newton's time (s) at each candidate level: a power law in elements through the calibration levels'."""
    ns = np.array([n[L] for L in CALIBRATION_LEVELS], float)
    ts = np.array([newton_time[L] for L in CALIBRATION_LEVELS])
    b, log_a = np.polyfit(np.log(ns), np.log(ts), 1)
    b = float(np.clip(b, 1.0, 2.0))
    return lambda L: float(np.exp(log_a) * n[L] ** b)


def choose(candidates: list[Candidate], accuracy_mm: float) -> tuple[Candidate, bool]:
    """The cheapest candidate predicted within SAFETY × budget, or the most accurate (and False)."""
    ok = [c for c in candidates if c.predicted_error_mm <= SAFETY * accuracy_mm]
    if ok:
        return min(ok, key=lambda c: c.predicted_time_s), True
    return min(candidates, key=lambda c: c.predicted_error_mm), False
