"""The run sink of `scissor simulate`: results.h5, the trial journal and the figures of a run directory.

`RunDirectory(out).open(...)` is the sink of a new run and
`open_for_resume(run_dir)` the sink that finishes a stored one; both
implement `experiments.sink.RunSink`, and `cli.py` hands them to the
pipeline. What goes where is docs/contract.md#resultsh5 and #figures.

How a run survives a kill (docs/contract.md#resume):

* results.h5 is written as `results.h5.tmp` (default HDF5 format, readable
  by any HDF5 ≥ 1.8), flushed after every stage and trial, each trial in the
  commit order of `results.write_trial`;
* each trial is first appended to `results.h5.journal` (`journal.py`),
  which a kill can only cut at its last record;
* every other stage product (a forward case, a layer check, the plans, a
  target's manipulation or insertions) is marked finished in the root
  attribute `finished` once it and its figure are stored, so `--resume`
  redoes only what is not marked;
* `--resume` continues `results.h5.tmp` when a killed run left one and it
  reads back whole; otherwise it falls back to `results.h5` (the state
  before the last resume) and says what was lost; and if no HDF5 file can
  be trusted it starts a fresh one, so the pipeline redoes the stages before
  the trials. In every case it then restores from the journal each trial the
  file lacks, so no finished trial is computed twice.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import h5py
import numpy as np

from scissor_cli.experiments import run_cache
from scissor_cli.experiments.sink import ForwardCase, Manipulation, ResumeError, product_key
from scissor_cli.experiments.study import rows_as_columns
from scissor_cli.output import figures, journal, layer_check, results
from scissor_cli.output.error_budget import results as budget_results
from scissor_cli.output.error_budget.figures import budget_figure
from scissor_cli.output.insertion.results import write_insertion, write_needle_model
from scissor_cli.output.manipulation import manipulation_figure_inputs
from scissor_cli.output.results import ResultsFile, temporary

#: root attribute: the `product_key`s of what the run stored whole (docs/contract.md#resume)
FINISHED = "finished"


class ResultsSink:
    """A run directory being written: implements `experiments.sink.RunSink` (and `ResumableSink`)."""

    def __init__(self, out: ResultsFile, *, trials_journal: Optional[journal.Journal] = None,
                 replay: list[dict] = (), notes: list[str] = (), rebuilt: bool = False):
        self.out = out
        self.location = out.path.parent
        self.config_yaml = str(out.h5.attrs["config_yaml"])
        self._journal = trials_journal
        self._replay = list(replay)
        self._notes = list(notes)
        self._rebuilt = rebuilt

    # -- the run's life ----------------------------------------------------
    def __enter__(self) -> "ResultsSink":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.out.__exit__(exc_type, exc, tb)
        if self._journal is not None:
            if exc is None:  # every trial is in the renamed results.h5 now
                self._journal.remove()
            else:  # kept: --resume restores from it what the file may lack
                self._journal.close()

    def notes(self) -> list[str]:
        return list(self._notes)

    def plans(self) -> Optional[dict[str, dict]]:
        if self._rebuilt or "plan" not in self.out.h5:
            return None
        return {name: dict(g.attrs) for name, g in self.out.h5["plan"].items()}

    def finished(self) -> frozenset[str]:
        h5 = self.out.h5
        if self._rebuilt:
            return frozenset()
        if FINISHED in h5.attrs:
            return frozenset(h5.attrs[FINISHED].astype(str).tolist()) if len(h5.attrs[FINISHED]) else frozenset()
        # A file from before the marks (scissor 0.2.0) was resumable only once its trials were allocated,
        # and then every stage before them had finished.
        if "trials" not in h5 or "plan" not in h5:
            return frozenset()
        keys = {"model", "jacobian", "study", "plan", "trials"}
        for stage in ("forward", "layer_check", "manipulation", "insertion"):
            keys |= {product_key(stage, name) for name in h5.get(stage, {}) if stage != "layer_check" or name != "mesh"}
        return frozenset(keys)

    def mark_finished(self, key: str) -> None:
        self.out.h5.attrs[FINISHED] = np.array(sorted(self.finished() | {key}), dtype=h5py.string_dtype())
        self.out.flush()

    # -- the stages --------------------------------------------------------
    def model(self, tissue) -> None:
        if tissue.dim == 3:
            from scissor_cli.output.body.results import write_body_model  # noqa: PLC0415

            write_body_model(self.out, tissue)
        else:
            results.write_model(self.out, tissue)
        self.out.flush()

    def target(self, name: str, rest: np.ndarray, desired: np.ndarray, source: str) -> None:
        results.write_target(self.out, name, rest, desired, source)
        self.out.flush()

    def body_resolution(self, choice) -> None:
        from scissor_cli.output.body.results import write_body_resolution  # noqa: PLC0415

        write_body_resolution(self.out, choice)
        self.out.flush()

    def selection(self, selection) -> None:
        results.write_selection(self.out, selection)
        self.out.flush()

    def slab_resolution(self, choice) -> None:
        results.write_slab_resolution(self.out, choice)
        self.out.flush()

    def forward_case(self, case: ForwardCase) -> Path | list[Path]:
        results.write_forward(self.out, case.name, case.strokes, case.result, case.rest, case.targets)
        self.out.flush()
        if case.kind == "body":
            from scissor_cli.output.body.figures import body_figures  # noqa: PLC0415

            section, view = body_figures(**case.figure)
            return [figures.save(section, self.location / f"forward_{case.name}.png"),
                    figures.save(view, self.location / f"forward_{case.name}_3d.png")]
        return figures.save(figures.forward_case_figure(**case.figure), self.location / f"forward_{case.name}.png")

    def layer_check_mesh(self, mesh) -> None:
        layer_check.write_layer_check_mesh(self.out, mesh.nodes, mesh.tetrahedra, mesh.levels_mm, mesh.layer_level)
        self.out.flush()

    def layer_check(self, case, figure: dict) -> Path:
        layer_check.write_layer_check_case(self.out, case)
        self.out.flush()
        return figures.save(layer_check.layer_check_figure(**figure), self.location / f"layer_check_{case.name}.png")

    def jacobian(self, target: str, J: np.ndarray, cup_names: list[str]) -> None:
        results.write_jacobian(self.out, target, J, cup_names)

    def study(self, study, seconds: float) -> None:
        results.write_study(self.out, rows_as_columns(study.rows), study.reference, study.notes, seconds)
        self.out.flush()

    def plan(self, target, plan, desired_source: str) -> None:
        results.write_target(self.out, target.name, target.rest, plan.desired, desired_source)
        results.write_plan(self.out, plan, plan.robot_note, plan.robot_ok)
        self.out.flush()

    def controller_model(self, data, target_names: list[str], paths, jacobian_update: str, title: str
                         ) -> Optional[Path]:
        """The controller's model (docs/model.md §15): /controller_model and its path figure (when drawn)."""
        from scissor_cli.output.controller_model import (  # noqa: PLC0415
            save_controller_model_figure,
            write_controller_model,
            write_paths,
        )

        write_controller_model(self.out.h5, data, target_names, jacobian_update)
        if paths is not None:
            write_paths(self.out.h5, paths)
        self.out.flush()
        return None if paths is None else save_controller_model_figure(paths, title, self.location)

    def stored_controller_model(self, target_names: list[str]):
        """The controller model a resumed run stored, or None."""
        from scissor_cli.output.controller_model import read_controller_model  # noqa: PLC0415

        return None if self._rebuilt else read_controller_model(self.out.h5, target_names)

    def manipulation_points(self, plan, scene) -> Path:
        """The manipulation-point plan (docs/model.md §7): /manipulation_points and its figure."""
        if getattr(scene, "dim", 2) == 3:  # `scene` is then the body's tissue (its skin is drawn)
            from scissor_cli.output.body.grips import save_body_grips_figure, write_body_grips  # noqa: PLC0415

            write_body_grips(self.out, plan)
            self.out.flush()
            return save_body_grips_figure(plan, scene, self.location)
        from scissor_cli.output.grip_figures import save_grip_figure, write_manipulation_points  # noqa: PLC0415

        write_manipulation_points(self.out, plan)
        self.out.flush()
        return save_grip_figure(plan, scene, self.location)

    def manipulation(self, m: Manipulation) -> Path | list[Path]:
        results.write_manipulation(self.out, m.target, m.closed, m.opened)
        self.out.flush()
        if m.tissue.dim == 3:  # a body: its section and 3-D view after the closed loop (docs/model.md §19)
            from scissor_cli.output.body.figures import manipulation_figures  # noqa: PLC0415

            section, view = manipulation_figures(m)
            return [figures.save(section, self.location / f"manipulation_{m.target}.png"),
                    figures.save(view, self.location / f"manipulation_{m.target}_3d.png")]
        inputs = manipulation_figure_inputs(m.tissue, m.closed, m.target_rest, m.corridor)
        return figures.save(figures.manipulation_figure(inputs), self.location / f"manipulation_{m.target}.png")

    def body_plan(self, plan) -> None:
        """A 3-D lesion's needle plan (docs/model.md §19): /plan/<target> and its /targets attributes."""
        from scissor_cli.output.body.results import write_body_plan  # noqa: PLC0415

        write_body_plan(self.out, plan)
        self.out.flush()

    def imaging(self, record, tissue, layer_frames: list) -> list[Path]:
        """/imaging/<target> (docs/contract.md), flushed, then imaging_<target>.png and .gif; returns their paths."""
        from scissor_cli.output.imaging.figures import imaging_outputs  # noqa: PLC0415
        from scissor_cli.output.imaging.results import write_imaging  # noqa: PLC0415

        write_imaging(self.out, record, [c.name for c in tissue.scene.cups])
        self.out.flush()
        return imaging_outputs(record, tissue, layer_frames, self.location)

    def insertion(self, ins) -> list[Path]:
        from scissor_cli.output.insertion.writer import insertion_outputs

        for r in ins.results:
            write_insertion(self.out, r)
        if ins.needle_model is not None and any(r.strategy == "loop" for r in ins.results):
            write_needle_model(self.out, ins.target, ins.needle_model)
        self.out.flush()
        return insertion_outputs(ins, self.location)

    # -- the trials --------------------------------------------------------
    def allocate_trials(self, targets: list[str], count: int, attrs: dict, without_plan: dict[str, str],
                        dim: int = 2) -> None:
        results.allocate_trials(self.out, targets, count, attrs, dim)
        for name, reason in without_plan.items():
            results.mark_without_plan(self.out, name, reason)
        self.out.flush()
        if self._journal is None:
            self._journal = journal.Journal.create(journal.journal_path(self.out.path), self.config_yaml,
                                                   int(self.out.h5.attrs["seed"]))
        self._apply_replay()

    def _apply_replay(self) -> None:
        """Store the journal's finished trials that the file lacks (a crashed trial is run again anyway)."""
        pending = {name: set(ks.tolist()) for name, ks in self.pending_trials().items()}
        restored = set()
        for rec in self._replay:
            if rec["ok"] and rec["trial"] in pending.get(rec["target"], ()):
                results.write_trial(self.out, rec)
                restored.add((rec["target"], rec["trial"]))
                pending[rec["target"]].discard(rec["trial"])
        if restored:
            self._notes.append(f"restored {len(restored)} finished trial(s) "
                               f"from {journal.journal_path(self.out.path).name}")
        self._replay = []

    def pending_trials(self) -> dict[str, np.ndarray]:
        return results.pending_trials(self.out.h5)

    def trial(self, target: str, outcome) -> None:
        rec = results.trial_record(target, outcome)  # checked finite before anything is written
        self._journal.append(rec)
        results.write_trial(self.out, rec)

    def budget_row(self, row: str, fields: dict, outcomes: dict[str, list]) -> None:
        budget_results.write_budget_row(self.out, row, fields, outcomes)

    def budget_figures(self, title: str, rows: list[str], profile: str) -> list[Path]:
        budget_results.write_budget_attrs(self.out, rows, profile)
        table = budget_results.budget_rows(budget_results.read_budget(self.out.h5))
        if not table:
            return []
        return [figures.save(budget_figure(title, table, profile), self.location / "budget.png")]

    def trial_figures(self, title: str) -> list[Path]:
        """Fig. 14 box plots of the x and y error per target, and the iterations histogram."""
        h5 = self.out.h5
        errors = {t: g["final_error"][:][results.finished_trials(g)] for t, g in h5["trials"].items()}
        errors = {t: e for t, e in errors.items() if len(e)}
        if not errors:
            return []
        profile = h5["trials"].attrs.get("profile", "")
        paths = [figures.save(figures.error_boxplots([(f"{title} ({profile})", errors)]),
                              self.location / "trials_error_boxplot.png")]
        iterations = {t: g["iterations"][:][g["iterations"][:] >= 0] for t, g in h5["trials"].items()}
        paths.append(figures.save(figures.iterations_histogram(iterations, f"{title}: control iterations per trial"),
                                  self.location / "trials_iterations.png"))
        return paths


#: the config a new run starts with (the command line's overrides applied), written before its first stage: a run
#: stopped before results.h5 exists (in the slab's ladder, say) starts again from it on `--resume`
STARTED = ".scissor-run.yaml"


class RunDirectory:
    """The sink factory of a new run into `path` (`experiments.sink.SinkFactory`)."""

    def __init__(self, path: Path | str):
        self.location = Path(path)

    def start(self, config_yaml: str) -> None:
        """Record the run's config (STARTED) before its first stage, whole or not at all."""
        run_cache.write_whole(self.location / STARTED,
                              lambda partial: partial.write_text(config_yaml, encoding="utf-8"))

    def open(self, config_yaml: str, seed: int) -> ResultsSink:
        self.location.mkdir(parents=True, exist_ok=True)
        path = self.location / "results.h5"
        journal.journal_path(path).unlink(missing_ok=True)  # an earlier run's (--force): not this run's trials
        out = ResultsFile.create(path, config_yaml, seed)
        out.h5.attrs[FINISHED] = np.array([], dtype=h5py.string_dtype())
        return ResultsSink(out)


def _problem(path: Path) -> Optional[str]:
    """Why the HDF5 file at `path` cannot be trusted, or None when it reads back whole.

    Opens it and reads every dataset and attribute back (a kill mid-write
    can break a group's heap or the global heap of variable-length strings
    such as the trials' stop reasons, not only the masks). A file another
    process is writing is not damaged: that is a ResumeError.
    """
    def read(name, obj):
        for key in obj.attrs:
            obj.attrs[key]
        if isinstance(obj, h5py.Dataset):
            obj[()]

    try:
        with h5py.File(path, "r") as h5:
            str(h5.attrs["config_yaml"])
            h5.visititems(read)
    except OSError as exc:
        if "unable to lock file" in str(exc):
            raise ResumeError(f"{path}: another process has it open for writing (is that run still going?); "
                              f"stop it first") from None
        return f"{type(exc).__name__}: {exc}"
    except (KeyError, ValueError, RuntimeError) as exc:
        return f"{type(exc).__name__}: {exc}"
    return None


def _repair(out: ResultsFile) -> int:
    """Un-mark trials marked done whose history is missing (a write cut short); returns how many."""
    n = 0
    for name, g in out.h5.get("trials", {}).items():
        ok = np.flatnonzero(results.finished_trials(g))
        for k in ok:
            if str(k) not in g["history"]:
                out.put(f"trials/{name}/done", int(k), False)
                n += 1
    if n:
        out.flush()
    return n


def started_config(run_dir: Path | str) -> Optional[str]:
    """The config a run in `run_dir` started with (`RunDirectory.start`), or None when it left none readable."""
    try:
        return (Path(run_dir) / STARTED).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None


def open_for_resume(run_dir: Path | str) -> ResultsSink:
    """The sink that finishes the run stored in `run_dir`; ResumeError if there is nothing to resume."""
    run_dir = Path(run_dir)
    path = run_dir / "results.h5"
    tmp, jpath = temporary(path), journal.journal_path(path)
    header, recs, valid = journal.read(jpath)
    notes: list[str] = []
    base = None
    if tmp.exists():
        problem = _problem(tmp)
        if problem is None:
            base = tmp
            notes.append(f"resuming from {tmp.name}, left by a run that was killed")
        else:
            damaged = tmp.with_name(path.name + ".damaged")
            tmp.replace(damaged)
            notes.append(f"{tmp.name} cannot be read ({problem}); a run was killed while writing it. "
                         f"Moved to {damaged.name}; what it held beyond the journal's trials is lost")
    if base is None and path.exists():
        problem = _problem(path)
        if problem is None:
            base = path
            if notes:
                notes.append(f"falling back to {path.name}, the run as it was before the killed resume")
        elif header is None:
            raise ResumeError(f"{path}: cannot be read ({problem}) and there is no trial journal; run simulate again")
        else:
            notes.append(f"{path.name} cannot be read either ({problem})")
    if base is None and header is None:
        if not notes:
            raise ResumeError(f"--resume {run_dir}: no results.h5 there")
        raise ResumeError(f"--resume {run_dir}: {'; '.join(notes)}; and there is no trial journal to rebuild from: "
                          f"run simulate again")
    if base is not None:
        with h5py.File(base, "r") as h5:
            config_yaml = str(h5.attrs["config_yaml"])
        if header is not None and header["config_yaml"] != config_yaml:
            notes.append(f"{jpath.name} belongs to another run; ignored")
            header, recs, valid = None, [], 0
        out = ResultsFile.continue_temporary(path) if base == tmp else results.reopen(path)
        repaired = _repair(out)
        if repaired:
            notes.append(f"{repaired} trial(s) marked done had no history (cut short by the kill); "
                         f"taken from the journal or run again")
        trials_journal = (journal.Journal.resume(jpath, valid) if header is not None
                          else journal.Journal.create(jpath, config_yaml, int(out.h5.attrs["seed"])))
        sink = ResultsSink(out, trials_journal=trials_journal, replay=recs, notes=notes)
        sink._apply_replay()
        return sink
    # No HDF5 file to trust: a fresh one from the journal's config; the stages before the trials run again.
    out = ResultsFile.create(path, header["config_yaml"], header["seed"])
    notes.append(f"rebuilding {path.name} from the config in {jpath.name}: the stages before the trials run again "
                 f"(the accuracy-driven /selection, if the run had one, is not repeated); "
                 f"the {sum(bool(r['ok']) for r in recs)} finished trial(s) in it are kept")
    return ResultsSink(out, trials_journal=journal.Journal.resume(jpath, valid), replay=recs, notes=notes, rebuilt=True)
