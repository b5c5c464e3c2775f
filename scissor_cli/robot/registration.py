"""Registration of the tissue layer in the robot's base frame, and layer plans to joints (docs/model.md §11).

The layer frame has its origin at `origin` (3,) mm in the base frame and is
turned by `yaw_rad` about base z; the layer is its z = 0 plane (the robot
config's `layer_origin_mm` and `layer_yaw_deg`).
"""

from __future__ import annotations

import numpy as np

from scissor_cli.robot.chain import RobotModel
from scissor_cli.robot.ik import IKResult, ik


def _rot_z(yaw_rad: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def layer_to_base(points_2d, origin, yaw_rad: float) -> np.ndarray:
    """Layer-plane points (K,2) or (2,) mm → base-frame points (K,3) mm.

    The layer frame has origin `origin` (3,) in the base frame and is turned
    by yaw_rad about base z; the layer is its z = 0 plane.
    """
    p = np.atleast_2d(np.asarray(points_2d, dtype=float))
    p3 = np.column_stack([p, np.zeros(len(p))])
    return p3 @ _rot_z(yaw_rad).T + np.asarray(origin, dtype=float)


def direction_layer_to_base(dir_2d, yaw_rad: float) -> np.ndarray:
    """Layer-plane directions (K,2) or (2,) → base-frame directions (K,3)."""
    d = np.atleast_2d(np.asarray(dir_2d, dtype=float))
    return np.column_stack([d, np.zeros(len(d))]) @ _rot_z(yaw_rad).T


def plan_to_joints(robot: RobotModel, target_layer_2d, direction_layer_2d, origin, yaw_rad: float) -> IKResult:
    """Joint values (an `IKResult`) that put the needle tip on a layer target.

    target_layer_2d (2,) mm and direction_layer_2d (2,) (the travel
    direction, normalised here) in the layer frame; origin (3,) mm and
    yaw_rad place the layer in the base frame (`layer_to_base`).
    """
    tip = layer_to_base(target_layer_2d, origin, yaw_rad)[0]
    d = np.asarray(direction_layer_2d, dtype=float).reshape(2)
    approach = direction_layer_to_base(d / np.linalg.norm(d), yaw_rad)[0]
    return ik(tip, approach, robot)
