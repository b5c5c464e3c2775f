"""The nominal slab at each plan's strokes, solved once per run for every slab-truth trial (docs/performance.md).

Every slab-truth trial of a target starts its first, big move from the
nominal slab's equilibrium at the plan's strokes (`layer3d.truth.SlabTruth.start`):
a load continuation from rest, about a minute on the paper's prosthesis
slab. Each worker used to solve it for every target it met (two workers,
four targets: eight such solves in a study's first minutes). The run now
solves each plan's once, the plans spread over its workers, keeps the
state in the cache beside the run (`<run's parent>/.scissor-cache/`, keyed
by what the nominal slab depends on, so a resume or a second run reads it)
and hands it to the trials with their task. It is solved by the same call
a worker made, so the trials' numbers do not change.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config import Config
from scissor_cli.experiments import run_cache
from scissor_cli.experiments.pool import run_pool
from scissor_cli.experiments.trials import TargetTask, trial_context
from scissor_cli.layer3d.truth import SLAB_TRUTH_TOL


def start_key(cfg: Config, strokes: np.ndarray) -> str:
    """What the nominal slab's equilibrium at `strokes` (C,) mm depends on, hashed."""
    return run_cache.key({
        "tol": SLAB_TRUTH_TOL,
        "scene": cfg.model_dump(mode="json", include={"tissue", "material", "cups", "obstacles", "layer_check"}),
        "strokes": np.round(np.asarray(strokes, float), 12).tolist(),
    })


def with_slab_starts(cfg: Config, config_yaml: str, tasks: list[TargetTask], cache_dir: Optional[Path],
                     jobs: int = 1) -> list[TargetTask]:
    """The tasks, each with the nominal slab's (strokes, x (N3, 3) mm) at its plan (`TargetTask.slab_start`).

    Only with `trials.truth: slab`; a plan at rest needs none. Read from
    `cache_dir` when there, else solved (on up to `jobs` workers) and
    written there (a temporary file renamed: a killed run leaves none half
    written).
    """
    if cfg.trials.truth != "slab" or cfg.layer_check is None:
        return tasks
    wanted = {start_key(cfg, t.plan_strokes): np.asarray(t.plan_strokes, float)
              for t in tasks if np.any(t.plan_strokes)}
    states: dict[str, np.ndarray] = {}
    for key in wanted:
        state = _read(cache_dir, key)
        if state is not None:
            states[key] = state
    missing = [key for key in wanted if key not in states]
    if missing:
        progress.info(f"slab truth: the nominal slab at {len(missing)} plan(s)' strokes, solved once for every trial")
        advance = progress.bar("nominal slab", len(missing))
        batches = [(config_yaml, key, wanted[key]) for key in missing]
        solved = (_solve_start(*b) for b in batches) if jobs <= 1 else run_pool(
            _solve_start_batch, [(b,) for b in batches], min(jobs, len(batches)))
        for key, state in solved:
            states[key] = state
            _write(cache_dir, key, state)
            advance(1)
    return [replace(t, slab_start=(np.asarray(t.plan_strokes, float), states[start_key(cfg, t.plan_strokes)]))
            if np.any(t.plan_strokes) else t for t in tasks]


def _solve_start(config_yaml: str, key: str, strokes: np.ndarray) -> tuple[str, np.ndarray]:
    """In this process or a worker: the trial context's own nominal-slab solve (what a trial would make)."""
    return key, trial_context(config_yaml).slab_truth.start(strokes)[1]


def _solve_start_batch(batch: tuple) -> list[tuple[str, np.ndarray]]:
    return [_solve_start(*batch)]


def _path(cache_dir: Path, key: str) -> Path:
    return cache_dir / f"slab-start-{key}.npy"


def _read(cache_dir: Optional[Path], key: str) -> Optional[np.ndarray]:
    if cache_dir is None or not _path(cache_dir, key).is_file():
        return None
    try:
        state = np.load(_path(cache_dir, key), allow_pickle=False)
    except (OSError, ValueError):  # unreadable: solved again
        return None
    return state if state.ndim == 2 and state.shape[1] == 3 and np.all(np.isfinite(state)) else None


def _write(cache_dir: Optional[Path], key: str, state: np.ndarray) -> None:
    if cache_dir is None:
        return
    run_cache.write_whole(_path(cache_dir, key), lambda partial: np.save(partial, state))
