"""A plug-in controller (docs/model.md §22: reset/act) as a policy of the gymnasium environments."""

from __future__ import annotations

from typing import Any

import numpy as np

from scissor_cli.control.plugin import checked_velocity


class PluginPolicy:
    """policy(obs, info) → action (C,): the controller's velocity (mm/s) over each cup's speed, clipped to [−1, 1].

    It reads the environment's `info` (the protocol's `observation` dict and
    the `frame_info` keys; `jacobian` needs the environment's
    `jacobian=True` for a law that uses it, as `control.PIDLaw`). It calls
    `controller.reset` on its first call, on every frame 0 (just after an
    environment's reset) and after `reset()`. The action is float64 so
    the velocity reaches the drives unrounded.
    """

    def __init__(self, controller):
        self.controller = controller
        self._fresh = True

    def reset(self) -> None:
        """The next call starts a new manipulation (calls `controller.reset`)."""
        self._fresh = True

    def __call__(self, obs: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        seen = info["observation"]
        if self._fresh or info["iteration"] == 0:
            self.controller.reset(seen, info)
            self._fresh = False
        velocity = checked_velocity(self.controller.act(seen, info), len(info["speed_mm_per_s"]))
        return np.clip(velocity / info["speed_mm_per_s"], -1.0, 1.0)
