"""The controller's 3-D model of a target under the needle, tabulated from the nominal tissue's insertion
(docs/model.md §18, §20).

`tabulate` inserts the needle into the nominal slab or body (the
controller's knowledge, no trial's perturbation) from its equilibrium at
the plan's strokes, along the plan's entry and axis (in the slab at the
given height) with an exact sensor:

1. with the `depth` strategy, recording after every step the target's 3-D
   position, and every JACOBIAN_EVERY-th step (every step once the tip is
   within JACOBIAN_NEAR_MM of the target, where the hold changes the
   response fastest) its held response to each cup
   (`ModelState.target_response` to JACOBIAN_TOL, the plant's own kept
   factorisation as the preconditioner), linear in depth between;
2. in the slab, with `loop` steered by that table, for the height the
   target ends at when the loop's cup moves correct the drag in the plane
   (a body's needle is aimed at the lesion in 3-D: no height to find).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from scissor_cli.config import ControllerConfig
from scissor_cli.insertion.model_state import ModelState
from scissor_cli.insertion.needle import NeedleParams, NeedleState
from scissor_cli.insertion.points import is_body, needle_points
from scissor_cli.insertion.run import InsertionOptions, NeedlePath, run_insertion
from scissor_cli.insertion.steering import NeedleModel
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import target_positions
from scissor_cli.solvers.common import SolverError

#: the held Jacobian is solved every this many steps (the table interpolates between)...
JACOBIAN_EVERY = 4
#: ...and at every step once the tip is this close (mm, along the axis) to the target
JACOBIAN_NEAR_MM = 3.0
#: the held Jacobian's relative tolerance: a steering gain, not an equilibrium
JACOBIAN_TOL = 1e-4


def tabulate(tissue: Tissue, x0: np.ndarray, strokes: np.ndarray, path: NeedlePath, params: NeedleParams,
             controller: ControllerConfig) -> NeedleModel:
    """The NeedleModel of one target: the nominal tissue's (a slab's or a body's) insertions from x0 (N, 3) at
    strokes (C,) mm along path (in the slab entry (3,) at the needle's height, direction (3,) with n_z = 0; in a
    body any axis); controller: the loop's gains. Raises SolverError when an insertion stops short of the target."""
    probe = needle_points(tissue, np.asarray(path.target_rest, float)).probe
    p0, n = np.asarray(path.entry, float), np.asarray(path.direction, float) / np.linalg.norm(path.direction)
    depths, targets, jacobians = [], [], []

    def record(state: NeedleState, x: np.ndarray, s: np.ndarray) -> None:
        y = target_positions(probe, x)[0]
        near = (y - p0) @ n - state.depth_mm <= JACOBIAN_NEAR_MM
        if near or len(depths) % JACOBIAN_EVERY == 0:
            R = ModelState(tissue, tissue, x, x, s).target_response(state, probe, state.solver, JACOBIAN_TOL)[0]
            jacobians.append(R)
        else:
            jacobians.append(None)
        depths.append(state.depth_mm)
        targets.append(y)

    _completed(run_insertion(tissue, x0, strokes, path, params,
                             InsertionOptions("depth", keep_displacement=False, record=record)), path)
    depths = np.array(depths)
    table = NeedleModel(depths, np.array(targets), _filled(depths, jacobians), float(p0[2]), float(p0[2]))
    if is_body(tissue):
        return table
    steered = run_insertion(tissue, x0, strokes, path, params,
                            InsertionOptions("loop", controller, needle_model=table, keep_displacement=False))
    _completed(steered, path)
    return replace(table, steered_height_mm=float(steered.target[-1, 2]))


def _filled(depths: np.ndarray, jacobians: list) -> np.ndarray:
    """The Jacobians (K, 3, C) with the steps that have none interpolated linearly in depth."""
    have = np.array([J is not None for J in jacobians])
    known = np.array([J for J in jacobians if J is not None])
    out = np.empty((len(depths),) + known.shape[1:])
    for index in np.ndindex(*known.shape[1:]):
        out[(slice(None),) + index] = np.interp(depths, depths[have], known[(slice(None),) + index])
    return out


def _completed(result, path: NeedlePath) -> None:
    if not result.completed:
        raise SolverError(f"the nominal slab's insertion into {path.target_name or 'the target'} stopped short: "
                          f"{result.stop_reason}")
