"""results.h5 `/insertion/<target>/<strategy>` (docs/contract.md, docs/model.md §12).

Every array is finite: the clearance without obstacles (+∞) is stored as
`FILL` with `has_obstacles` false, like the plan's clearance.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.output.results import FILL, ResultsFile, check_finite


def insertion_path(target: str, strategy: str) -> str:
    return f"insertion/{target}/{strategy}"


def write_insertion(out: ResultsFile, r) -> None:
    """One `InsertionResult` (scissor_cli.insertion) at /insertion/<target>/<strategy>."""
    base = insertion_path(r.target_name, r.strategy)
    d = np.asarray(r.entry).size  # 2 in the layer, 3 in the slab: tip, target (K, d), displacement (K, N, d)
    out.dataset(f"{base}/depth_mm", np.asarray(r.depth_mm, float), "mm", description="needle depth per step")
    out.dataset(f"{base}/tip", np.asarray(r.tip, float).reshape(-1, d), "mm", description="tip position per step")
    out.dataset(f"{base}/target", np.asarray(r.target, float).reshape(-1, d), "mm", description="true target per step")
    out.dataset(f"{base}/needle_force_mN", np.asarray(r.needle_force_mN, float), "mN",
                description="axial force on the needle per step: friction + stuck reactions + tip force")
    out.dataset(f"{base}/stuck", np.asarray(r.stuck, np.int64), description="captured nodes sticking")
    out.dataset(f"{base}/slipping", np.asarray(r.slipping, np.int64), description="captured nodes slipping")
    out.dataset(f"{base}/min_clearance_mm", np.asarray(r.min_clearance_mm, float), "mm",
                description=f"shaft to the nearest deformed obstacle; {FILL} without obstacles (has_obstacles)")
    out.dataset(f"{base}/strokes", np.asarray(r.strokes, float).reshape(r.steps, -1), "mm",
                description="cup strokes per step")
    if r.displacement is not None:
        disp = np.asarray(r.displacement, float)
        check_finite(f"/{base}/displacement", disp)
        path = f"{base}/displacement"
        if path in out.h5:
            del out.h5[path]
        out.h5.create_dataset(path, data=disp, compression="gzip", compression_opts=4, shuffle=True)
        out.attrs(path, {"units": "mm", "description": "every node's displacement from rest per step"})
    out.attrs(base, {
        "miss_mm": float(r.miss_mm), "depth_error_mm": float(r.depth_error_mm),
        "entry": np.asarray(r.entry, float), "direction": np.asarray(r.direction, float),
        "time_s": float(r.time_s), "steps": int(r.steps), "obstacle_touched": bool(r.obstacle_touched),
        "has_obstacles": bool(r.has_obstacles), "completed": bool(r.completed), "stop_reason": str(r.stop_reason),
        "unsettled_steps": int(r.unsettled),
    })


def write_needle_model(out: ResultsFile, target: str, model) -> None:
    """The `insertion.NeedleModel` a body's `loop` steered with, at /insertion/<target>/loop/needle_model: per step
    of the nominal `depth` insertion it was tabulated from, its depth, the lesion and its held response."""
    base = f"{insertion_path(target, 'loop')}/needle_model"
    out.dataset(f"{base}/depth_mm", np.asarray(model.depth_mm, float), "mm",
                description="needle depth per step of the nominal insertion tabulated")
    out.dataset(f"{base}/target", np.asarray(model.target_mm, float), "mm", description="the lesion per step")
    out.dataset(f"{base}/jacobian", np.asarray(model.jacobian, float), "mm/mm",
                description="the lesion's held response to a unit stroke of each cup per step (3, C)")
