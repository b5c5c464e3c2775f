"""The calibrated layer: one stroke transmission per cup fitted to the nominal slab (docs/model.md §15).

Against the slab the 2-D layer overstates a cup's effect (its gain is about
2× too high on the example scene): a cup's stroke moves less tissue in the
slab, where the tissue above and below the layer holds it back. The
calibrated model keeps the layer and its nonlinearity but lets each cup c
act through a transmission τ_c: the layer sees the stroke τ ⊙ s.

Each τ_c is fitted on the cup's own strokes near the plan (`calibration_strokes`:
the plans' strokes of that cup, their halves and the limit beyond them, else
± half its range),
other cups at rest: the nominal slab is solved there (a handful of solves,
one tracked slab), and τ_c minimises the summed squared in-plane distance
between the layer's targets at τ_c v and the slab's at v (bounded scalar
search). Its error: the largest of those distances at the fitted τ.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.optimize import minimize_scalar

from scissor_cli.layer3d.slab import SlabProbe
from scissor_cli.layer3d.surrogate import solve_samples
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import TargetProbe, target_positions
from scissor_cli.solvers.tracking import TrackedEquilibrium

#: the range searched for a transmission: from a cup that barely moves the tissue to one that moves it 1.5×
TRANSMISSION_RANGE = (0.02, 1.5)


@dataclass(frozen=True)
class Calibration:
    """Transmissions (C,); the cup strokes (S, C) mm fitted on and the slab's targets there (S, T, 3) mm."""

    transmission: np.ndarray
    strokes: np.ndarray
    targets: np.ndarray
    error_mm: float


def calibration_strokes(lo: np.ndarray, hi: np.ndarray, plan_strokes: list[np.ndarray]) -> list[np.ndarray]:
    """Per cup, the stroke values (V_c,) mm its transmission is fitted on, near the plans: each plan's stroke,
    its half and the stroke limit on its side (the layer's plan asks too little of a stiffer slab); else ± half
    the cup's range."""
    out = []
    for c in range(len(lo)):
        planned = np.array([s[c] for s in plan_strokes if s[c] != 0.0])
        limits = np.where(planned > 0, hi[c], lo[c])
        values = (np.concatenate([planned, 0.5 * planned, limits]) if planned.size
                  else np.array([0.5 * lo[c], 0.5 * hi[c]]))
        values = np.unique(np.round(values[values != 0.0], 9))
        out.append(values)
    return out


def fit_transmission(layer: Tissue, probe: TargetProbe, slab: Tissue, slab_targets: SlabProbe,
                     values: list[np.ndarray], tol: float, advance: Callable[[int], None] = lambda n: None
                     ) -> Calibration:
    """τ (C,) fitted per cup on its stroke values (`calibration_strokes`) against the nominal slab."""
    C = len(values)
    strokes = np.vstack([np.outer(v, np.eye(C)[c]) for c, v in enumerate(values)]) if C else np.zeros((0, 0))
    answers = solve_samples(slab, slab_targets, strokes, tol, advance)[0]
    tau, errors, row = np.ones(C), [], 0
    for c, v in enumerate(values):
        want = answers[row:row + v.size, :, :2]  # (V, T, 2): what the camera sees
        row += v.size
        eq = TrackedEquilibrium(layer)
        largest: dict[float, float] = {}  # per τ tried: the largest in-plane distance (mm), for the error

        def misfit(t, v=v, want=want, c=c, eq=eq, largest=largest):
            total, worst = 0.0, 0.0
            for k in np.argsort(np.abs(v)):  # outwards from rest: each layer solve starts close
                s = np.zeros(C)
                s[c] = t * v[k]
                eq.move_to(s, tangent=False)
                d = np.linalg.norm(target_positions(probe, eq.x) - want[k], axis=1)
                total += float(np.sum(d ** 2))
                worst = max(worst, float(np.max(d)))
            largest[float(t)] = worst
            return total

        best = minimize_scalar(misfit, bounds=TRANSMISSION_RANGE, method="bounded", options={"xatol": 1e-4})
        tau[c] = float(best.x)
        if tau[c] not in largest:  # (the bounded search returns a point it evaluated; kept safe anyway)
            misfit(tau[c])
        errors.append(largest[tau[c]])
    return Calibration(tau, strokes, answers, float(max(errors, default=0.0)))
