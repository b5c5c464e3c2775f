"""Fast 2-D plane-strain kernels: Ψ, P and the tangent on component rows (docs/model.md §3).

Called through :func:`scissor_cli.mechanics.materials.evaluate` for
``F`` of shape ``(M, 2, 2)``. Plane strain: ``F3 = diag(F, 1)``,
``J = det F``, ``I1 = tr(FᵀF) + 1``, ``Ī1 = J^(-2/3) I1``,
``I4 = a0ᵀ FᵀF a0`` with the unit in-plane fiber ``a0`` (M, 2).
``vec(F) = [F00, F01, F10, F11]`` (row-major); P is (M, 2, 2) and the
tangent (M, 4, 4), both in kPa.

Closed forms used (``f = vec F``, ``c = vec cof F = [F11, −F10, −F01, F00]``,
``g = J^(-2/3)``)::

    P   = μ g F + s cof F,            s = κ (J − 1) − μ g I1 / (3 J)
    d²Ψ = μ g I + s Q − (2/3)(μ g/J)(f cᵀ + c fᵀ) + (κ + (5/9) μ g I1/J²) c cᵀ
    fiber, v = F a0, t = 2η (I4 − 1):
    P  += t v a0ᵀ,   d²Ψ += t kron(I2, a0 a0ᵀ) + 4η w wᵀ,  w = vec(v a0ᵀ)

where ``Q = d²J/df²`` (+1 at (0,3),(3,0), −1 at (1,2),(2,1)).

Scratch memory
--------------
The nonlinear models work on ``(M,)`` component rows with elementwise numpy
ufuncs writing into a per-thread scratch buffer that is reused across calls
(``_N_ROWS`` = 43 rows of the largest M seen, ≈3.4 MB at M = 10 000; 63 rows
once :func:`evaluate_projected` has been called). On virtual machines where
the first touch of freshly allocated memory is expensive, allocating the ≈60
(M,) temporaries of a naive version on every call costs several times the
arithmetic; reusing one buffer avoids that (measurements: docs/performance.md).
Only the returned arrays are new. :func:`release_workspace` frees the buffer.
"""

from __future__ import annotations

import threading

import numpy as np

from scissor_cli.mechanics.materials.params import J_FLOOR

# --------------------------------------------------------------------------
# scratch memory
# --------------------------------------------------------------------------


class _Workspace(threading.local):
    buf: np.ndarray | None = None


_WS = _Workspace()


def _scratch(rows: int, M: int) -> np.ndarray:
    """A (rows, M) view of this thread's reusable scratch buffer.

    Reusing one buffer (grown to the largest M seen) keeps the evaluation on
    already-mapped pages; see the module docstring for why that matters.
    """
    buf = _WS.buf
    if buf is None or buf.shape[0] < rows or buf.shape[1] < M:
        r = max(rows, 0 if buf is None else buf.shape[0])
        m = max(M, 0 if buf is None else buf.shape[1])
        buf = np.empty((r, m))
        _WS.buf = buf
    return buf[:rows, :M]


def release_workspace() -> None:
    """Free this thread's scratch buffer (it is re-created on demand)."""
    _WS.buf = None




def _eval_linear(F, params, order):
    mu = params.mu
    lam = params.lam
    e00 = F[:, 0, 0] - 1.0
    e11 = F[:, 1, 1] - 1.0
    e01x2 = F[:, 0, 1] + F[:, 1, 0]  # 2 ε01
    tr = e00 + e11
    psi = mu * (e00 * e00 + e11 * e11 + 0.5 * e01x2 * e01x2) + 0.5 * lam * tr * tr
    if order == 0:
        return psi, None, None
    P = np.empty(F.shape)
    ltr = lam * tr
    P[:, 0, 0] = 2.0 * mu * e00 + ltr
    P[:, 1, 1] = 2.0 * mu * e11 + ltr
    shear = mu * e01x2
    P[:, 0, 1] = shear
    P[:, 1, 0] = shear
    if order == 1:
        return psi, P, None
    C = np.zeros((F.shape[0], 4, 4))
    d = 2.0 * mu + lam
    C[:, 0, 0] = d
    C[:, 3, 3] = d
    C[:, 0, 3] = lam
    C[:, 3, 0] = lam
    C[:, 1, 1] = mu
    C[:, 2, 2] = mu
    C[:, 1, 2] = mu
    C[:, 2, 1] = mu
    return psi, P, C


# Scratch rows used by _eval_neo_hookean: 0-3 F components, 4-7 their
# squares, 8-23 tangent (row 4i+j = C_ij), 24-27 stress (row 2i+j = P_ij),
# 28-42 intermediates. After an order-2 evaluation (what _project_rows
# relies on): 30 μ g, 32 s, 33 γ = κ + (5/9) μ g I1/J²,
# 34 F00 F11, 35 F01 F10, and for the fiber model 38-39 v = F a0,
# 40 I4 − 1, 41 t = 2 η_eff (I4 − 1), 42 4 η_eff; 24-29, 31, 36, 37 are free.
_N_ROWS = 43


def _addmul(target, x, y, tmp):
    np.multiply(x, y, out=tmp)
    target += tmp


def _submul(target, x, y, tmp):
    np.multiply(x, y, out=tmp)
    target -= tmp


def _eval_neo_hookean(F, params, order, keep_rows=False):
    """Ψ, P and C of the neo-Hookean models (see :func:`evaluate`).

    With ``keep_rows`` (order 2 only) the tangent is not copied out: the
    third result is the (``_N_ROWS``, M) scratch view itself, whose rows hold
    the tangent and the intermediates listed at ``_N_ROWS``. It is valid
    until the next call that uses the scratch buffer.
    """
    M = F.shape[0]
    fiber = params.model == "neo_hookean_fiber"
    mu = params.mu
    kappa = params.kappa
    mul, add, sub = np.multiply, np.add, np.subtract

    S = _scratch(_N_ROWS, M)
    Fr = S[0:4]
    f0, f1, f2, f3 = Fr
    sq0, sq1, sq2, sq3 = S[4:8]
    H = S[8:24]
    Pr = S[24:28]
    J, I1, alpha, iJ, s, aIJ, p03, p12, t1, t2, v0, v1, I4m1, teta, e4 = S[28:43]

    # One transposed copy gives contiguous component rows, so every later
    # op runs on unit-stride data.
    np.copyto(Fr.T, F.reshape(M, 4))
    mul(f0, f3, out=p03)
    mul(f1, f2, out=p12)
    sub(p03, p12, out=J)
    mul(f0, f0, out=sq0)
    mul(f1, f1, out=sq1)
    mul(f2, f2, out=sq2)
    mul(f3, f3, out=sq3)
    add(sq0, sq1, out=I1)
    I1 += sq2
    I1 += sq3
    I1 += 1.0
    # J.max() < inf also routes overflowed/NaN rows to the slow path below.
    all_valid = M == 0 or (J.min() > 0.0 and J.max() < np.inf)

    np.maximum(J, J_FLOOR, out=iJ)
    # exp(log(.)) beats np.power and np.cbrt for J^(-2/3) on this numpy build.
    np.log(iJ, out=alpha)
    alpha *= -2.0 / 3.0
    np.exp(alpha, out=alpha)
    alpha *= mu  # μ J^(-2/3)
    np.reciprocal(iJ, out=iJ)  # 1 / max(J, J_FLOOR)

    psi = mul(alpha, I1)
    mul(mu, 3.0, out=t1)
    psi -= t1
    sub(J, 1.0, out=s)  # J - 1 for now; becomes s in the stress block
    mul(s, s, out=t1)
    t1 *= kappa
    psi += t1
    psi *= 0.5

    if fiber:
        a, b, aa, ab, bb = params._fib
        mul(f0, a, out=v0)  # v = F a0
        _addmul(v0, f1, b, t1)
        mul(f2, a, out=v1)
        _addmul(v1, f3, b, t1)
        mul(v0, v0, out=I4m1)
        _addmul(I4m1, v1, v1, t1)
        I4m1 -= 1.0
        if params.tension_only:
            mul(params.eta, I4m1 > 0.0, out=teta)
        else:
            np.copyto(teta, params.eta)
        mul(I4m1, I4m1, out=t1)
        t1 *= teta
        t1 *= 0.5
        psi += t1

    if not all_valid:
        psi[~(J > 0.0)] = np.inf
        psi[np.isnan(psi)] = np.inf  # overflow (|F| ~ 1e154) gives inf·0
    if order == 0:
        return psi, None, None

    # s = κ (J - 1) - μ g I1 / (3 J);  P = μ g F + s cof F
    s *= kappa
    mul(alpha, I1, out=aIJ)
    aIJ *= iJ
    mul(aIJ, 1.0 / 3.0, out=t1)
    s -= t1
    P00, P01, P10, P11 = Pr
    mul(alpha, f0, out=P00)
    _addmul(P00, s, f3, t1)
    mul(alpha, f1, out=P01)
    mul(s, f2, out=t1)
    P01 -= t1
    mul(alpha, f2, out=P10)
    mul(s, f1, out=t1)
    P10 -= t1
    mul(alpha, f3, out=P11)
    _addmul(P11, s, f0, t1)
    if fiber:
        mul(teta, 4.0, out=e4)  # 4 η_eff, for the tangent
        teta *= I4m1
        teta *= 2.0  # t = 2 η_eff (I4 - 1)
        mul(teta, v0, out=t2)  # P += t v a0ᵀ
        _addmul(P00, t2, a, t1)
        _addmul(P01, t2, b, t1)
        mul(teta, v1, out=t2)
        _addmul(P10, t2, a, t1)
        _addmul(P11, t2, b, t1)
    P = np.empty((M, 2, 2))
    np.copyto(P.reshape(M, 4), Pr.T)
    if order == 1:
        return psi, P, None

    # β = -(2/3) μ g / J,  γ = κ + (5/9) μ g I1 / J²  (J, aIJ rows reused)
    beta = J
    mul(alpha, iJ, out=beta)
    beta *= -2.0 / 3.0
    gamma = aIJ
    gamma *= iJ
    gamma *= 5.0 / 9.0
    gamma += kappa
    d = I1  # free scratch from here on, like iJ
    tmp = iJ
    # C_ii: α ± 2β (F00 F11 | F01 F10) + γ c_i²
    mul(beta, p03, out=d)
    d *= 2.0
    d += alpha
    mul(gamma, sq3, out=H[0])
    H[0] += d
    mul(gamma, sq0, out=H[15])
    H[15] += d
    mul(beta, p12, out=d)
    d *= -2.0
    d += alpha
    mul(gamma, sq2, out=H[5])
    H[5] += d
    mul(gamma, sq1, out=H[10])
    H[10] += d
    # u = β (F01 F11 - F00 F10): C01 = u - γ F10 F11, C23 = -u - γ F00 F01
    mul(f1, f3, out=d)
    mul(f0, f2, out=tmp)
    d -= tmp
    d *= beta
    mul(f2, f3, out=H[1])
    H[1] *= gamma
    sub(d, H[1], out=H[1])
    mul(f0, f1, out=H[11])
    H[11] *= gamma
    H[11] += d
    np.negative(H[11], out=H[11])
    # w = β (F10 F11 - F00 F01): C02 = w - γ F01 F11, C13 = -w - γ F00 F10
    mul(f2, f3, out=d)
    mul(f0, f1, out=tmp)
    d -= tmp
    d *= beta
    mul(f1, f3, out=H[2])
    H[2] *= gamma
    sub(d, H[2], out=H[2])
    mul(f0, f2, out=H[7])
    H[7] *= gamma
    H[7] += d
    np.negative(H[7], out=H[7])
    # C03 = s + β (F00² + F11²) + γ F00 F11;  C12 = -s - β (F01² + F10²) + γ F01 F10
    add(sq0, sq3, out=d)
    d *= beta
    d += s
    mul(gamma, p03, out=H[3])
    H[3] += d
    add(sq1, sq2, out=d)
    d *= beta
    d += s
    mul(gamma, p12, out=H[6])
    H[6] -= d

    if fiber:
        # t kron(I, a aᵀ) + 4η w wᵀ, w = vec(v aᵀ): per 2x2 block (rows of F)
        # the block is k a aᵀ with k0 = t + 4η v0², k1 = t + 4η v1², k01 = 4η v0 v1.
        _fiber_block(H, _addmul, v0, v1, e4, teta, aa, ab, bb, d, tmp)

    if keep_rows:
        return psi, P, S
    return psi, P, _tangent_from_rows(H)


def _tangent_from_rows(H) -> np.ndarray:
    """(M, 4, 4) tangents from the upper-triangle rows H (16, M): mirror, then one transposed copy."""
    for lower, upper in ((4, 1), (8, 2), (9, 6), (12, 3), (13, 7), (14, 11)):
        np.copyto(H[lower], H[upper])
    C = np.empty((H.shape[1], 4, 4))
    np.copyto(C.reshape(-1, 16), H.T)
    return C


def _fiber_block(H, accumulate, v0, v1, c, d, aa, ab, bb, k, tmp):
    """H ±= (c v vᵀ + d I) ⊗ a aᵀ on the upper-triangle rows (16, M), v = F a0.

    The fiber tangent (c = 4η, d = t) and its negative part (c = (n2 − n1)/I4,
    d = n1) have this form; `accumulate` is _addmul or _submul; k, tmp scratch rows.
    """
    for (i, j), rows in (((0, 0), (0, 1, 5)), ((1, 1), (10, 11, 15))):
        np.multiply((v0, v1)[i], (v0, v1)[j], out=k)
        k *= c
        k += d
        for row, w in zip(rows, (aa, ab, bb)):
            accumulate(H[row], k, w, tmp)
    np.multiply(v0, v1, out=k)
    k *= c
    for row, w in zip((2, 3, 6, 7), (aa, ab, ab, bb)):
        accumulate(H[row], k, w, tmp)

