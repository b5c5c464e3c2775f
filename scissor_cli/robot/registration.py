"""Registration of the tissue layer in the robot's base frame, and layer plans to joints (docs/model.md §11).

The layer frame has its origin at `origin` (3,) mm in the base frame and is
turned by `yaw_rad` about base z; the layer is its z = 0 plane (the robot
config's `layer_origin_mm` and `layer_yaw_deg`). A 3-D body's frame is
placed the same way (its platform is the layer's plane, z up), and
`body_plan_to_joints` turns a body plan into joint values.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.robot.chain import RobotModel
from scissor_cli.robot.ik import HORIZONTAL_TOL, IKResult, ik


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


def body_plan_to_joints(robot: RobotModel, tip_body, direction_body, origin, yaw_rad: float) -> IKResult:
    """Joint values (an `IKResult`) that put the needle tip on a point of a 3-D body, travelling along a direction.

    tip_body (3,) mm and direction_body (3,) (normalised here) in the body's frame, which sits at origin (3,) mm
    in the base frame turned by yaw_rad about z. The puncture module keeps its needle horizontal (docs/model.md
    §11), so a direction with a vertical component beyond HORIZONTAL_TOL is unreachable: the result says so
    (`reachable` false, NaN joints) rather than raising.
    """
    R = _rot_z(yaw_rad)
    tip = R @ np.asarray(tip_body, dtype=float).reshape(3) + np.asarray(origin, dtype=float).reshape(3)
    d = np.asarray(direction_body, dtype=float).reshape(3)
    n = float(np.linalg.norm(d))
    if not n > 0:
        raise ValueError("the needle's direction has zero length")
    d = d / n
    if abs(d[2]) > HORIZONTAL_TOL:
        tilt = float(np.rad2deg(np.arcsin(np.clip(d[2], -1.0, 1.0))))
        return IKResult(q=np.full(robot.n_joints, np.nan), reachable=False, violations={},
                        reason=(f"unreachable: the needle's direction has a vertical component {d[2]:.3g} "
                                f"({tilt:.2f}° from horizontal); the puncture module keeps the needle horizontal "
                                f"(docs/model.md §11)"))
    return ik(tip, R @ np.array([d[0], d[1], 0.0]), robot)
