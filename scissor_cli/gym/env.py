"""The gymnasium environments: move a lesion onto its planned needle line with the cups (docs/model.md §22).

`LesionAlign2D` runs the 2-D layer, `LesionAlign3D` a 3-D body (plant
"body": the body solved at every step; "surrogate": its learned map,
`scenario.SurrogatePlant`). One episode is one target's manipulation from
rest: one trial of `scissor simulate` (the trial index drawn from the
environment's `np_random`, `api.trial_run`) or, with `profile_draws`
False, the nominal run (truth = model, exact sensor).

Spaces (C cups, d = 2 or 3):

* action (C,) float32 in [−1, 1]: each cup's velocity as a fraction of its
  speed; the command is `control.plugin.drive` of it over one control
  period dt = 1 / controller.rate_hz (speed, then stroke limits, then the
  resolution), so a cup never leaves [lo, hi] nor moves more than
  speed·dt per step;
* observation (d + 2C,) float32: the measured miss across the needle
  P (desired − measured) (d,) mm, clipped to ±`MISS_BOUND_MM` (an axis
  the sensor does not see, NaN in its reading, counts as 0: one camera on
  a body gives no depth); the commanded strokes mapped to [−1, 1] over
  [lo, hi] (C,); the last action (C,).

Reward: −|miss|² (mm², the observation's miss) − action_penalty·|action|².
`terminated` when the measured miss has been ≤ controller.tolerance_mm
for controller.stop_frames consecutive frames, or when a solve fails
(`info["solver_failed"]` the message, reward `FAILURE_REWARD`);
`truncated` after controller.max_iterations steps.

info: `true_miss_mm` the true lesion's distance (mm) across the needle;
`strokes_mm` (C,) the commanded strokes, `true_strokes_mm` (C,) the
realised ones; `clipped` the cups the drives cut in this step's command
(0 at reset); `observation` the plug-in protocol's observation dict
(`control.plugin.observation`); and the keys of `control.plugin.frame_info`
(`jacobian` (d, C) only with `jacobian=True`: then the controller's model
is moved to every command, as the CLI's loop does, which `PIDLaw` needs).

The model is built at the first reset (`scenario.built`, shared by the
environments of a process), so `gymnasium.make` and pickling are cheap.
`stroke_limits_mm` and `max_stroke_step_mm` come from the config and are
there from construction. `benchmarks/bench_gym.py` measures steps per
second and reset times.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import gymnasium
import numpy as np
from gymnasium import spaces

from scissor_cli import api
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.control.allocation import projector
from scissor_cli.control.broyden import BroydenCorrection
from scissor_cli.control.plugin import drive, frame_info, observation
from scissor_cli.gym import scenario
from scissor_cli.solvers.common import SolverError

#: the miss (mm) the observation holds: a lesion farther across the needle reads as this far
MISS_BOUND_MM = 1000.0
#: a failed solve ends the episode with the reward of the largest miss the observation holds
FAILURE_REWARD = -(MISS_BOUND_MM ** 2)


class LesionAlignEnv(gymnasium.Env):
    """One target of a scene as a gymnasium environment (the module docstring); the 2-D and 3-D ones below.

    config: the scene's YAML path; target: its name (None: the first with
    a feasible plan); profile_draws: trials' draws (False: nominal);
    action_penalty (1/mm² of reward per unit action²); jacobian: track the
    controller's model for `info["jacobian"]`; plant: "body" or, on a body,
    "surrogate".
    """

    metadata = {"render_modes": []}
    DIM = 2

    def __init__(self, config=None, target: Optional[str] = None, profile_draws: bool = True,
                 action_penalty: float = 1e-3, jacobian: bool = False, plant: str = "body"):
        if plant not in scenario.PLANTS:
            raise ValueError(f"plant must be one of {scenario.PLANTS}, got {plant!r}")
        self.config_path = Path(config) if config is not None else self.default_config()
        self.cfg = api.load_config(self.config_path)
        if isinstance(self.cfg, BodyConfig) != (self.DIM == 3):
            raise ValueError(f"{self.config_path}: a {'3-D body' if self.DIM == 3 else '2-D layer'} scene is "
                             f"needed by {type(self).__name__}")
        if plant == "surrogate" and self.DIM != 3:
            raise ValueError("plant 'surrogate' is a body's (LesionAlign3D)")
        self.target, self.profile_draws, self.plant_kind = target, bool(profile_draws), plant
        self.action_penalty, self.track_jacobian = float(action_penalty), bool(jacobian)
        cups, ctl = self.cfg.cups, self.cfg.controller
        lo = np.array([c.stroke_mm[0] for c in cups], float)
        hi = np.array([c.stroke_mm[1] for c in cups], float)
        #: (lo (C,), hi (C,)) mm: each cup's stroke limits
        self.stroke_limits_mm = (lo, hi)
        self.speed_mm_per_s = np.array([c.speed_mm_per_s for c in cups], float)
        self.dt_s = 1.0 / ctl.rate_hz
        #: (C,) mm: the most a cup moves in one step (its speed over one control period)
        self.max_stroke_step_mm = self.speed_mm_per_s * self.dt_s
        C, d = len(cups), self.DIM
        self.action_space = spaces.Box(-1.0, 1.0, (C,), np.float32)
        low = np.concatenate([np.full(d, -MISS_BOUND_MM), -np.ones(2 * C)]).astype(np.float32)
        self.observation_space = spaces.Box(low, -low, dtype=np.float32)
        self._model = self._task = self._plant = self._controller = None

    @classmethod
    def default_config(cls) -> Path:
        return scenario.LAYER_SCENE

    # -- episode -------------------------------------------------------------------------------------------

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        super().reset(seed=seed)
        if self._model is None:
            self._model = scenario.built(self.cfg, surrogate=self.plant_kind == "surrogate")
            self._task = scenario.task_named(self._model, self.target)
        trial = int(self.np_random.integers(0, 2**31)) if self.profile_draws else None
        self._plant, self._controller, direction, run = scenario.episode_parts(self._model, self._task, trial,
                                                                               self.plant_kind)
        self.trial = trial
        self._sensor, self._direction = run.sensor, direction
        self._P = projector(direction)
        self._desired = np.asarray(self._task.desired, float)
        self._command = np.array(self._controller.strokes, float)
        self._time_s, self._iteration, self._within = 0.0, 0, 0
        self._action = np.zeros(len(self._command))
        ctl = self.cfg.controller
        self._correction = (BroydenCorrection(run.sensor.noise_mm)
                            if self.track_jacobian and ctl.jacobian_update == "broyden" else None)
        self._frame()
        return self._obs(), self._info(0)

    def step(self, action):
        if self._plant is None:
            raise RuntimeError("reset() the environment before step()")
        # float64 as given: the plug-in path's velocities pass through unrounded (float32 would cut them)
        a = np.clip(np.asarray(action, float).reshape(-1), -1.0, 1.0)
        lo, hi = self.stroke_limits_mm
        moved = drive(self._command, a * self.speed_mm_per_s, self.dt_s, lo, hi, self.speed_mm_per_s,
                      self._controller.resolution_mm)
        self._action = a
        self._iteration += 1
        truncated = self._iteration >= self.cfg.controller.max_iterations
        try:
            self._plant.apply(moved.command, tangent=self.track_jacobian and self._controller.shares(self._plant))
            if self.track_jacobian:
                self._controller.update(moved.command, self._plant)
        except SolverError as exc:
            info = self._info(moved.clipped)
            info["solver_failed"] = str(exc)
            return self._obs(), FAILURE_REWARD, True, False, info
        self._time_s += max(self.dt_s, self._plant.actuator.last_move_s)
        self._command = moved.command
        self._frame()
        miss = self._miss()
        self._within = self._within + 1 if np.linalg.norm(miss) <= self.cfg.controller.tolerance_mm else 0
        terminated = self._within >= self.cfg.controller.stop_frames
        reward = -float(miss @ miss) - self.action_penalty * float(a @ a)
        return self._obs(), reward, bool(terminated), bool(truncated and not terminated), self._info(moved.clipped)

    # -- what is seen --------------------------------------------------------------------------------------

    def _frame(self) -> None:
        """This frame's measurement, and the controller's J seen through the Broyden correction if any."""
        self._measured = np.asarray(self._sensor.measure(self._plant.true_state()), float)
        if self.track_jacobian:
            J = self._controller.jacobian
            if self._correction is not None:  # the order of `loop.run_loop`: observe, then correct
                self._correction.observe(J, self._command, self._measured)
                J = self._correction.jacobian(J)
            self._J = J

    def _miss(self) -> np.ndarray:
        """P (desired − measured) (d,) mm, an unseen (NaN) axis counted as 0."""
        e = np.nan_to_num(self._desired - self._measured, nan=0.0)
        return e if self._P is None else self._P @ e

    def _obs(self) -> np.ndarray:
        lo, hi = self.stroke_limits_mm
        scaled = 2.0 * (self._command - lo) / np.maximum(hi - lo, 1e-12) - 1.0
        obs = np.concatenate([np.clip(self._miss(), -MISS_BOUND_MM, MISS_BOUND_MM), np.clip(scaled, -1, 1),
                              self._action]).astype(np.float32)
        return np.clip(obs, self.observation_space.low, self.observation_space.high)

    def _info(self, clipped: int) -> dict[str, Any]:
        true_e = self._desired - np.asarray(self._plant.position, float)
        true_miss = true_e if self._P is None else self._P @ true_e
        scene = self._model.tissue.scene
        lo, hi = self.stroke_limits_mm
        frame = frame_info(self._J if self.track_jacobian else np.zeros(0), lo, hi, self.speed_mm_per_s,
                           self.dt_s, self.cfg.controller.error, self._iteration, self._task.name,
                           list(scene.cup_names))
        if not self.track_jacobian:
            del frame["jacobian"]
        return {"true_miss_mm": float(np.linalg.norm(true_miss)), "strokes_mm": self._command.copy(),
                "true_strokes_mm": np.array(self._plant.strokes, float), "clipped": int(clipped),
                "observation": observation(self._measured, self._desired, self._direction, self._command,
                                           self._time_s),
                **frame}


class LesionAlign2D(LesionAlignEnv):
    """`scissor/LesionAlign2D-v0`: the 2-D layer (default the CLI's example scene)."""

    DIM = 2

    def __init__(self, config=None, target: Optional[str] = None, profile_draws: bool = True,
                 action_penalty: float = 1e-3, jacobian: bool = False):
        super().__init__(config, target, profile_draws, action_penalty, jacobian, "body")


class LesionAlign3D(LesionAlignEnv):
    """`scissor/LesionAlign3D-v0`: a 3-D body (default configs/example_dome.yaml), plant "body" or "surrogate"."""

    DIM = 3

    @classmethod
    def default_config(cls) -> Path:
        return scenario.BODY_SCENE
