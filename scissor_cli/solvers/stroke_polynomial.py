"""The stroke polynomial a tracker's predictor fits to its last equilibria (`tracking.TrackedEquilibrium._fitted`).

x(s0 + d) ≈ x0 + Σ_n (1/n!) A_n[d, …, d]: the exponents of its terms in C
strokes, how many equations a degree needs, the terms at a stroke
increment, and the weights that give the fitted value as a combination of
the remembered data (docs/model.md §6, "Tracking an equilibrium").
"""

from __future__ import annotations

from functools import lru_cache
from itertools import combinations_with_replacement
from math import factorial
from typing import Optional

import numpy as np
import scipy.linalg

#: The predictor's polynomial: degree at most MAX_DEGREE, at most MAX_UNKNOWNS fitted coefficients per dof
#: (two cups: the truth's position fit of degree 5 needs 27 states, the model's Hermite fit of degree 6 twelve).
MAX_DEGREE = 6
MAX_UNKNOWNS = 25


def highest_degree(C: int, exact: bool, have: int,
                   cap: int = MAX_DEGREE) -> Optional[tuple[np.ndarray, np.ndarray, int]]:
    """The highest-degree polynomial (`polynomial`) up to degree `cap` whose equations `have` data covers, or None."""
    best = None
    for p in range(lowest_degree(exact), min(cap, MAX_DEGREE) + 1):
        fit = polynomial(C, exact, p)
        if len(fit[0]) > MAX_UNKNOWNS or fit[2] > have:
            break
        best = fit
    return best


def lowest_degree(exact: bool) -> int:
    """The lowest degree fitted: 2 with the exact tangent (it gives the first-order term), else 1."""
    return 2 if exact else 1


@lru_cache(maxsize=None)
def polynomial(C: int, exact: bool, p: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The predictor's polynomial of degree p in C strokes: (exponents (k, C), 1/e! (k,), equations wanted).

    Degrees from 2 (with the exact tangent) or 1 up to p; Σ_e d^e/e! ∂^e x
    over the exponents e of degree n is the symmetric form (1/n!) A_n[d, …, d],
    so the unknowns fitted are the partial derivatives ∂^e x. Equations: as
    many as unknowns with one stroke, a third more with several.
    """
    first = lowest_degree(exact)
    E = np.array([np.bincount(combo, minlength=C) for n in range(first, p + 1)
                  for combo in combinations_with_replacement(range(C), n)]).reshape(-1, C)
    coefficient = 1.0 / np.prod([[factorial(int(v)) for v in e] for e in E], axis=1)
    k = len(E)
    return E, coefficient, (k if C == 1 else -(-4 * k // 3))


def weights(A: np.ndarray, f: np.ndarray) -> np.ndarray:
    """w (m,) = f pinv(A) for the fit's equations A (m, k) and the terms f (k,) at the move: the min-norm lstsq
    of Aᵀ w = f.

    LAPACK's gelsy (rank-revealing QR): half the time of the SVD's gelsd on these few-dozen-row systems.
    """
    return scipy.linalg.lstsq(A.T, f, cond=1e-10, lapack_driver="gelsy", check_finite=False)[0]


def taylor(E: np.ndarray, coefficient: np.ndarray, d: np.ndarray, along: Optional[int] = None) -> np.ndarray:
    """(m, k): the terms d^e/e! at the stroke increments d (m, C), or their derivatives along stroke `along`."""
    if along is None:
        return coefficient * np.prod(d[:, None, :] ** E, axis=2)
    lowered = E.copy()
    lowered[:, along] = np.maximum(lowered[:, along] - 1, 0)  # the terms without this stroke vanish (× e = 0)
    return coefficient * E[:, along] * np.prod(d[:, None, :] ** lowered, axis=2)
