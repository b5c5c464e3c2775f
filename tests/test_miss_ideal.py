"""With the ideal error profile every target of the default scene and of the two-cup scene ends within
0.1 mm of its needle axis (the miss, docs/model.md §6), on the plans `simulate` makes (docs/model.md §7)."""

import numpy as np
import pytest

from scissor_cli.config import load_config, resolved_yaml
from scissor_cli.experiments.simulate import robot_joint_check, trial_tasks
from scissor_cli.experiments.trials import TrialContext
from scissor_cli.planning.needle_plan import plan_targets

from helpers import ROOT


@pytest.mark.parametrize("name", ["example", "two_cups"])
def test_ideal_trials_reach_a_miss_within_0_1_mm(name):
    cfg = load_config(ROOT / "configs" / f"{name}.yaml")
    cfg = cfg.model_copy(update={"trials": cfg.trials.model_copy(update={"profile": "ideal", "count": 1})})
    ctx = TrialContext(resolved_yaml(cfg))
    plans = plan_targets(ctx.tissue, ctx.scene, cfg.needle, robot_check=robot_joint_check(cfg))
    assert all(p.feasible and p.robot_ok for p in plans), [(p.target, p.robot_note) for p in plans]
    tasks = trial_tasks(ctx.tissue, plans)
    assert len(tasks) == len(ctx.scene.targets)
    for task in tasks:
        o = ctx.run(task, 0)
        assert o.ok and o.stop_reason == "tolerance", (task.name, o.stop_reason, o.message)
        assert o.miss_mm <= 0.1, (task.name, o.miss_mm)
        assert o.corridor_clear, task.name
        n = task.direction / np.linalg.norm(task.direction)
        assert o.along_mm == pytest.approx(float(-n @ o.final_error))
