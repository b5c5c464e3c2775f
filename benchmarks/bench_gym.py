"""Steps per second and reset times of the gymnasium environments (docs/model.md §22, `scissor_cli.gym`).

Three environments, each with the trials' draws (`profile_draws`, the default) and random actions in [−1, 1]
(a reset when an episode ends, not timed): the 2-D layer (configs/example.yaml), the 3-D dome
(configs/example_dome.yaml) with its surrogate as the plant, and the dome body itself. For each: the first reset
(it builds the model: mesh, tissue, plans, and for the surrogate the body solves of its design), the median
reset after it, and steps per second, the median over --repeats runs of --steps steps (the body's over a tenth
of them). Goals (reported, not asserted): layer ≥ 200 steps/s, surrogate ≥ 1,000, body ≥ 5, reset ≤ 1 s.

    python benchmarks/bench_gym.py [--repeats 3] [--steps 400]

The machine has 2 cores and other work may share them: the numbers are wall-clock medians, not CPU time.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import gymnasium  # noqa: E402
import results_io  # noqa: E402

import scissor_cli.gym  # noqa: E402, F401 - registers the environments

ROOT = Path(__file__).resolve().parents[1]
CASES = (  # name, environment id, config, keyword arguments, share of --steps, goal steps/s
    ("layer", "scissor/LesionAlign2D-v0", "configs/example.yaml", {}, 1.0, 200.0),
    ("surrogate", "scissor/LesionAlign3D-v0", "configs/example_dome.yaml", {"plant": "surrogate"}, 1.0, 1000.0),
    ("body", "scissor/LesionAlign3D-v0", "configs/example_dome.yaml", {"plant": "body"}, 0.1, 5.0),
)
RESET_GOAL_S = 1.0


def measure(env_id: str, config: Path, kwargs: dict, steps: int, repeats: int) -> dict:
    """First reset s, median later reset s, median steps/s of one environment."""
    env = gymnasium.make(env_id, config=str(config), **kwargs)
    t0 = time.perf_counter()
    env.reset(seed=0)
    first = time.perf_counter() - t0
    resets, rates = [], []
    rng = np.random.default_rng(0)
    for r in range(repeats):
        t0 = time.perf_counter()
        env.reset(seed=r + 1)
        resets.append(time.perf_counter() - t0)
        stepping = 0.0
        for _ in range(steps):
            action = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
            t0 = time.perf_counter()
            _, _, terminated, truncated, _ = env.step(action)
            stepping += time.perf_counter() - t0
            if terminated or truncated:
                env.reset()
        rates.append(steps / stepping)
    env.close()
    return {"first_reset_s": first, "reset_s": float(np.median(resets)), "steps_per_s": float(np.median(rates))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--steps", type=int, default=400)
    args = ap.parse_args()
    res = results_io.Results("bench_gym")
    rows = []
    print("| environment | first reset s | reset s (median) | steps/s (median) | goal steps/s |")
    print("|---|---|---|---|---|")
    for name, env_id, config, kwargs, share, goal in CASES:
        got = measure(env_id, ROOT / config, kwargs, max(1, int(args.steps * share)), args.repeats)
        rows.append({"environment": name, "config": config, **got, "goal_steps_per_s": goal,
                     "goal_reset_s": RESET_GOAL_S})
        for key, unit in (("first_reset_s", "s"), ("reset_s", "s"), ("steps_per_s", "1/s")):
            res.figure(f"{name}_{key}", got[key], unit)
        print(f"| {name} | {got['first_reset_s']:.2f} | {got['reset_s']:.3f} | {got['steps_per_s']:.1f} | {goal:g} |",
              flush=True)
    res.table("environments", rows, units={"first_reset_s": "s", "reset_s": "s", "steps_per_s": "1/s",
                                           "goal_steps_per_s": "1/s", "goal_reset_s": "s"})
    res.write()


if __name__ == "__main__":
    main()
