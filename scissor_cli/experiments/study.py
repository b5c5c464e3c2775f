"""The solver study: speed against error over meshes, models and solvers (docs/model.md §9).

For every forward case it sweeps mesh level (the size field scaled) and
kind (graded or uniform), material model, and solver (Newton; ADMM at a
ladder of tolerances; ADMM with Anderson acceleration), and records for
each combination the element count, the wall time (median of repeats), the
iterations and the targets' error

* against the exact discrete solution of that mesh and model (Newton), and
* against the reference: the finest graded mesh, the richest model
  (fiber-reinforced), Newton.

Errors are the largest distance (mm) over the scene's targets.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config import Config, StudyConfig, estimate_elements
from scissor_cli.experiments.build import scene_of
from scissor_cli.mechanics.tissue import build_tissue
from scissor_cli.mesh.mesh import Mesh, mesh_for_config
from scissor_cli.mesh.probe import probe_targets, target_positions
from scissor_cli.scene.scene import Scene
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.equilibrium import EquilibriumSolver, solve_equilibrium

RICHEST = "neo_hookean_fiber"


class StudyError(ValueError):
    """The study cannot run on this scene (e.g. no targets)."""


@dataclass
class StudyRow:
    case: str
    level: float
    kind: str  # "graded" | "uniform"
    model: str
    solver: str  # "newton" | "admm" | "admm+anderson"
    tolerance: float  # NaN for Newton (its own 1e-10)
    n_elements: int
    time_s: float
    iterations: int
    converged: bool
    error_discrete_mm: float = float("nan")
    error_reference_mm: float = float("nan")
    note: str = ""


@dataclass
class StudyResult:
    rows: list[StudyRow]
    reference: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def timed(fn: Callable[[], object], repeats: int, repeat_below_s: float) -> tuple[object, float]:
    """fn's result and its median wall time; slow calls (> repeat_below_s) run once."""
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
        if times[-1] > repeat_below_s:
            break
    return result, float(np.median(times))


def mesh_variants(cfg: Config, scene: Scene, study: StudyConfig, notes: list[str]) -> list[tuple[float, str, Mesh]]:
    """(level, kind, mesh) for every level and kind the study asks for, within max_elements."""
    out = []
    kinds = ["graded"] + (["uniform"] if study.uniform else [])
    for kind in kinds:
        mesh_cfg = cfg.tissue.mesh.model_copy(update={"graded": kind == "graded"})
        for level in sorted(study.levels, reverse=True):
            # the size is estimated before meshing: skip a mesh without paying for it (and never past the budget)
            estimate = estimate_elements(cfg, scale=level * cfg.tissue.mesh.scale, graded=kind == "graded")
            if estimate > 2 * study.max_elements:
                notes.append(f"{kind} level {level:g}: about {estimate} elements > max_elements, skipped")
                continue
            mesh = mesh_for_config(scene, mesh_cfg, scale=level * cfg.tissue.mesh.scale)
            if mesh.n_elements > study.max_elements:
                notes.append(f"{kind} level {level:g}: {mesh.n_elements} elements > max_elements, skipped")
                continue
            out.append((level, kind, mesh))
    return out


def run_study(cfg: Config) -> StudyResult:
    """Sweep meshes × models × solvers for the config's forward cases."""
    study = cfg.study or StudyConfig()
    scene = scene_of(cfg)
    if not scene.targets:
        raise StudyError("the study measures target errors: the scene needs at least one target")
    cases = [c for c in cfg.forward if study.cases is None or c.name in study.cases]
    if not cases:
        raise StudyError("the study needs at least one forward case")
    notes: list[str] = []
    variants = mesh_variants(cfg, scene, study, notes)
    if not any(kind == "graded" for _, kind, _ in variants):
        raise StudyError(f"every graded mesh level has more than study.max_elements = {study.max_elements} elements")
    rest = np.array([t.rest for t in scene.targets])
    rows: list[StudyRow] = []
    finest = min(level for level, kind, _ in variants if kind == "graded")
    for level, kind, mesh in variants:
        probe = probe_targets(mesh, rest)
        for model in study.models:
            tissue = build_tissue(scene, mesh, model=model, element=cfg.tissue.mesh.element)
            for case in cases:
                strokes = scene.strokes_vector(case.strokes)
                exact = _newton_row(tissue, strokes, probe, case.name, level, kind, model, study, rows)
                if exact is not None and tissue.element.per_element and mesh.n_elements <= study.admm_max_elements:
                    for memory in [0] + ([study.anderson_memory] if study.anderson_memory else []):
                        _admm_rows(tissue, strokes, probe, exact, case.name, level, kind, model, memory, study, rows)
            progress.info(f"study: {kind} level {level:g} ({mesh.n_elements} elements), {model} done")
    reference = _fill_reference_errors(rows, finest)
    return StudyResult(rows, reference, notes)


def _newton_row(tissue, strokes, probe, case, level, kind, model, study, rows) -> Optional[np.ndarray]:
    try:
        result, t = timed(lambda: solve_equilibrium(tissue, strokes), study.repeats, study.repeat_below_s)
    except SolverError as exc:
        rows.append(StudyRow(case, level, kind, model, "newton", np.nan, tissue.mesh.n_elements, np.nan, 0, False,
                             note=str(exc)))
        return None
    positions = target_positions(probe, result.x)
    rows.append(StudyRow(case, level, kind, model, "newton", np.nan, tissue.mesh.n_elements, t, result.iterations,
                         True, 0.0, note=_encode(positions)))
    return positions


def _admm_rows(tissue, strokes, probe, exact, case, level, kind, model, memory, study, rows) -> None:
    """One ADMM run continued through the tolerance ladder: time and iterations to reach each."""
    tolerances = sorted(study.admm_tolerances, reverse=True)
    name = "admm+anderson" if memory else "admm"

    def ladder():
        t0 = time.perf_counter()
        # built inside the first solve: the factorisation is part of the cost
        solver = EquilibriumSolver(tissue, "admm", anderson_memory=memory)
        used, out = 0, []
        for tol in tolerances:
            solver.tol, solver.max_iter = tol, max(study.admm_max_iterations - used, 1)
            try:
                result = solver.solve(strokes, continue_previous=used > 0)
            except SolverError as exc:
                partial = exc.result
                if partial is None:
                    out.append((tol, time.perf_counter() - t0, used, False, None, str(exc)))
                else:
                    used += partial.iterations
                    out.append((tol, time.perf_counter() - t0, used, False, partial.x, partial.message))
                break
            used += result.iterations
            out.append((tol, time.perf_counter() - t0, used, True, result.x, result.message))
        return out

    runs = []
    for _ in range(study.repeats):
        runs.append(ladder())
        if runs[-1] and runs[-1][-1][1] > study.repeat_below_s:
            break
    for j, (tol, _, used, ok, x, message) in enumerate(runs[0]):
        t = float(np.median([run[j][1] for run in runs if len(run) > j]))
        row = StudyRow(case, level, kind, model, name, tol, tissue.mesh.n_elements, t, used, ok,
                       note="" if ok else message)
        if x is not None:
            positions = target_positions(probe, x)
            row.error_discrete_mm = float(np.linalg.norm(positions - exact, axis=1).max())
            row.note = _encode(positions) if ok else message
        rows.append(row)


def _encode(positions: np.ndarray) -> str:
    # Target positions travel in the row's note until the reference is known.
    return "pos:" + ",".join(f"{v:.17g}" for v in positions.ravel())


def _decode(note: str) -> Optional[np.ndarray]:
    if not note.startswith("pos:"):
        return None
    return np.array([float(v) for v in note[4:].split(",")]).reshape(-1, 2)


def _fill_reference_errors(rows: list[StudyRow], finest: float) -> dict[str, str]:
    """error_reference_mm of every row against the finest graded, richest-model Newton solve of its case."""
    models = {r.model for r in rows}
    ref_model = RICHEST if RICHEST in models else sorted(models)[-1]
    refs = {}
    for r in rows:
        if r.solver == "newton" and r.kind == "graded" and r.level == finest and r.model == ref_model:
            refs[r.case] = _decode(r.note)
    for r in rows:
        positions = _decode(r.note)
        if positions is not None:
            ref = refs.get(r.case)
            if ref is not None:
                r.error_reference_mm = float(np.linalg.norm(positions - ref, axis=1).max())
            r.note = ""
    return {"mesh": f"graded, level {finest:g}", "model": ref_model, "solver": "newton"}


# --------------------------------------------------------------------------
# Reading a study: the Pareto front and the cheapest setting per accuracy


def pareto_front(time_s: np.ndarray, error: np.ndarray) -> np.ndarray:
    """Indices of the rows no other row beats in both time and error, by increasing time."""
    ok = np.flatnonzero(np.isfinite(time_s) & np.isfinite(error))
    order = ok[np.lexsort((error[ok], time_s[ok]))]
    front, best = [], np.inf
    for i in order:
        if error[i] < best:
            front.append(i)
            best = error[i]
    return np.array(front, dtype=int)


def cheapest(rows: list[StudyRow], threshold_mm: float, case: Optional[str] = None) -> Optional[StudyRow]:
    """The fastest converged row whose reference error is within threshold_mm."""
    ok = [r for r in rows if r.converged and np.isfinite(r.time_s) and r.error_reference_mm <= threshold_mm
          and (case is None or r.case == case)]
    return min(ok, key=lambda r: r.time_s) if ok else None


def graded_vs_uniform(rows: list[StudyRow], threshold_mm: float) -> Optional[tuple[int, int]]:
    """Fewest elements a graded and a uniform mesh need (Newton, richest model) to reach threshold_mm, per case max."""
    models = {r.model for r in rows}
    model = RICHEST if RICHEST in models else sorted(models)[-1]
    best = {}
    for kind in ("graded", "uniform"):
        per_case = {}
        for r in rows:
            if r.solver == "newton" and r.kind == kind and r.model == model and r.error_reference_mm <= threshold_mm:
                per_case[r.case] = min(per_case.get(r.case, 10**12), r.n_elements)
        cases = {r.case for r in rows}
        if set(per_case) != cases:
            return None
        best[kind] = max(per_case.values())
    return best["graded"], best["uniform"]


COLUMNS = [f for f in StudyRow.__dataclass_fields__]


def rows_as_columns(rows: list[StudyRow]) -> dict[str, np.ndarray]:
    data = [asdict(r) for r in rows]
    return {c: np.array([d[c] for d in data]) for c in COLUMNS}


def rows_from_columns(cols: dict[str, np.ndarray]) -> list[StudyRow]:
    n = len(cols["case"])
    out = []
    for i in range(n):
        values = {}
        for c in COLUMNS:
            v = cols[c][i]
            if isinstance(v, bytes):
                v = v.decode()
            values[c] = v.item() if hasattr(v, "item") else v
        out.append(StudyRow(**values))
    return out
