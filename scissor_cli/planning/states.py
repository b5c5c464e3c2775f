"""Deformed states over the cups' strokes: the equilibrium cache and the stroke grid (docs/model.md §7).

The planner judges corridors on full nonlinear equilibria, not on a
linearisation: each sampled stroke vector is solved by Newton
(`solvers.equilibrium`), warm-started from the nearest solved one, and kept.
The grid orders strokes outwards from rest so that every solve starts close.
"""

from __future__ import annotations

import itertools
import time
from typing import Optional

import numpy as np

from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.scene.scene import Scene
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.equilibrium import solve_equilibrium


class StateCache:
    """Equilibria (N, 2) of a tissue for cup strokes (C,) mm, each solved once.

    A new stroke is solved by Newton warm-started from the nearest solved one
    (stroke distance), so a sweep ordered outwards from zero is a chain of
    small load steps. Zero strokes are the rest state without a solve. Share
    one cache between the targets of a scene to solve each stroke once.
    """

    def __init__(self, tissue: Tissue, tol: float = 1e-9):
        self.tissue = tissue
        self.tol = tol
        self._states: dict[tuple[float, ...], np.ndarray] = {}
        self.failures: dict[tuple[float, ...], str] = {}
        self.solves = 0
        self.solve_time_s = 0.0
        zero = (0.0,) * tissue.n_cups
        self._states[zero] = tissue.rest

    @staticmethod
    def key(strokes) -> tuple[float, ...]:
        # Round so that a grid value reached twice by float arithmetic is one state.
        return tuple(float(v) for v in np.round(np.asarray(strokes, float), 9))

    def state(self, strokes) -> Optional[np.ndarray]:
        """Node positions (N, 2) at the strokes, or None if the solve failed (see `failures`)."""
        k = self.key(strokes)
        if k in self._states:
            return self._states[k]
        if k in self.failures:
            return None
        s = np.array(k)
        known = np.array(list(self._states))
        near = known[np.argmin(np.linalg.norm(known - s, axis=1))]
        t0 = time.perf_counter()
        self.solves += 1
        try:
            x = solve_equilibrium(self.tissue, s, start=self._states[tuple(near)], start_strokes=near, tol=self.tol).x
        except SolverError as exc:
            self.failures[k] = str(exc)
            return None
        finally:
            self.solve_time_s += time.perf_counter() - t0
        self._states[k] = x
        return x


def _values_per_cup(n_cups: int, samples: int) -> int:
    # A tensor grid grows as n^C, so several cups get a coarse grid and rely on the refinement.
    return samples if n_cups == 1 else max(5, int(np.ceil(np.sqrt(samples))) + 2)


def stroke_grid(scene: Scene, samples: int) -> np.ndarray:
    """Stroke samples (S, C) mm over every cup's range, zero included, nearest zero first.

    One cup gets `samples` values; several cups a coarse tensor grid of
    max(5, ⌈√samples⌉ + 2) values each (a refinement follows the search).
    """
    n = _values_per_cup(len(scene.cups), samples)
    axes = []
    for cup in scene.cups:
        v = np.linspace(cup.stroke_min_mm, cup.stroke_max_mm, n)
        if cup.stroke_min_mm <= 0 <= cup.stroke_max_mm:
            v = np.union1d(v, [0.0])
        axes.append(v)
    grid = np.array(list(itertools.product(*axes))).reshape(-1, len(scene.cups))
    # Outwards from rest, so every solve warm-starts from a close neighbour.
    return grid[np.argsort(np.linalg.norm(grid, axis=1), kind="stable")]


def grid_steps(scene: Scene, samples: int) -> np.ndarray:
    """Spacing (C,) mm of `stroke_grid(scene, samples)` along each cup: the refinement's coarse step."""
    n = _values_per_cup(len(scene.cups), samples)
    return np.array([(c.stroke_max_mm - c.stroke_min_mm) / (n - 1) for c in scene.cups])


def clip_strokes(scene: Scene, s: np.ndarray) -> np.ndarray:
    """Strokes s (C,) mm clipped into every cup's [stroke_min_mm, stroke_max_mm]."""
    lo = np.array([c.stroke_min_mm for c in scene.cups])
    hi = np.array([c.stroke_max_mm for c in scene.cups])
    return np.clip(s, lo, hi)
