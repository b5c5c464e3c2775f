"""results.h5 as docs/contract.md#resultsh5 lays it out.

The file is written under a temporary name (`results.h5.tmp`) and renamed
when closed, so a reader never sees half a file. A run that fails part-way
still renames it, with `status = "failed"` and the reason, keeping
everything it finished.

**No non-finite number is written.** `ResultsFile` is the only way into
the file and refuses any NaN or infinity with `NonFiniteError`, naming the
dataset or attribute. A value that is absent by definition is stored as a
finite fill value, and a mask tells it apart (docs/contract.md#no-nan-fill-values):

* trials (`/trials/<target>/…`): a trial not run yet, or crashed, holds
  `FILL` (0.0) in its float arrays, `iterations` −1 and `corridor_clear`
  false; `done` and `failed` say which trials hold real numbers;
* clearances (`clearance_mm`, `closed_clearance_mm`): `FILL` where the
  clearance is undefined: no obstacle to clear (+inf in docs/model.md §7),
  or no corridor (no plan, or no entry through its side); `corridor_clear`
  is the verdict;
* `/plan/<target>`: `entry`, `direction`, `depth_mm` are `FILL` when no
  insertion was found at all (`side` is then ""); `joints` are `FILL` where
  inverse kinematics gave none (`robot_reachable` false);
* `/study/<column>` and `/selection/admm_mm`: `MISSING` (−1.0) for a
  number that was not measured (Newton has no tolerance, a failed solve no
  time or error, a tolerance ADMM did not reach). Every genuine value there
  is ≥ 0. `read_study` turns them back into NaN.

Storing a trial follows a commit order so a kill at any moment leaves the
file consistent: its `done` flag is cleared, its numbers and history are
written and flushed, and only then is `done` set and flushed again.
"""

from __future__ import annotations

import datetime as _dt
import os
import shutil
from pathlib import Path
from typing import Any, Mapping

import h5py
import numpy as np

from scissor_cli import __version__
from scissor_cli.experiments.sink import NonFiniteError

FILL = 0.0
MISSING = -1.0
TRIAL_FLOATS = ("final_error", "time_s", "clearance_mm", "correctable_mm", "uncorrectable_mm", "manipulation_miss_mm",
                "along_mm")


def check_finite(where: str, value: Any) -> None:
    """Raise NonFiniteError if `value` holds a float that is NaN or infinite."""
    if isinstance(value, (str, bytes, bool)) or value is None:
        return
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        return
    if a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
        bad = a[~np.isfinite(a)] if a.ndim else a
        count = "" if a.ndim == 0 else f" ({int(np.size(bad))} of {a.size} entries)"
        raise NonFiniteError(f"refusing to write a non-finite value to {where}: {np.ravel(bad)[0].item()}{count}")


def check_history(where: str, table: np.ndarray, columns: list[str]) -> None:
    """Raise NonFiniteError for a non-finite entry of a history table (K, n), but NaN in its `measured_*`
    columns: the one NaN a results.h5 holds, a coordinate a 3-D scene's sensor does not see (docs/contract.md)."""
    table = np.asarray(table, float)
    unseen_ok = np.array([c.startswith("measured_") for c in columns], bool) if table.ndim == 2 else None
    if unseen_ok is not None and unseen_ok.size == table.shape[1]:
        check_finite(where, np.where(np.isnan(table) & unseen_ok[None, :], 0.0, table))
    else:
        check_finite(where, table)


def filled(value: Any, fill: float = FILL) -> Any:
    """`value` with its non-finite entries replaced by `fill`: for numbers that are absent by definition."""
    a = np.asarray(value, float)
    out = np.where(np.isfinite(a), a, fill)
    return float(out) if out.ndim == 0 else out


class ResultsFile:
    """An open results.h5 being written (as results.h5.tmp); use as a context manager."""

    def __init__(self, path: Path | str, h5: h5py.File):
        self.path = Path(path)
        self.tmp = temporary(self.path)
        self.h5 = h5

    @classmethod
    def create(cls, path: Path | str, config_yaml: str, seed: int) -> "ResultsFile":
        """A new file with the provenance attributes and `status = "running"`."""
        path = Path(path)
        obj = cls(path, h5py.File(temporary(path), "w"))
        obj.attrs("/", {
            "scissor_version": __version__,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "config_yaml": config_yaml, "seed": int(seed), "status": "running",
        })
        return obj

    @classmethod
    def continue_temporary(cls, path: Path | str) -> "ResultsFile":
        """Keep writing the existing results.h5.tmp of `path` (a killed run's)."""
        path = Path(path)
        obj = cls(path, h5py.File(temporary(path), "r+"))
        obj.attrs("/", {"status": "running"})
        return obj

    def __enter__(self) -> "ResultsFile":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is None:
            self.close("complete")
        else:
            self.close("failed", failure_reason(exc))

    def close(self, status: str, reason: str = "") -> None:
        if not self.h5.id.valid:
            return
        self.h5.attrs["status"] = status
        if reason:
            self.h5.attrs["failure"] = reason
        self.h5.close()
        os.replace(self.tmp, self.path)

    def dataset(self, path: str, data, units: str | None = None, **attrs) -> h5py.Dataset:
        if "columns" in attrs and "/history" in path:  # a history: unseen measured coordinates may be NaN
            check_history(f"/{path}", data, list(attrs["columns"]))
        else:
            check_finite(f"/{path}", data)
        if path in self.h5:
            del self.h5[path]
        ds = self.h5.create_dataset(path, data=data)
        self.attrs(path, ({"units": units} if units is not None else {}) | attrs)
        return ds

    def attrs(self, path: str, values: Mapping[str, Any]) -> None:
        """Set attributes of the group or dataset at `path` (a group is created if missing)."""
        for key, value in values.items():
            check_finite(f"{'/' + path.strip('/') if path.strip('/') else ''}@{key}", value)
        target = self.h5[path] if path in self.h5 else self.h5.require_group(path)
        target.attrs.update(values)

    def put(self, path: str, index: int, value) -> None:
        """Write one entry of an existing dataset."""
        check_finite(f"/{path}[{index}]", value)
        self.h5[path][index] = value

    def group(self, path: str) -> h5py.Group:
        return self.h5.require_group(path)

    def flush(self) -> None:
        self.h5.flush()


def temporary(path: Path) -> Path:
    """Where results.h5 is written until it is closed."""
    return path.with_name(path.name + ".tmp")


def failure_reason(exc: BaseException) -> str:
    if isinstance(exc, KeyboardInterrupt):  # Ctrl-C: "interrupted"; a termination signal: "interrupted (SIGTERM)"
        return "interrupted" + (f" ({exc.args[0]})" if exc.args and exc.args[0] not in ("", "SIGINT") else "")
    return f"{type(exc).__name__}: {exc}"


def reopen(path: Path | str) -> ResultsFile:
    """Continue writing a closed results.h5 (for --resume): copied to the temporary name first."""
    path = Path(path)
    shutil.copyfile(path, temporary(path))
    return ResultsFile.continue_temporary(path)


def write_model(out: ResultsFile, tissue) -> None:
    """/mesh, /material, /cups: what the run was computed on."""
    mesh = tissue.mesh
    out.dataset("mesh/nodes", mesh.nodes, "mm")
    out.dataset("mesh/triangles", mesh.triangles.astype(np.int64))
    out.dataset("mesh/fiber", tissue.fiber, "1")
    out.dataset("mesh/fixed_nodes", tissue.fixed_nodes.astype(np.int64))
    out.dataset("mesh/element_E_kPa", tissue.element_E_kPa, "kPa")
    out.dataset("mesh/element_obstacle", mesh.element_obstacle.astype(np.int64),
                description="obstacle index, -1 tissue")
    angles = mesh.angles_deg()
    out.attrs("mesh", {"n_nodes": mesh.n_nodes, "n_elements": mesh.n_elements, "min_angle_deg": float(angles.min()),
                       "element": tissue.element.name,
                       "nodes_per_element": tissue.element.nodes_per_element})
    m = tissue.scene.material
    out.attrs("material", {
        "model": tissue.params.model, "E_kPa": m.E_kPa, "nu": m.nu, "eta_kPa": m.eta_kPa,
        "thickness_mm": tissue.ops.thickness_mm, "density_kg_per_mm3": m.density_kg_per_mm3,
        "fiber_tension_only": bool(m.tension_only), "fiber_angle_rad": m.fiber_angle_rad,
    })
    for c, cup in enumerate(tissue.scene.cups):
        out.dataset(f"cups/{cup.name}/nodes", tissue.cup_nodes[c].astype(np.int64))
        out.attrs(f"cups/{cup.name}", {
            "axis": cup.axis, "contact": cup.contact, "radius_mm": cup.radius_mm,
            "stroke_range_mm": [cup.stroke_min_mm, cup.stroke_max_mm], "speed_mm_per_s": cup.speed_mm_per_s,
        })


def write_target(out: ResultsFile, name: str, rest: np.ndarray, desired: np.ndarray, source: str) -> None:
    out.attrs(f"targets/{name}", {"rest": np.asarray(rest, float), "desired": np.asarray(desired, float),
                                  "desired_source": source, "units": "mm"})


def write_forward(out: ResultsFile, case: str, strokes: dict[str, float], result, rest: np.ndarray,
                  targets: dict[str, np.ndarray]) -> None:
    out.group(f"forward/{case}")
    out.attrs(f"forward/{case}/strokes", {k: float(v) for k, v in strokes.items()} | {"units": "mm"})
    out.dataset(f"forward/{case}/displacement", result.x - rest, "mm")
    for name, pos in targets.items():
        out.dataset(f"forward/{case}/targets/{name}", np.asarray(pos, float), "mm")
    out.attrs(f"forward/{case}", {
        "solver": result.solver, "iterations": int(result.iterations), "time_s": float(result.time_s),
        "residual": float(result.residual), "converged": bool(result.converged), "message": result.message,
    })


def write_jacobian(out: ResultsFile, name: str, J: np.ndarray, cup_names: list[str]) -> None:
    """/jacobian/<target>: (d, C) mm of target motion per mm of stroke, at rest (d = 2, or 3 in a body)."""
    J = np.asarray(J, float)
    out.dataset(f"jacobian/{name}", J, "mm/mm", columns=cup_names, rows=["x", "y", "z"][:J.shape[0]])


def clearance(value: float) -> float:
    """A clearance (mm) as stored: `FILL` where it is undefined (no obstacles: +inf; no corridor: NaN)."""
    return filled(value)


def write_plan(out: ResultsFile, plan, joints_note: str, robot_reachable: bool) -> None:
    """/plan/<target>: the needle plan (docs/model.md §7, §11) as attributes, absent values filled."""
    no_insertion = not plan.side
    geometry = (lambda v: filled(v)) if no_insertion else (lambda v: np.asarray(v, float))
    joints = np.asarray(plan.joints, float)
    out.attrs(f"plan/{plan.target}", {
        "entry": geometry(plan.entry),
        "direction": geometry(plan.direction),
        "depth_mm": float(geometry(plan.depth_mm)),
        "clearance_mm": clearance(plan.clearance_mm),
        "joints": joints if robot_reachable else filled(joints),
        "joints_units": "d1, d2, d3 mm; theta4 rad; d5 mm",
        "joints_note": joints_note,
        "robot_reachable": bool(robot_reachable),
        "feasible": bool(plan.feasible),
        "reason": plan.reason,
        "desired": np.asarray(plan.desired, float),
        "strokes": np.asarray(plan.strokes, float),
        "side": plan.side,
        "desired_error_mm": float(plan.desired_error_mm),
        **{name: np.asarray(value, float)
           for name, value in (("model_strokes", plan.model_strokes), ("slab_strokes", plan.slab_strokes))
           if value is not None},
        **({} if plan.model_error_mm is None else {"model_error_mm": float(plan.model_error_mm)}),
    })


def write_manipulation(out: ResultsFile, target: str, closed, opened) -> None:
    """/manipulation/<target>: the nominal closed loop against the open-loop baseline, and its history."""
    out.attrs(f"manipulation/{target}", {
        "closed_final_error": closed.final_error, "closed_iterations": closed.iterations,
        "closed_stop_reason": closed.stop_reason, "closed_corridor_clear": bool(closed.corridor_clear),
        "closed_clearance_mm": clearance(closed.clearance_mm), "open_final_error": opened.final_error,
        "uncorrectable_mm": closed.uncorrectable_error_mm, "units": "mm",
        "closed_miss_mm": closed.miss_mm, "closed_along_mm": closed.along_error_mm, "open_miss_mm": opened.miss_mm,
        "error": closed.error_mode,
    })
    names, table = closed.history_table()
    out.dataset(f"manipulation/{target}/history", table, "mm (time_s: s)", columns=names)


TRIALS_FILL_NOTE = ("not done or crashed (see done, failed): final_error, time_s, trial_time_s, clearance_mm, "
                    "correctable_mm, uncorrectable_mm, manipulation_miss_mm, along_mm 0, iterations -1; clearance_mm "
                    "is also 0 where undefined (no obstacles, no corridor)")


def allocate_trials(out: ResultsFile, names: list[str], count: int, attrs: dict, dim: int = 2) -> None:
    """/trials/<target>/...: arrays for `count` trials holding the fill values, filled as trials finish; dim = 3
    for a 3-D scene's (x, y, z)."""
    out.attrs("trials", attrs | {"fill_values": TRIALS_FILL_NOTE})
    for name in names:
        t = f"trials/{name}"
        out.dataset(f"{t}/final_error", np.full((count, dim), FILL), "mm",
                    description="true minus desired, x and y" + (" and z" if dim == 3 else ""))
        out.dataset(f"{t}/iterations", np.full(count, -1, np.int64))
        out.dataset(f"{t}/time_s", np.full(count, FILL), "s", description="wall time of the loop")
        out.dataset(f"{t}/trial_time_s", np.full(count, FILL), "s",
                    description="wall time of the whole trial: the loop and every strategy's insertion")
        out.dataset(f"{t}/corridor_clear", np.zeros(count, bool))
        out.dataset(f"{t}/clearance_mm", np.full(count, FILL), "mm")
        out.dataset(f"{t}/correctable_mm", np.full(count, FILL), "mm")
        out.dataset(f"{t}/uncorrectable_mm", np.full(count, FILL), "mm")
        out.dataset(f"{t}/manipulation_miss_mm", np.full(count, FILL), "mm",
                    description="after the loop: true target's distance across the plan's needle axis")
        out.dataset(f"{t}/along_mm", np.full(count, FILL), "mm",
                    description="after the loop: desired minus true along the needle axis, left to the depth")
        out.dataset(f"{t}/stop_reason", np.array([""] * count, dtype=h5py.string_dtype()))
        out.dataset(f"{t}/done", np.zeros(count, bool), description="trial finished (successfully or not)")
        out.dataset(f"{t}/failed", np.zeros(count, bool), description="trial crashed; see message")
        out.dataset(f"{t}/message", np.array([""] * count, dtype=h5py.string_dtype()))
        out.group(f"{t}/history")
        if attrs.get("sensor") == "ultrasound":
            out.dataset(f"{t}/frames", np.zeros(count, np.int64), description="ultrasound frames the trial formed")
            out.dataset(f"{t}/lost_frames", np.zeros(count, np.int64),
                        description="frames on which the tracking lost the lesion (the last position kept)")
        strategies = list(attrs.get("insertion_strategies", []))
        if strategies:
            out.dataset(f"{t}/miss_mm", np.full((count, len(strategies)), FILL), "mm", strategies=strategies,
                        description="final miss at the needle (target to the needle line) per strategy")
            out.dataset(f"{t}/depth_error_mm", np.full((count, len(strategies)), FILL), "mm", strategies=strategies,
                        description="final tip minus target along the needle per strategy")


def mark_without_plan(out: ResultsFile, name: str, reason: str) -> None:
    """A target with no plan has nothing to manipulate towards: its trials are done, with stop_reason no_plan."""
    t = f"trials/{name}"
    out.h5[f"{t}/done"][:] = True
    out.h5[f"{t}/stop_reason"][:] = "no_plan"
    out.h5[f"{t}/message"][:] = f"no plan: {reason}"


def trial_record(name: str, o) -> dict:
    """One finished trial (a `trials.TrialOutcome`) as the plain values stored, checked finite.

    A crashed trial's numbers are replaced by the fill values; the history
    is stored only for a trial that ran to its end.
    """
    ok = bool(o.ok)
    rec = {
        "target": name, "trial": int(o.trial), "ok": ok, "message": str(o.message), "stop_reason": str(o.stop_reason),
        "final_error": np.asarray(o.final_error, float) if ok else np.zeros(np.size(o.final_error) or 2),
        "iterations": int(o.iterations) if ok else -1,
        "time_s": float(o.time_s) if np.isfinite(o.time_s) else FILL,
        "trial_time_s": float(o.trial_time_s) if np.isfinite(o.trial_time_s) else FILL,
        "corridor_clear": bool(o.corridor_clear) and ok,
        "clearance_mm": clearance(o.clearance_mm) if ok else FILL,
        "correctable_mm": float(o.correctable_mm) if ok else FILL,
        "uncorrectable_mm": float(o.uncorrectable_mm) if ok else FILL,
        "manipulation_miss_mm": float(getattr(o, "miss_mm", FILL)) if ok else FILL,
        "along_mm": float(getattr(o, "along_mm", FILL)) if ok else FILL,
        "frames": int(getattr(o, "frames", 0)) if ok else 0,
        "lost_frames": int(getattr(o, "lost_frames", 0)) if ok else 0,
        "history_columns": [str(c) for c in o.history_columns] if ok else [],
        "history": np.asarray(o.history, float) if ok else np.zeros((0, 0)),
    }
    miss = np.asarray(getattr(o, "insertion_miss_mm", np.zeros(0)), float)
    if miss.size:  # with insertion: per strategy; a crashed trial keeps the fill values
        rec["miss_mm"] = miss if ok else np.zeros_like(miss)
        rec["depth_error_mm"] = np.asarray(o.insertion_depth_error_mm, float) if ok else np.zeros_like(miss)
    where = f"/trials/{name}/{{}} (trial {rec['trial']})"
    for key in TRIAL_FLOATS:
        check_finite(where.format(key), rec[key])
    check_history(where.format(f"history/{rec['trial']}"), rec["history"], rec["history_columns"])
    for key in ("miss_mm", "depth_error_mm"):
        if key in rec:
            check_finite(where.format(key), rec[key])
    return rec


def write_trial(out: ResultsFile, rec: dict) -> None:
    """Store one trial record (`trial_record`) with the commit order of the module docstring."""
    t, k = f"trials/{rec['target']}", rec["trial"]
    if out.h5[f"{t}/done"][k]:  # a crashed trial run again: not done until the new numbers are all in
        out.put(f"{t}/done", k, False)
        out.flush()
    for key in TRIAL_FLOATS + ("iterations", "corridor_clear", "stop_reason", "message"):
        out.put(f"{t}/{key}", k, rec[key])
    for key in ("miss_mm", "depth_error_mm", "frames", "lost_frames", "trial_time_s"):  # (a run begun without them)
        if key in rec and f"{t}/{key}" in out.h5:
            out.put(f"{t}/{key}", k, rec[key])
    out.put(f"{t}/failed", k, not rec["ok"])
    if rec["ok"]:
        out.dataset(f"{t}/history/{k}", rec["history"], "mm (time_s: s)", columns=rec["history_columns"],
                    stop_reason=rec["stop_reason"])
    out.flush()
    out.put(f"{t}/done", k, True)
    out.flush()


def finished_trials(g: h5py.Group) -> np.ndarray:
    """(T,) bool: the trials of one `/trials/<target>` group that ran to the end (not failed; a target
    without a plan runs none: its trials are marked done with stop_reason `no_plan` and zeros)."""
    ok = g["done"][:] & ~g["failed"][:]
    if "stop_reason" in g:
        ok &= g["stop_reason"].asstr()[:] != "no_plan"
    return ok


def pending_trials(h5: h5py.File) -> dict[str, np.ndarray]:
    """Trials per target still to run: not done, or done but failed."""
    if "trials" not in h5:
        return {}
    return {name: np.flatnonzero(~g["done"][:] | g["failed"][:]) for name, g in h5["trials"].items()}


def write_study(out: ResultsFile, columns: dict[str, np.ndarray], reference: dict, notes: list[str],
                seconds: float) -> None:
    """/study: one row per (case, mesh level, kind, model, solver, tolerance), as column datasets.

    A number that was not measured (NaN in the rows) is stored as `MISSING`.
    """
    units = {"level": "1", "tolerance": "1", "time_s": "s", "error_discrete_mm": "mm", "error_reference_mm": "mm"}
    for name, values in columns.items():
        if values.dtype.kind == "U":
            data = np.array(values.tolist(), dtype=h5py.string_dtype())
        elif values.dtype.kind == "f":
            data = np.where(np.isnan(values), MISSING, values)
        else:
            data = values
        out.dataset(f"study/{name}", data, units.get(name))
    out.attrs("study", {f"reference_{k}": v for k, v in reference.items()}
              | {"notes": "\n".join(notes), "wall_time_s": seconds, "missing_value": "-1: not measured"})


def read_study(h5: h5py.File) -> dict[str, np.ndarray] | None:
    """The /study columns, with the numbers that were not measured as NaN again."""
    if "study" not in h5:
        return None
    out = {}
    for name, ds in h5["study"].items():
        data = ds[:]
        if data.dtype.kind == "f":
            data = np.where(data == MISSING, np.nan, data)
        out[name] = data
    return out


def write_selection(out: ResultsFile, sel) -> None:
    """/selection: what `solver.accuracy_mm` picked, why, and the calibration behind it (docs/model.md §9)."""
    p = sel.pick
    out.attrs("selection", {
        "accuracy_mm": sel.accuracy_mm, "meets_budget": sel.meets_budget, "explanation": sel.explain(),
        "element": p.element, "level": p.level, "model": p.model, "solver": p.solver, "tolerance": p.tolerance,
        "n_elements": p.n_elements, "predicted_error_mm": p.predicted_error_mm, "predicted_time_s": p.predicted_time_s,
        "observed_order": sel.order[p.element], "calibration_case": sel.case, "calibration_s": sel.calibration_s,
    })
    elements = list(sel.discretisation_mm)
    levels = sorted(sel.discretisation_mm[p.element])
    out.dataset("selection/discretisation_mm", np.array([sel.discretisation_mm[p.element][L] for L in levels]), "mm",
                levels=levels, element=p.element)
    out.dataset("selection/element_discretisation_mm",
                np.array([[sel.discretisation_mm[e][L] for L in levels] for e in elements]), "mm", levels=levels,
                elements=elements, observed_orders=[sel.order[e] for e in elements])
    out.dataset("selection/model_mm", np.array(list(sel.model_mm.values())), "mm", models=list(sel.model_mm))
    tols = sorted(sel.solver_mm)
    out.dataset("selection/admm_mm", filled([sel.solver_mm[t] for t in tols], MISSING), "mm", tolerances=tols,
                missing_value="-1: ADMM did not reach this tolerance")


def write_slab_resolution(out: ResultsFile, choice) -> None:
    """/layer_check_resolution: the slabs (in-plane scale, z grading) `layer_check.accuracy_mm` tried and the one it
    picked (docs/model.md §13)."""
    c = choice.chosen
    out.attrs("layer_check_resolution", {
        "accuracy_mm": choice.accuracy_mm, "explanation": choice.explain(), "in_plane_scale": c.in_plane_scale,
        "first_layer_mm": c.first_layer_mm,
        "max_layer_mm": c.max_layer_mm, "levels": c.levels, "n_tetrahedra": c.n_tetrahedra, "error_mm": c.error_mm,
        "size_ratio": choice.size_ratio, "pick": choice.pick, "solved": choice.solved,
        "missing_value": "-1: not solved (error_mm -1: solved as a reference only)",
    })
    rows = choice.candidates
    for name, unit in (("in_plane_scale", "1"), ("first_layer_mm", "mm"), ("max_layer_mm", "mm"), ("levels", "1"),
                       ("n_tetrahedra", "1"), ("error_mm", "mm"), ("factor_s", "s"), ("solve_s", "s"),
                       ("reference", "1")):
        out.dataset(f"layer_check_resolution/{name}", np.array([getattr(r, name) for r in rows]), unit)
