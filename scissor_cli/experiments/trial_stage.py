"""The trials stage of `scissor simulate`: every pending trial run and stored as it finishes (docs/contract.md).

Shared by a layer's run (`experiments.simulate`) and a body's
(`experiments.body_closed_loop`): the trials run in local worker processes
or on a Dask cluster (`Execution`), each stored the moment it is in; the
trial figures drawn at the end; crashed trials reported for `--resume`.
"""

from __future__ import annotations

import time
from contextlib import closing
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

from scissor_cli import progress
from scissor_cli.experiments.pool import deferred_signals
from scissor_cli.experiments.sink import RunSink
from scissor_cli.experiments.trial_types import NominalOutcome, TargetTask
from scissor_cli.experiments.trials import WorkItem, execute
from scissor_cli.text import duration


class TrialsFailed(RuntimeError):
    """Some trials crashed; the others are stored and `--resume` re-runs the crashed ones."""


@dataclass(frozen=True)
class Execution:
    """How trials run: worker processes, or a Dask cluster at `scheduler`."""

    jobs: int = 1
    executor: str = "local"  # "local" | "dask"
    scheduler: str | None = None


def run_trial_stage(sink: RunSink, cfg, tasks: list[TargetTask], execution: Execution,
                    nominal: Sequence[WorkItem] = (),
                    store_nominal: Optional[Callable[[NominalOutcome], None]] = None) -> int:
    """Run every pending trial of the sink and store each as it finishes; returns how many ran.

    `nominal`: work items of a body's nominal insertions (task, `NominalInsertion`) and manipulations (task,
    None) the workers run first, in the order given, beside the trials (with several local workers);
    `store_nominal` stores each as it comes in. Storing is not cut short by a stop signal (`deferred_signals`);
    leaving the loop for any reason stops the workers at once.
    """
    pending = sink.pending_trials()
    by_name = {t.name: t for t in tasks}
    by_index = {t.index: t for t in tasks}
    work = [(by_name[name], int(k)) for name, ks in pending.items() if name in by_name for k in ks]
    if work:
        progress.info(f"trials: {len(work)} to run ({cfg.trials.profile} profile, {execution.jobs} job(s), "
                      f"{execution.executor} executor)" + _beside(nominal))
    advance = progress.bar("trials", len(work))
    t0, failed, finished, lost, refused, trials_s = time.perf_counter(), 0, 0, [], [], 0.0
    checkpoint = estimate_checkpoint(len(work), execution)
    items = list(nominal) + work
    with closing(execute(sink.config_yaml, items, execution.jobs, execution.executor, execution.scheduler)) as outcomes:
        for outcome in outcomes:
            if isinstance(outcome, NominalOutcome):
                with deferred_signals():
                    store_nominal(outcome)
                continue
            with deferred_signals():
                sink.trial(by_index[outcome.target_index].name, outcome)
            if outcome.ok:
                pass
            elif outcome.stop_reason == "controller_failed":  # the user's controller's doing: a result, not a crash
                refused.append(f"{by_index[outcome.target_index].name}#{outcome.trial}: {outcome.message}")
            else:
                failed += 1
            if outcome.lost_frames:
                lost.append(f"{by_index[outcome.target_index].name}#{outcome.trial}: {outcome.lost_frames}")
            finished += 1
            trials_s += outcome.trial_time_s
            if finished == 1 and len(work) > 1:
                loop_s = outcome.time_s if getattr(cfg, "insertion", None) is not None else None  # the rest: the needle
                progress.info(expected_duration(outcome.trial_time_s, len(work), execution, loop_s=loop_s,
                                                beside=len(nominal)))
            if finished == checkpoint:
                progress.info(remaining_duration(trials_s / finished, finished, len(work), execution))
            advance(1)
    if work:
        progress.info(f"trials done in {time.perf_counter() - t0:.1f} s")
    if lost:  # with imaging: frames on which the tracking lost the lesion (the last position held)
        progress.info(f"imaging: the lesion was lost on some frames of {len(lost)} trial(s) ({', '.join(lost[:10])}"
                      f"{', …' if len(lost) > 10 else ''})")
    if refused:  # an outside controller raised or gave no finite velocities (docs/model.md §22)
        progress.info(f"controller: {len(refused)} trial(s) failed in the controller (failed in results.h5, with "
                      f"the message); the first: {refused[0]}")
    sink.trial_figures(cfg.name)
    if failed:
        raise TrialsFailed(f"{failed} trial(s) crashed (see /trials/<target>/message); re-run them with --resume")
    return len(work)


def _beside(nominal: Sequence[WorkItem]) -> str:
    """What the trials' workers run beside the trials, said after the trials' count."""
    manipulations = sum(k is None for _, k in nominal)
    parts = [f"{n} nominal {what}(s)" for n, what in ((len(nominal) - manipulations, "insertion"),
                                                       (manipulations, "manipulation")) if n]
    return f", beside {' and '.join(parts)}" if parts else ""


#: a run estimates the rest of its trials again once 1/CHECKPOINT_PARTS of them are in (`remaining_duration`)
CHECKPOINT_PARTS = 10


def estimate_checkpoint(n_trials: int, execution: Execution) -> int | None:
    """After how many finished trials a run estimates the rest again: a tenth of them, and at least two per worker
    more than the first; None when fewer than that many would be left to estimate."""
    workers = max(1, min(execution.jobs, n_trials))
    at = max(1 + 2 * workers, -(-n_trials // CHECKPOINT_PARTS))
    return at if n_trials - at >= at else None


def remaining_duration(mean_s: float, finished: int, n_trials: int, execution: Execution) -> str:
    """The line a run prints at `estimate_checkpoint`: the rest of the trials at mean_s s each (the finished
    trials' own mean time, `TrialOutcome.trial_time_s`) per worker. The first trial alone (`expected_duration`)
    often overstates a run: a body's later trials take over the model's moves its earlier ones solved."""
    rest = n_trials - finished
    return (f"trials: {finished} of {n_trials} done, {duration(mean_s)} each on average; the other {rest} "
            f"should take about {duration(_on_workers(mean_s, rest, execution)[0])}")


def _on_workers(trial_s: float, n_trials: int, execution: Execution) -> tuple[float, int]:
    """(the wall time s of n_trials trials of trial_s s each on the execution's workers, the workers busy): the
    busiest worker's share, no idle worker counted."""
    workers = max(1, min(execution.jobs, n_trials))
    return trial_s * -(-n_trials // workers), workers


def expected_duration(first_s: float, n_trials: int, execution: Execution, loop_s: float | None = None,
                      beside: int = 0) -> str:
    """The line a run prints when its first trial is in: how long all of them should take.

    first_s: the first trial's own time, its loop and, with insertion, every
    strategy's insertion (`TrialOutcome.trial_time_s`; outcomes arrive in
    batches, so the wall time until the first arrives can hold several
    trials), times the trials per worker; building each worker's model
    comes on top, and so do the `beside` nominal runs the workers run
    beside the trials (a body's nominal insertions and manipulations, whose
    time the first trial does not tell). loop_s: the loop's part of it,
    named when the rest (the insertion) is a noticeable share. A Dask
    cluster's size is not known here: there it is per job asked for.
    """
    total, workers = _on_workers(first_s, n_trials, execution)
    split = ""
    if loop_s is not None and first_s - loop_s > 0.1 * first_s:
        split = f" (the loop {duration(loop_s)}, the needle's insertion {duration(first_s - loop_s)})"
    return (f"trials: the first took {duration(first_s)}{split}; all {n_trials} should take about "
            f"{duration(total)} with {workers} worker(s), plus building each worker's model"
            + (f" and the {beside} nominal run(s) beside the trials" if beside else ""))
