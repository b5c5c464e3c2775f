"""Type-II Anderson acceleration of a fixed-point iteration: ADMM-PD's (Zhang et al. 2019; docs/model.md §4) and
the needle's chord steps on a kept factorisation (`insertion.chord`, docs/model.md §12).

With `anderson_memory = m > 0` the solver treats one ADMM iteration as a
fixed-point map G(z, u) (x depends only on z and u) and extrapolates over
the last m differences, in the W-weighted norm. The safeguard is the
solver's: the combined residual ‖W f‖² = ‖W (z' − z)‖² + ‖W (D x − z')‖² of
an accelerated point must be below that of the last accepted point, else
the plain ADMM iterate from that point is taken instead and the history is
cleared (also cleared when the weights change). An accelerated z may have
det ≤ 0: the local step always warm-starts from the last plain z (valid,
cached). Anderson pays a little per iteration for far fewer iterations, and
helps most where plain ADMM is slowest.

The chord steps x ↦ x + d(x) of a 3-D body or slab contract slowly on a
kept factor of an older state; there G(x) = x + d, f = d (no weights), and
each accelerated step must contract as a chord step must, else the plain
one is taken (`ChordSolver.converge`).
"""

from __future__ import annotations

import numpy as np


class Anderson:
    """Type-II Anderson acceleration of a fixed-point map s ↦ G(s) on flat vectors (n,), weighted norm.

    memory: how many past differences enter the extrapolation.
    """

    def __init__(self, memory: int):
        self.m = memory
        self.reset()

    def reset(self):
        """Forget the history: the next `step` returns its g unchanged."""
        self.dF, self.dG = [], []
        self.f_prev = self.g_prev = None

    @property
    def extrapolating(self) -> bool:
        """Whether the last `step` extrapolated (it had a past difference), rather than returning g as it was."""
        return bool(self.dF)

    def step(self, g: np.ndarray, f: np.ndarray) -> np.ndarray:
        """g = G(s) and the weighted residual f = W (G(s) − s) of an accepted point → the next s."""
        if self.f_prev is not None:
            self.dF.append(f - self.f_prev)
            self.dG.append(g - self.g_prev)
            if len(self.dF) > self.m:
                self.dF.pop(0)
                self.dG.pop(0)
        self.f_prev, self.g_prev = f, g
        if not self.dF:
            return g
        dF = np.stack(self.dF)  # (m, n)
        gram = dF @ dF.T
        # A tiny Tikhonov term keeps nearly dependent differences from blowing up γ.
        gram[np.diag_indices_from(gram)] += 1e-10 * np.trace(gram) + 1e-300
        gamma = np.linalg.solve(gram, dF @ f)
        return g - gamma @ np.stack(self.dG)
