"""results.h5 as CONTRACT.md lays it out.

The file is written under a temporary name and renamed when closed, so a
reader never sees half a file. A run that fails part-way still renames it,
with `status = "failed"` and the reason, keeping everything it finished.
"""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path

import h5py
import numpy as np

from scissor_cli import __version__


class ResultsFile:
    """An open results.h5 being written; use as a context manager."""

    def __init__(self, path: Path | str, config_yaml: str, seed: int):
        self.path = Path(path)
        self.tmp = self.path.with_name(self.path.name + ".tmp")
        self.h5 = h5py.File(self.tmp, "w")
        attrs = self.h5.attrs
        attrs["scissor_version"] = __version__
        attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        attrs["config_yaml"] = config_yaml
        attrs["seed"] = int(seed)
        attrs["status"] = "running"

    def __enter__(self) -> "ResultsFile":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is None:
            self.close("complete")
        else:
            self.close("failed", f"{type(exc).__name__}: {exc}" if not isinstance(exc, KeyboardInterrupt) else "interrupted")

    def close(self, status: str, reason: str = "") -> None:
        if not self.h5.id.valid:
            return
        self.h5.attrs["status"] = status
        if reason:
            self.h5.attrs["failure"] = reason
        self.h5.close()
        os.replace(self.tmp, self.path)

    def dataset(self, path: str, data, units: str | None = None, **attrs) -> h5py.Dataset:
        if path in self.h5:
            del self.h5[path]
        ds = self.h5.create_dataset(path, data=data)
        if units is not None:
            ds.attrs["units"] = units
        for key, value in attrs.items():
            ds.attrs[key] = value
        return ds

    def group(self, path: str) -> h5py.Group:
        return self.h5.require_group(path)

    def flush(self) -> None:
        self.h5.flush()


def write_model(out: ResultsFile, tissue, material_cfg) -> None:
    """/mesh, /material, /cups: what the run was computed on."""
    mesh = tissue.mesh
    out.dataset("mesh/nodes", mesh.nodes, "mm")
    out.dataset("mesh/triangles", mesh.triangles.astype(np.int64))
    out.dataset("mesh/fiber", tissue.fiber, "1")
    out.dataset("mesh/fixed_nodes", tissue.fixed_nodes.astype(np.int64))
    out.dataset("mesh/element_E_kPa", tissue.element_E_kPa, "kPa")
    out.dataset("mesh/element_obstacle", mesh.element_obstacle.astype(np.int64), description="obstacle index, -1 tissue")
    angles = mesh.angles_deg()
    out.group("mesh").attrs.update(
        {"n_nodes": mesh.n_nodes, "n_elements": mesh.n_elements, "min_angle_deg": float(angles.min())}
    )
    m = tissue.scene.material
    out.group("material").attrs.update(
        {
            "model": tissue.params.model,
            "E_kPa": m.E_kPa,
            "nu": m.nu,
            "eta_kPa": m.eta_kPa,
            "thickness_mm": tissue.ops.thickness_mm,
            "density_kg_per_mm3": m.density_kg_per_mm3,
            "fiber_tension_only": bool(m.tension_only),
            "fiber_angle_rad": m.fiber_angle_rad,
        }
    )
    for c, cup in enumerate(tissue.scene.cups):
        out.dataset(f"cups/{cup.name}/nodes", tissue.cup_nodes[c].astype(np.int64))
        out.group(f"cups/{cup.name}").attrs.update(
            {
                "axis": cup.axis,
                "contact": cup.contact,
                "radius_mm": cup.radius_mm,
                "stroke_range_mm": [cup.stroke_min_mm, cup.stroke_max_mm],
                "speed_mm_per_s": cup.speed_mm_per_s,
            }
        )


def write_target(out: ResultsFile, name: str, rest: np.ndarray, desired: np.ndarray, source: str) -> None:
    g = out.group(f"targets/{name}")
    g.attrs.update({"rest": np.asarray(rest, float), "desired": np.asarray(desired, float), "desired_source": source, "units": "mm"})


def write_forward(out: ResultsFile, case: str, strokes: dict[str, float], result, rest: np.ndarray, targets: dict[str, np.ndarray]) -> None:
    g = out.group(f"forward/{case}")
    out.group(f"forward/{case}/strokes").attrs.update({k: float(v) for k, v in strokes.items()})
    out.group(f"forward/{case}/strokes").attrs["units"] = "mm"
    out.dataset(f"forward/{case}/displacement", result.x - rest, "mm")
    for name, pos in targets.items():
        out.dataset(f"forward/{case}/targets/{name}", np.asarray(pos, float), "mm")
    g.attrs.update(
        {
            "solver": result.solver,
            "iterations": int(result.iterations),
            "time_s": float(result.time_s),
            "residual": float(result.residual),
            "converged": bool(result.converged),
            "message": result.message,
        }
    )


def write_jacobian(out: ResultsFile, name: str, J: np.ndarray, cup_names: list[str]) -> None:
    """/jacobian/<target>: (2, C) mm of target motion per mm of stroke, at rest."""
    out.dataset(f"jacobian/{name}", np.asarray(J, float), "mm/mm", columns=cup_names, rows=["x", "y"])


def write_plan(out: ResultsFile, plan, joints_note: str, robot_reachable: bool) -> None:
    """/plan/<target>: the needle plan (MODEL.md §7, §11) as attributes."""
    g = out.group(f"plan/{plan.target}")
    g.attrs.update(
        {
            "entry": np.asarray(plan.entry, float),
            "direction": np.asarray(plan.direction, float),
            "depth_mm": float(plan.depth_mm),
            "clearance_mm": float(plan.clearance_mm),
            "joints": np.asarray(plan.joints, float),
            "joints_units": "d1, d2, d3 mm; theta4 rad; d5 mm",
            "joints_note": joints_note,
            "robot_reachable": bool(robot_reachable),
            "feasible": bool(plan.feasible),
            "reason": plan.reason,
            "desired": np.asarray(plan.desired, float),
            "strokes": np.asarray(plan.strokes, float),
            "side": plan.side,
            "desired_error_mm": float(plan.desired_error_mm),
        }
    )


def allocate_trials(out: ResultsFile, names: list[str], count: int, attrs: dict) -> None:
    """/trials/<target>/...: arrays for `count` trials, filled as trials finish (done marks which)."""
    g = out.group("trials")
    g.attrs.update(attrs)
    for name in names:
        t = f"trials/{name}"
        out.dataset(f"{t}/final_error", np.full((count, 2), np.nan), "mm", description="true minus desired, x and y")
        out.dataset(f"{t}/iterations", np.full(count, -1, np.int64))
        out.dataset(f"{t}/time_s", np.full(count, np.nan), "s", description="wall time of the loop")
        out.dataset(f"{t}/corridor_clear", np.zeros(count, bool))
        out.dataset(f"{t}/clearance_mm", np.full(count, np.nan), "mm")
        out.dataset(f"{t}/correctable_mm", np.full(count, np.nan), "mm")
        out.dataset(f"{t}/uncorrectable_mm", np.full(count, np.nan), "mm")
        out.dataset(f"{t}/stop_reason", np.array([""] * count, dtype=h5py.string_dtype()))
        out.dataset(f"{t}/done", np.zeros(count, bool), description="trial finished (successfully or not)")
        out.dataset(f"{t}/failed", np.zeros(count, bool), description="trial crashed; see message")
        out.dataset(f"{t}/message", np.array([""] * count, dtype=h5py.string_dtype()))
        out.group(f"{t}/history")


def write_trial(out: ResultsFile, name: str, o) -> None:
    """Store one finished trial (a `trials.TrialOutcome`) in its target's arrays."""
    t, k = f"trials/{name}", o.trial
    h5 = out.h5
    h5[f"{t}/final_error"][k] = o.final_error
    h5[f"{t}/iterations"][k] = o.iterations
    h5[f"{t}/time_s"][k] = o.time_s
    h5[f"{t}/corridor_clear"][k] = o.corridor_clear
    h5[f"{t}/clearance_mm"][k] = o.clearance_mm
    h5[f"{t}/correctable_mm"][k] = o.correctable_mm
    h5[f"{t}/uncorrectable_mm"][k] = o.uncorrectable_mm
    h5[f"{t}/stop_reason"][k] = o.stop_reason
    h5[f"{t}/message"][k] = o.message
    h5[f"{t}/failed"][k] = not o.ok
    if o.ok:
        ds = out.dataset(f"{t}/history/{k}", o.history, "mm (time_s: s)", columns=o.history_columns)
        ds.attrs["stop_reason"] = o.stop_reason
    h5[f"{t}/done"][k] = True


def pending_trials(h5: h5py.File) -> dict[str, np.ndarray]:
    """Trials per target still to run: not done, or done but failed."""
    if "trials" not in h5:
        return {}
    return {
        name: np.flatnonzero(~g["done"][:] | g["failed"][:])
        for name, g in h5["trials"].items()
    }


def reopen(path: Path | str) -> ResultsFile:
    """Continue writing an existing results.h5 (for --resume): copied to the temporary name first."""
    import shutil

    path = Path(path)
    obj = ResultsFile.__new__(ResultsFile)
    obj.path = path
    obj.tmp = path.with_name(path.name + ".tmp")
    shutil.copyfile(path, obj.tmp)
    obj.h5 = h5py.File(obj.tmp, "r+")
    obj.h5.attrs["status"] = "running"
    return obj


def write_study(out: ResultsFile, columns: dict[str, np.ndarray], reference: dict, notes: list[str], seconds: float) -> None:
    """/study: one row per (case, mesh level, kind, model, solver, tolerance), as column datasets."""
    units = {"level": "1", "tolerance": "1", "time_s": "s", "error_discrete_mm": "mm", "error_reference_mm": "mm"}
    for name, values in columns.items():
        data = values if values.dtype.kind != "U" else np.array(values.tolist(), dtype=h5py.string_dtype())
        out.dataset(f"study/{name}", data, units.get(name))
    out.group("study").attrs.update(
        {f"reference_{k}": v for k, v in reference.items()} | {"notes": "\n".join(notes), "wall_time_s": seconds}
    )


def read_study(h5: h5py.File) -> dict[str, np.ndarray] | None:
    if "study" not in h5:
        return None
    return {name: ds[:] for name, ds in h5["study"].items()}


def write_selection(out: ResultsFile, sel) -> None:
    """/selection: what `solver.accuracy_mm` picked, why, and the calibration behind it."""
    p = sel.pick
    g = out.group("selection")
    g.attrs.update({
        "accuracy_mm": sel.accuracy_mm, "meets_budget": sel.meets_budget, "explanation": sel.explain(),
        "level": p.level, "model": p.model, "solver": p.solver, "tolerance": p.tolerance, "n_elements": p.n_elements,
        "predicted_error_mm": p.predicted_error_mm, "predicted_time_s": p.predicted_time_s,
        "observed_order": sel.order, "calibration_case": sel.case, "calibration_s": sel.calibration_s,
    })
    levels = sorted(sel.discretisation_mm)
    out.dataset("selection/discretisation_mm", np.array([sel.discretisation_mm[L] for L in levels]), "mm", levels=levels)
    out.dataset("selection/model_mm", np.array(list(sel.model_mm.values())), "mm", models=list(sel.model_mm))
    tols = sorted(sel.solver_mm)
    out.dataset("selection/admm_mm", np.array([sel.solver_mm[t] for t in tols]), "mm", tolerances=tols)
