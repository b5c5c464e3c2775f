"""The gymnasium environments (docs/model.md §22, `scissor_cli.gym`): the checker, the drives' limits, seeds,
vector environments, the built-in PID through the plug-in path, and a short policy run.

The 2-D environment runs configs/example.yaml; the 3-D one a coarse copy of configs/example_dome.yaml (coarser
tetrahedra, a smaller surrogate design and two cameras, so that every axis is seen: gymnasium's checker compares
infos with `allclose`, where a NaN of an unseen axis never equals itself).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

gymnasium = pytest.importorskip("gymnasium")

from gymnasium.utils.env_checker import check_env  # noqa: E402

import scissor_cli.api as api  # noqa: E402
from scissor_cli.control import PIDLaw  # noqa: E402
from scissor_cli.gym import LesionAlign2D, LesionAlign3D, PluginPolicy  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LAYER = ROOT / "configs" / "example.yaml"
ID_2D, ID_3D = "scissor_cli.gym:scissor/LesionAlign2D-v0", "scissor_cli.gym:scissor/LesionAlign3D-v0"


@pytest.fixture(scope="module")
def dome(tmp_path_factory) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "example_dome.yaml").read_text())
    data["tissue"]["mesh"] = {"max_edge_mm": 12.0, "min_edge_mm": 4.0}
    data["controller"]["surrogate"] = {"samples": 8}
    data["cameras"] = [{**data.pop("camera")}, {**data.get("camera", {}), "position_mm": [0.0, -400.0, 12.0],
                                                "look_at_mm": [0.0, 0.0, 12.0]}]
    path = tmp_path_factory.mktemp("dome") / "dome.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_the_2d_environment_passes_gymnasiums_checker():
    env = gymnasium.make(ID_2D, config=str(LAYER))
    check_env(env.unwrapped, skip_render_check=True)
    assert isinstance(env.unwrapped, LesionAlign2D)


@pytest.mark.parametrize("plant", ["surrogate", "body"])
def test_the_3d_environment_passes_gymnasiums_checker(dome, plant):
    env = gymnasium.make(ID_3D, config=str(dome), plant=plant)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=3)
    assert isinstance(env.unwrapped, LesionAlign3D) and obs.shape == (3 + 2 * 1,)
    assert info["observation"]["measured_mm"].shape == (3,) and np.isfinite(info["true_miss_mm"])


def test_random_actions_keep_every_cup_within_its_limits_and_speed():
    env = gymnasium.make(ID_2D, config=str(LAYER)).unwrapped
    lo, hi = env.stroke_limits_mm
    _, info = env.reset(seed=11)
    rng = np.random.default_rng(0)
    before = info["strokes_mm"]
    for _ in range(200):
        action = rng.uniform(-1.5, 1.5, env.action_space.shape)  # beyond [−1, 1] too: the drives hold the speed
        obs, _, terminated, truncated, info = env.step(action)
        s = info["strokes_mm"]
        assert np.all(s >= lo) and np.all(s <= hi)
        assert np.all(np.abs(s - before) <= env.max_stroke_step_mm + 1e-9)
        assert env.observation_space.contains(obs)
        before = s
        if terminated or truncated:
            _, info = env.reset()
            before = info["strokes_mm"]


def test_the_same_seed_and_actions_give_the_same_observations_bit_for_bit():
    actions = np.random.default_rng(1).uniform(-1, 1, (15, 1)).astype(np.float32)

    def episode(env):
        out = [env.reset(seed=5)[0]]
        out += [env.step(a)[0] for a in actions]
        return np.array(out)

    first = gymnasium.make(ID_2D, config=str(LAYER))
    a, b = episode(first), episode(first)
    c = episode(gymnasium.make(ID_2D, config=str(LAYER)))
    assert np.array_equal(a, b) and np.array_equal(a, c)


def test_an_async_vector_environment_steps():
    envs = gymnasium.make_vec(ID_2D, num_envs=2, vectorization_mode="async", config=str(LAYER))
    try:
        obs, _ = envs.reset(seed=2)
        assert obs.shape == (2, 4)
        for _ in range(3):
            obs, reward, *_ = envs.step(envs.action_space.sample())
        assert obs.shape == (2, 4) and np.all(np.isfinite(reward))
    finally:
        envs.close()


def test_the_builtin_pid_through_the_environment_commands_what_the_clis_loop_commands(tmp_path):
    # The CLI's PID may command more than one frame's travel (the actuator then takes longer); the plug-in path
    # holds each cup's speed per frame. At 50 mm/s the speed never binds, so the two must agree.
    data = yaml.safe_load(LAYER.read_text())
    for cup in data["cups"]:
        cup["speed_mm_per_s"] = 50.0
    path = tmp_path / "fast.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    cfg = api.load_config(path)
    env = gymnasium.make(ID_2D, config=str(path), profile_draws=False, jacobian=True).unwrapped
    obs, info = env.reset(seed=0)
    task = env._task
    cli = api.manipulate(cfg, task)
    commands = cli.hist_strokes_cmd
    assert len(commands) >= 3
    c = cfg.controller
    policy = PluginPolicy(PIDLaw(c.kp, c.ki, c.kd))
    mine = [info["strokes_mm"]]
    for _ in range(len(commands) - 1):
        obs, _, terminated, truncated, info = env.step(policy(obs, info))
        mine.append(info["strokes_mm"])
        if terminated or truncated:
            break
    n = min(len(mine), len(commands))
    assert n == len(commands)
    np.testing.assert_allclose(np.array(mine[:n]), commands[:n], rtol=0, atol=1e-9)


def test_a_proportional_policy_brings_the_lesion_onto_its_needle():
    """docs/model.md §22's proportional controller: the velocity that removes the miss in about a second."""
    env = gymnasium.make(ID_2D, config=str(LAYER), profile_draws=False, jacobian=True)
    obs, info = env.reset(seed=0)
    start = info["true_miss_mm"]
    for _ in range(60):
        J, axis = info["jacobian"], info["observation"]["direction"]
        P = np.eye(2) - np.outer(axis, axis)
        miss = P @ (info["observation"]["desired_mm"] - info["observation"]["measured_mm"])
        velocity = np.linalg.lstsq(P @ J, miss, rcond=None)[0] / 1.0
        obs, _, terminated, truncated, info = env.step(np.clip(velocity / info["speed_mm_per_s"], -1, 1))
        if terminated or truncated:
            break
    assert start > 1.0 and info["true_miss_mm"] <= env.unwrapped.cfg.controller.tolerance_mm + 1e-9
