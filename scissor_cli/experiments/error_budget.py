"""The error budget: the trials again with one error source at a time (docs/model.md §16).

A budget row is an ordinary trial run of a variant of the config: every
`trials` setting of the other sources at 0 (and the truth the layer, unless
the row is the 3-D truth's), its own sources as the run has them. Trials
draw every random number whatever its σ (experiments/profiles.py), so a
row's trials meet exactly the draws of the full run for their own source:
a row equals the trials of that variant config run on its own, bit for
bit, and the `all` row is the run's own trials (not run again).

Rows, where the scene has them: camera pixel noise; localisation bias;
with `imaging` instead of those two (the camera's sources do not apply to
the ultrasound, docs/model.md §17): the tissue's sound speed; the probe's
calibration (position and angle); the electronic noise; the speckle alone
(every other source off: the realisation of the scatterers, always there,
is what is left of the ultrasound's error); material mismatch as four
rows (E with its heterogeneity field; ν; η; the fiber angle); actuator
(resolution and backlash); release slip (only when the run sets one); the
3-D truth (with a `layer_check`: the slab against the layer); the needle
(with `insertion`: the drawn friction and tip force); a 3-D scene's own
(docs/model.md §20): the body's registration in the robot's frame and the
lesion's stiffness (a body has no slab or release-slip row);
`none` (every source off: what is left is the loop's own tolerance, pixel
rounding and, with insertion, the nominal needle drag; with `imaging`, the
exact sensor: the imaging section left out and the `ideal` profile, since
the ultrasound cannot be switched off within itself). With imaging every
other row keeps the speckle, as the camera's rows keep the pixel rounding.
"""

from __future__ import annotations

import time
from contextlib import closing
from dataclasses import dataclass, field, replace

from scissor_cli import progress
from scissor_cli.config import Config, resolved_yaml
from scissor_cli.experiments.pool import deferred_signals
from scissor_cli.experiments.profiles import BODY_SPREADS, CAMERA_SPREADS, IMAGING_SPREADS, error_model
from scissor_cli.experiments.sink import product_key
from scissor_cli.experiments.trials import execute_rows

#: every `trials` field that switches an error source (their values: the profile's, or the config's)
SOURCE_FIELDS = ("pixel_noise_px", "localisation_error_mm", "E_log_sd", "heterogeneity_log_sd", "nu_sd",
                 "eta_log_sd", "fiber_angle_sd_deg", "actuator_resolution_mm", "backlash_mm", "release_slip_mm",
                 "friction_log_sd", "tip_force_log_sd") + IMAGING_SPREADS + BODY_SPREADS
#: the rows of the budget and the fields each switches on, in the order they are reported
ROWS: dict[str, tuple[str, ...]] = {
    "camera": ("pixel_noise_px",),
    "localisation": ("localisation_error_mm",),
    "sound_speed": ("sound_speed_sd_m_per_s",),
    "probe_calibration": ("probe_position_sd_mm", "probe_angle_sd_deg"),
    "electronic_noise": ("electronic_noise_scale",),
    "speckle": (),
    "E": ("E_log_sd", "heterogeneity_log_sd"),
    "nu": ("nu_sd",),
    "eta": ("eta_log_sd",),
    "fiber": ("fiber_angle_sd_deg",),
    "actuator": ("actuator_resolution_mm", "backlash_mm"),
    "release_slip": ("release_slip_mm",),
    "slab": (),
    "needle": ("friction_log_sd", "tip_force_log_sd"),
    "registration": ("registration_mm", "registration_deg"),
    "lesion_stiffness": ("lesion_stiffness_log_sd",),
    "none": (),
}
assert set(f for fs in ROWS.values() for f in fs) == set(SOURCE_FIELDS)
#: the rows only a scene with imaging has, and those (the camera's) it then has not
IMAGING_ROWS = ("sound_speed", "probe_calibration", "electronic_noise", "speckle")
CAMERA_ROWS = tuple(name for name, fields in ROWS.items() if fields and set(fields) <= set(CAMERA_SPREADS))
#: the rows only a 3-D scene has, and those a 3-D trial does not draw (the slab is a layer's truth; the release
#: slip a layer's)
BODY_ROWS = ("registration", "lesion_stiffness")
LAYER_ROWS = ("slab", "release_slip")


@dataclass(frozen=True)
class BudgetPlan:
    """The rows a run's budget has, each with its variant config, and what the scene cannot have."""

    rows: dict[str, Config] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def budget_plan(cfg: Config) -> BudgetPlan:
    """The budget's rows for a config: variant configs (trials.budget off) by row name, and the rows skipped."""
    values = {k: getattr(error_model(cfg.trials), k) for k in SOURCE_FIELDS}
    rows, notes = {}, []
    imaging, body = getattr(cfg, "imaging", None), getattr(cfg, "dim", 2) == 3
    if imaging is None:
        notes.append(f"no imaging rows ({', '.join(IMAGING_ROWS)}): the scene has no imaging section")
    else:
        notes.append(f"no {' or '.join(CAMERA_ROWS)} row: with imaging the camera's sources do not apply")
    for name, fields in ROWS.items():
        if (name in IMAGING_ROWS and imaging is None) or (name in CAMERA_ROWS and imaging is not None):
            continue
        if (name in BODY_ROWS and not body) or (name in LAYER_ROWS and body):
            continue
        if name == "slab" and cfg.layer_check is None:
            notes.append("no 3-D truth row: the scene has no layer_check section")
            continue
        if name == "needle" and cfg.insertion is None:
            notes.append("no needle row: the scene has no insertion section")
            continue
        if fields and not any(values[f] for f in fields):
            notes.append(f"no {name} row: its spread is 0 in this run ({', '.join(fields)})")
            continue
        on = {f: (values[f] if f in fields else 0.0) for f in SOURCE_FIELDS}
        truth = "slab" if name == "slab" else "layer"
        trials = {**on, "truth": truth, "budget": False}
        update = {}
        if name == "none" and imaging is not None:  # the exact sensor (module docstring)
            trials["profile"], update["imaging"] = "ideal", None
        rows[name] = cfg.model_copy(update={**update, "trials": cfg.trials.model_copy(update=trials)})
    return BudgetPlan(rows, notes)


def row_config_yaml(cfg: Config) -> str:
    """A row's config as the trial workers read it (the resolved YAML, as for the run's own trials)."""
    return resolved_yaml(cfg)


def identical_trials(row: Config) -> bool:
    """Whether every trial of a row gives the same numbers: no source's spread on and no imaging.

    A trial draws all its numbers whatever their σ (experiments/profiles.py)
    and scales them by σ, so with every σ 0 no draw changes a number (x + 0·z
    is x); the ultrasound draws its speckle per trial whatever the profile.
    Such a row (`none`, `slab` of a camera scene) runs one trial per target,
    which stands for all its trials.
    """
    em = error_model(row.trials)
    return getattr(row, "imaging", None) is None and not any(getattr(em, f) for f in SOURCE_FIELDS)


def run_budget(cfg: Config, tasks: list, sink, execution, done: frozenset[str] = frozenset()) -> list:
    """Run every budget row not yet finished and store it whole (`budget/<row>`); returns figure paths.

    One set of workers runs every row's trials; a row is stored and marked
    finished as soon as its last trial is in, so a killed run keeps its
    finished rows and `--resume` runs the others. A row of identical trials
    (`identical_trials`) runs trial 0 of each target and stores it as each
    of its trials, marked `identical_trials` in its attributes.
    """
    plan = budget_plan(cfg)
    for note in plan.notes:
        progress.info(f"budget: {note}")
    names = [t.name for t in tasks]
    by_index = {t.index: t for t in tasks}
    todo = [name for name in plan.rows if product_key("budget", name) not in done]
    count = cfg.trials.count
    once = {name for name in todo if identical_trials(plan.rows[name])}
    work = {name: [(task, k) for task in tasks for k in range(1 if name in once else count)] for name in todo}
    if todo:
        progress.info(f"budget: {len(todo)} row(s) of {len(tasks) * count} trials ({', '.join(todo)})")
    if once:
        progress.info(f"budget: {', '.join(sorted(once))}: no source drawn, every trial the same: one per target run")
    advance = progress.bar("budget", sum(len(w) for w in work.values()))
    outcomes = {name: {n: [None] * count for n in names} for name in todo}
    left = {name: len(work[name]) for name in todo}
    t0 = time.perf_counter()
    rows_yaml = {name: row_config_yaml(plan.rows[name]) for name in todo}
    with closing(execute_rows(rows_yaml, work, execution.jobs, execution.executor, execution.scheduler)) as stream:
        for name, outcome in stream:
            copies = range(count) if name in once else (outcome.trial,)
            for k in copies:
                outcomes[name][by_index[outcome.target_index].name][k] = replace(outcome, trial=k)
            left[name] -= 1
            advance(1)
            if left[name] == 0:  # a row is stored whole as soon as its last trial is in
                fields = _fields_on(name, plan.rows[name]) | ({"identical_trials": True} if name in once else {})
                with deferred_signals():
                    sink.budget_row(name, fields, outcomes.pop(name))
                    sink.mark_finished(product_key("budget", name))
                progress.info(f"budget {name}: done ({time.perf_counter() - t0:.1f} s into the budget)")
    return sink.budget_figures(cfg.name, list(plan.rows), cfg.trials.profile)


def _fields_on(name: str, row: Config) -> dict[str, float | str]:
    """What a row switches on, for the file: its fields' values and the truth."""
    em = error_model(row.trials)
    return {**{f: getattr(em, f) for f in ROWS[name]}, "truth": row.trials.truth}


