"""The controller's surrogate: the targets' positions over the strokes, learned from nominal slab equilibria
(docs/model.md §15).

Training: the nominal slab (no trial perturbation) is solved at a
space-filling design of strokes within the cups' limits — the 2^C corners
of the stroke box (when there are at most half as many corners as samples)
and scrambled Halton points for the rest — and at a quarter as many other
Halton points (at least 4) kept out of the fit to measure its error. They
are split into two groups by the sign of the first cup's stroke (`groups`);
in each, one tracked slab (`solvers.tracking.TrackedEquilibrium`) visits them in
a nearest-neighbour chain from rest, so each solve starts from a close
equilibrium. The groups are independent: with `--jobs 2` they are solved
in two worker processes, with the same numbers as one after the other. One
slab solve answers for every target.

The map: per target, the three coordinates as a thin-plate-spline radial
basis interpolant with a linear polynomial (scipy's RBFInterpolator,
strokes scaled to [−1, 1] per cup), exact at the training samples; J by
central differences of the interpolant (its step, 1e-4 of each cup's
range, is far below the samples' spacing, so the difference error is
round-off). Its error: the largest in-plane distance between its
prediction and the slab at the held-out strokes, over targets — the part
the camera sees and the controller uses (the height is learned too and
stored, but a thin slab's height can swing by millimetres over the strokes
and is not what the loop steers).

The same solves also give the layer: the slab's nodes at the layer's
height, in-plane (one per 2-D node), learned the same way (`layer_at`), so
a plan made again with the model judges the obstacles and the skin where
the slab moves them, not where the 2-D layer does (docs/model.md §15).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from scissor_cli.layer3d.slab import SlabProbe
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.tracking import TrackedEquilibrium

#: the Halton design's scrambling seed: the design is part of the model, not of a trial's draw
DESIGN_SEED = 20240906
#: J's central-difference step as a fraction of each cup's stroke range
FD_STEP = 1e-4


@dataclass(frozen=True)
class SurrogateSamples:
    """The nominal slab's answers: strokes (S, C) mm → targets (S, T, 3) mm; held-out (V, C) → (V, T, 3)."""

    strokes: np.ndarray
    targets: np.ndarray
    held_strokes: np.ndarray
    held_targets: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    build_time_s: float
    #: the slab's layer in-plane at the training (S, N2, 2) and held-out (V, N2, 2) strokes, mm; None: not learned
    layer: Optional[np.ndarray] = None
    held_layer: Optional[np.ndarray] = None


def design(lo: np.ndarray, hi: np.ndarray, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Training strokes (samples, C) and held-out strokes (max(4, samples // 4), C) mm within [lo, hi]."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    C = lo.size
    corners = np.zeros((0, C))
    if 2 ** C <= samples // 2:
        corners = np.array(np.meshgrid(*[[0.0, 1.0]] * C, indexing="ij")).reshape(C, -1).T
    n_held = max(4, samples // 4)
    from scipy.stats import qmc  # noqa: PLC0415 - scipy.stats costs every `simulate` start most of a second

    unit = qmc.Halton(d=C, scramble=True, seed=DESIGN_SEED).random(samples - len(corners) + n_held)
    train = np.vstack([corners, unit[:samples - len(corners)]])
    return lo + train * (hi - lo), lo + unit[samples - len(corners):] * (hi - lo)


def chain(points: np.ndarray) -> np.ndarray:
    """A visiting order (P,) of stroke points (P, C): nearest-neighbour from rest, so each solve starts close."""
    order, here = [], np.zeros(points.shape[1])
    left = list(range(len(points)))
    while left:
        k = min(left, key=lambda i: float(np.linalg.norm(points[i] - here)))
        order.append(k)
        left.remove(k)
        here = points[k]
    return np.array(order, np.int64)


def groups(points: np.ndarray) -> list[np.ndarray]:
    """The design's points (P, C) as two independent groups of indices: first cup's stroke < 0, and ≥ 0."""
    if points.shape[1] == 0:
        return [np.arange(len(points))]
    negative = points[:, 0] < 0.0
    return [g for g in (np.flatnonzero(negative), np.flatnonzero(~negative)) if g.size]


def solve_samples(slab: Tissue, probe: SlabProbe, strokes: np.ndarray, tol: float,
                  advance: Callable[[int], None] = lambda n: None, layer: SlabProbe | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The targets (P, T, 3) mm and the layer in-plane (P, N2, 2) mm (`layer`: the layer's nodes in the slab,
    `slab.layer_probe`; none: N2 = 0) of the nominal slab at each stroke vector (P, C), solved along `chain`
    from rest."""
    eq = TrackedEquilibrium(slab, tol)
    targets = np.empty((len(strokes), len(probe.nodes), 3))
    layer_xy = np.empty((len(strokes), 0 if layer is None else len(layer.nodes), 2))
    for k in chain(strokes):
        eq.move_to(strokes[k], tangent=False)
        targets[k] = probe.positions(eq.x)
        if layer is not None:
            layer_xy[k] = layer.positions(eq.x)[:, :2]
        advance(1)
    return targets, layer_xy


#: solves groups of stroke points [(P_g, C)] → their (targets (P_g, T, 3), layer (P_g, N2, 2)), in order
#: (`train`'s parallel hook)
GroupSolver = Callable[[list[np.ndarray]], list[tuple[np.ndarray, np.ndarray]]]


def train(slab: Tissue, probe: SlabProbe, layer: SlabProbe | None, lo, hi, samples: int, tol: float,
          advance: Callable[[int], None] = lambda n: None, solve_groups: GroupSolver | None = None
          ) -> SurrogateSamples:
    """Solve the design (`design`) on the nominal slab, in its `groups`: the training set and the held-out set.

    `probe` is anything with `nodes` (T rows) and `positions(x)` → (T, 3) mm;
    `layer` None learns no layer (a body's surrogate, docs/model.md §19).

    solve_groups: how the groups are solved (default: one after the other
    here, each by `solve_samples`); the numbers do not depend on it.
    """
    t0 = time.perf_counter()
    strokes, held = design(lo, hi, samples)
    points = np.vstack([strokes, held])
    parts = groups(points)
    if solve_groups is None:
        def solve_groups(chunks):
            return [solve_samples(slab, probe, chunk, tol, advance, layer) for chunk in chunks]
    answers = np.empty((len(points), len(probe.nodes), 3))
    layer_xy = np.empty((len(points), 0 if layer is None else len(layer.nodes), 2))
    for part, (solved, solved_layer) in zip(parts, solve_groups([points[g] for g in parts])):
        answers[part], layer_xy[part] = solved, solved_layer
    learnt = (None, None) if layer is None else (layer_xy[:samples], layer_xy[samples:])
    return SurrogateSamples(strokes, answers[:samples], held, answers[samples:], np.asarray(lo, float),
                            np.asarray(hi, float), time.perf_counter() - t0, *learnt)


class Surrogate:
    """The interpolant of `SurrogateSamples`: predict(strokes (C,)) → targets (T, 3) mm, and J.

    components: what the controller steers and the error is measured on —
    2, the slab's in-plane part; 3, a body's whole position.
    """

    def __init__(self, data: SurrogateSamples, components: int = 2):
        self.data, self.components = data, components
        self._centre = 0.5 * (data.lo + data.hi)
        self._half = np.maximum(0.5 * (data.hi - data.lo), 1e-12)
        from scipy.interpolate import RBFInterpolator  # noqa: PLC0415 - as scipy.stats above

        S, T, _ = data.targets.shape
        self.n_targets = T
        self._rbf = RBFInterpolator(self._scaled(data.strokes), data.targets.reshape(S, 3 * T),
                                    kernel="thin_plate_spline", degree=1)
        self._layer_rbf = None if data.layer is None else RBFInterpolator(
            self._scaled(data.strokes), data.layer.reshape(S, -1), kernel="thin_plate_spline", degree=1)

    def _scaled(self, strokes: np.ndarray) -> np.ndarray:
        return (np.atleast_2d(strokes) - self._centre) / self._half

    def predict(self, strokes: np.ndarray) -> np.ndarray:
        """Targets (P, T, 3) mm at strokes (P, C) mm."""
        s = np.atleast_2d(np.asarray(strokes, float))
        return self._rbf(self._scaled(s)).reshape(len(s), self.n_targets, 3)

    def answer(self, strokes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Targets (T, 3) mm and J (T, 3, C) mm/mm at strokes (C,) mm: one batched evaluation of 2C + 1 points."""
        s = np.asarray(strokes, float)
        C = s.size
        h = FD_STEP * 2.0 * self._half
        points = np.vstack([s, s + np.diag(h), s - np.diag(h)])
        values = self.predict(points)
        J = (values[1:C + 1] - values[C + 1:]) / (2.0 * h)[:, None, None]  # (C, T, 3)
        return values[0], np.moveaxis(J, 0, 2)

    def validation_error_mm(self) -> float:
        """The largest distance (mm; its `components`) between the prediction and the solves at the held-out
        strokes."""
        d, k = self.data, self.components
        if not len(d.held_strokes):
            return float("nan")
        return float(np.max(np.linalg.norm((self.predict(d.held_strokes) - d.held_targets)[:, :, :k], axis=2)))

    @property
    def knows_layer(self) -> bool:
        return self._layer_rbf is not None

    def layer_at(self, strokes: np.ndarray) -> np.ndarray:
        """The slab's layer in-plane (N2, 2) mm at strokes (C,) mm (one row per 2-D node)."""
        return self._layer_rbf(self._scaled(np.asarray(strokes, float))).reshape(-1, 2)

    def layer_error_mm(self) -> float:
        """The largest distance (mm) of a layer node between the prediction and the slab at the held-out strokes."""
        d = self.data
        if d.held_layer is None or not len(d.held_strokes):
            return float("nan")
        predicted = self._layer_rbf(self._scaled(d.held_strokes)).reshape(d.held_layer.shape)
        return float(np.max(np.linalg.norm(predicted - d.held_layer, axis=2)))

    def target_map(self, target: int):
        """The `control.models.TargetMap` of one target: strokes → (position (k,), J (k, C)), k = `components`."""
        k = self.components

        def answer(strokes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            y, J = self.answer(strokes)
            return y[target, :k], J[target, :k]

        return answer
