"""What a 3-D scene asks that its layers refuse, checked before any run (exit 2): `scissor validate` and `simulate`.

Apart from `body_run` so that validating a body imports the scene, the
mesher's estimate and the cameras, not the solvers and stages of a run.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.config.element_budget import TETRAHEDRA_BUDGET
from scissor_cli.mesh.body_inputs import body_shape, inclusions, sizing
from scissor_cli.mesh.body_mesh import estimate_tetrahedra
from scissor_cli.scene.body_scene import build_body_scene
from scissor_cli.sensing.camera3d import camera_problems


def body_scene_problems(cfg: BodyConfig) -> list[str]:
    """The scene's problems, each one message naming its field: the mesh over the element budget, cameras that
    cannot see or cannot triangulate its lesions. Empty when there are none."""
    problems = []
    budget = body_budget_problem(cfg)
    if budget is not None:
        problems.append(budget)
    points = [t.position_mm for t in cfg.targets] + [t.desired_mm for t in cfg.targets if t.desired_mm is not None]
    found = camera_problems(cfg.cameras if cfg.cameras else [cfg.camera], np.array(points, float) if points else None)
    if not cfg.cameras:  # the scene's one `camera`
        found = [p.replace("cameras[0]", "camera") for p in found]
    field = "cameras" if cfg.cameras else "camera"
    return problems + [p if p.startswith("camera") else f"{field}: {p}" for p in found]


def body_budget_problem(cfg: BodyConfig) -> str | None:
    """Why the scene's mesh may not be made (estimated above `TETRAHEDRA_BUDGET` before meshing), or None."""
    if cfg.tissue.mesh.file is not None:
        return None
    scene = build_body_scene(cfg)
    n = estimate_tetrahedra(body_shape(scene), inclusions(scene), sizing(scene, cfg.tissue.mesh))
    if n <= TETRAHEDRA_BUDGET:
        return None
    return (f"tissue.mesh: the body's mesh is estimated at {n} tetrahedra, above the budget of {TETRAHEDRA_BUDGET} "
            f"(the largest mesh whose forward cases solve in the time of a run): use a larger min_edge_mm, "
            f"max_edge_mm or scale, or a steeper grading")
