"""Plans judged, and made again where needed, with the controller's model and the nominal slab (docs/model.md §15).

After the layer's needle plans, each planned target is taken through named
steps:

1. `ModelPlanning.model_strokes`: the strokes the controller's model needs
   for the plan's desired point (`control.models.strokes_for`), inside the
   stroke reserve, and how far from it they leave the target;
2. `replanned`: when that is beyond the tolerance and the planner (not the
   config) chose the point, the target planned again on the model's own
   target positions and obstacles;
3. `slab_strokes`: what the nominal slab needs for the same point (reported
   when the slab cannot get there);
4. `verdict`: with a 3-D-aware model, a point it cannot reach makes the
   plan infeasible before any trial runs;
5. `corridor_blocked`: the plan's needle corridor judged again on the
   nominal slab at its strokes (its obstacles are where the slab moves
   them, not where the layer does); a blocked corridor is planned again on
   the model's obstacles, or refused;
6. `with_model_error`: the model's error against the nominal slab at the
   strokes it asks for.

With the `layer` model the slab's verdicts are reported beside the plan
(the paper's method is tested as it is).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config import Config
from scissor_cli.control.corridor_check import Corridor
from scissor_cli.control.models import strokes_for
from scissor_cli.layer3d.tissue_models import ControllerModel, SceneMap, SlabMap
from scissor_cli.planning.corridor import corridor_radius
from scissor_cli.text import ranges, vector

#: (target index, its position (2,) at strokes (C,) → mm, the layer's nodes (N2, 2) at strokes → mm or None)
#: → a `planning.needle_plan.NeedlePlan`
Replan = Callable[[int, Callable[[np.ndarray], np.ndarray], Optional[Callable[[np.ndarray], np.ndarray]]], object]


def reserved_limits(lo: np.ndarray, hi: np.ndarray, reserve: float) -> tuple[np.ndarray, np.ndarray]:
    """The stroke limits (C,) mm a 3-D-aware model's plan may use: each limit moved towards rest by the
    fraction `reserve` of itself (a limit on rest's side of zero, e.g. a push-only cup's 0, stays)."""
    return lo - reserve * np.minimum(lo, 0.0), hi - reserve * np.maximum(hi, 0.0)


def reserved_scene(scene, reserve: float):
    """The scene with each cup's stroke range cut to `reserved_limits`: where a 3-D-aware model plans again
    (the planner's pick is then one the model's check keeps, not the same plan inside the reserve)."""
    lo, hi = reserved_limits(np.array([c.stroke_min_mm for c in scene.cups]),
                             np.array([c.stroke_max_mm for c in scene.cups]), reserve)
    return replace(scene, cups=[replace(c, stroke_min_mm=float(a), stroke_max_mm=float(b))
                                for c, a, b in zip(scene.cups, lo, hi)])


def one_target(answer: SceneMap, target: int):
    """One target's `control.models.TargetMap` from a scene map."""

    def one(strokes):
        y, J = answer(strokes)
        return y[target], J[target]

    return one


@dataclass
class ModelPlanning:
    """What judging the plans with the controller's model needs (see the module's steps).

    lo, hi (C,) mm: the cups' limits; lo_kept, hi_kept: less the stroke
    reserve; tol_mm: the controller's tolerance; mode: its error (miss or
    position); radius_mm: the needle corridor's half width; replan: see
    `Replan` (None: no plan is made again).
    """

    model: ControllerModel
    slab_answer: Optional[SlabMap]
    lo: np.ndarray
    hi: np.ndarray
    reserve: float
    tol_mm: float
    mode: str
    radius_mm: float
    replan: Optional[Replan] = None

    def __post_init__(self):
        self.lo_kept, self.hi_kept = reserved_limits(self.lo, self.hi, self.reserve)
        self.model_answer = self.model.scene_map() if self.model.kind != "layer" else None
        # the layer's answers too, for its error against the slab
        self.model_view = self.model_answer if self.model_answer is not None else self.model.scene_map()
        self.model_layer = self.model.layer_map()
        self.seen = "target positions and obstacles" if self.model_layer is not None else "target positions"

    @classmethod
    def of(cls, cfg: Config, model: ControllerModel, slab_answer: Optional[SlabMap],
           replan: Optional[Replan] = None) -> "ModelPlanning":
        lo = np.array([c.stroke_mm[0] for c in cfg.cups])
        hi = np.array([c.stroke_mm[1] for c in cfg.cups])
        return cls(model, slab_answer, lo, hi, cfg.controller.stroke_reserve, cfg.controller.tolerance_mm,
                   cfg.controller.error, corridor_radius(cfg.needle), replan)

    def direction(self, plan) -> Optional[np.ndarray]:
        return plan.direction if self.mode == "miss" else None

    def model_strokes(self, t: int, plan) -> tuple[np.ndarray, float]:
        """Step 1: the model's strokes (C,) mm for the plan's desired point, and the error (mm) they leave."""
        if self.model_answer is None:
            return np.asarray(plan.strokes, float), 0.0
        start = plan.strokes if self.model.transmission is None else plan.strokes / self.model.transmission
        return strokes_for(one_target(self.model_answer, t), plan.desired, self.lo_kept, self.hi_kept,
                           self.direction(plan), self.mode, start)

    def target_at(self, t: int):
        """Target t's position (2,) at strokes by the model (`planning.needle_plan.TargetAt`)."""
        return lambda s: one_target(self.model_answer, t)(s)[0]

    def replanned(self, t: int, plan, model_s: np.ndarray, left: float):
        """Step 2: (plan, model strokes, error left, the note for a refusal) after planning target t again on the
        model's own positions when its desired point is beyond the model's reach."""
        again = self.replan(t, self.target_at(t), self.model_layer)
        if not again.feasible:
            return plan, model_s, left, f"; planned again on the model's {self.seen}: {again.reason}"
        progress.info(f"plan {plan.target}: the layer's desired point is beyond the {self.model.kind} model's "
                      f"reach (left {left:.2f} mm at strokes {vector(model_s)} mm): planned again on the "
                      f"model's {self.seen}")
        plan = replace(again, planned_with=self.model.kind)
        model_s, left = self.model_strokes(t, plan)
        return plan, model_s, left, ""

    def slab_strokes(self, t: int, plan, model_s: np.ndarray, left: float) -> Optional[np.ndarray]:
        """Step 3: the nominal slab's strokes for the plan's point (reported when it cannot get there)."""
        if self.slab_answer is None:
            return None
        if self.model.kind == "slab":
            slab_s, slab_left = model_s, left
        else:
            slab_s, slab_left = strokes_for(one_target(self.slab_answer, t), plan.desired, self.lo, self.hi,
                                            self.direction(plan), self.mode, model_s)
        if slab_left > self.tol_mm and (self.model.kind == "layer" or left <= self.tol_mm):
            # (else the model's verdict says it)
            progress.info(f"plan {plan.target}: the nominal slab cannot bring the target within {self.tol_mm:g} mm "
                          f"of its desired position inside the stroke limits (left {slab_left:.2f} mm at strokes "
                          f"{vector(slab_s)} mm; the {self.model.kind} model asks {vector(model_s)} mm)")
        return slab_s

    def verdict(self, plan, model_s: np.ndarray, left: float, again_reason: str):
        """Step 4: a 3-D-aware model's plan takes its strokes, and is infeasible when they leave more than the
        tolerance."""
        if self.model_answer is None:
            return plan
        plan = replace(plan, strokes=model_s)
        if left <= self.tol_mm:
            return plan
        kept = "" if self.reserve == 0 else (f" less the stroke reserve of {self.reserve:g} (strokes in "
                                             f"{ranges(self.lo_kept, self.hi_kept)} mm)")
        return replace(plan, feasible=False, reason=(
            f"the {self.model.kind} controller model cannot bring the target within {self.tol_mm:g} mm of its "
            f"desired position inside the stroke limits{kept} (left {left:.2f} mm at strokes {vector(model_s)} mm)"
            + again_reason))

    def corridor_blocked(self, plan, slab_s: Optional[np.ndarray]) -> Optional[str]:
        """Step 5: why the nominal slab blocks the plan's needle corridor at its strokes, or None."""
        corridor = Corridor.from_plan(plan, self.radius_mm)
        if self.slab_answer is None or not plan.feasible or corridor is None:
            return None
        clearance = self.slab_answer.clearance(slab_s, plan.desired, corridor)
        if clearance > 0:  # (NaN: the ray does not leave the slab's skin through the plan's side)
            return None
        return (f"in the nominal slab at strokes {vector(slab_s)} mm the needle's corridor to the desired "
                f"position is blocked (clearance {clearance:.2f} mm): the slab does not move the obstacles "
                f"where the layer does")

    def with_model_error(self, t: int, plan):
        """Step 6: the plan with the model's error (mm) against the nominal slab at the strokes the model asks for."""
        if self.slab_answer is None:
            return plan
        if self.model.kind == "slab":
            return replace(plan, model_error_mm=0.0)
        s = np.asarray(plan.model_strokes, float)
        error = float(np.linalg.norm(one_target(self.model_view, t)(s)[0] - one_target(self.slab_answer, t)(s)[0]))
        return replace(plan, model_error_mm=error)

    def judge(self, t: int, plan, may_replan: bool):
        """Steps 1–6 for one plan: (the judged plan, whether the nominal slab blocks its corridor)."""
        model_s, left = self.model_strokes(t, plan)
        again_reason = ""
        if left > self.tol_mm and may_replan:
            plan, model_s, left, again_reason = self.replanned(t, plan, model_s, left)
        slab_s = self.slab_strokes(t, plan, model_s, left)
        plan = self.verdict(replace(plan, model_strokes=model_s, slab_strokes=slab_s), model_s, left, again_reason)
        blocked = self.corridor_blocked(plan, slab_s)
        if blocked is not None:
            if self.model_answer is not None:
                return replace(plan, feasible=False, reason=blocked), True
            progress.info(f"plan {plan.target}: {blocked}")
        return self.with_model_error(t, plan), False

    def plan(self, t: int, plan, may_replan: bool):
        """One target's plan judged; a blocked corridor planned again on the model's obstacles where it may be."""
        if not plan.feasible:
            return plan
        may_replan = may_replan and self.replan is not None and self.model_answer is not None
        first, blocked = self.judge(t, plan, may_replan)
        if not (blocked and may_replan and self.model_layer is not None and first.planned_with == "layer"):
            return first
        # The layer's plan, reachable for the model, crosses obstacles where the slab has them: plan again where
        # the model puts them.
        again = self.replan(t, self.target_at(t), self.model_layer)
        if not again.feasible:
            return replace(first, reason=f"{first.reason}; planned again on the model's {self.seen}: {again.reason}")
        progress.info(f"plan {plan.target}: {first.reason}; planned again on the {self.model.kind} model's {self.seen}")
        return self.judge(t, replace(again, planned_with=self.model.kind), False)[0]


def plan_with_model(cfg: Config, plans: list, model: ControllerModel, slab_answer: Optional[SlabMap],
                    replan: Optional[Replan] = None) -> list:
    """The plans with `model_strokes` (and `strokes`, for a 3-D-aware model) and `slab_strokes` (docs/model.md §15).

    replan(t, target_at, layer_at): target t planned again with the
    target's position at strokes given by target_at and the layer's nodes
    — the obstacles and the skin — by layer_at (`ControllerModel.layer_map`;
    None: the 2-D layer's). A 3-D-aware model that cannot reach a desired
    point the planner chose (not the config), or whose plan's corridor the
    nominal slab blocks, gets its own plan that way before the plan is
    given up.
    """
    planning = ModelPlanning.of(cfg, model, slab_answer, replan)
    return [planning.plan(t, plan, cfg.targets[t].desired_mm is None) for t, plan in enumerate(plans)]
