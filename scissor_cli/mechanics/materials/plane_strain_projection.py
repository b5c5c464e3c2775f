"""Closed-form per-term PSD projection of the 2-D plane-strain tangent (docs/model.md §3).

Used by :func:`scissor_cli.mechanics.materials.evaluate_projected` for
``F`` of shape ``(M, 2, 2)``; returns (M, 4, 4) tangents in kPa.

The projection is done **per energy term**, with closed-form
eigensystems (Smith, de Goes & Kim 2019, "Analytic eigensystems for
isotropic distortion energies"; Kim, de Goes & Smith 2019, "Anisotropic
elasticity for inversion-safety and element rehabilitation"):
``C_proj = proj(C_iso) + proj(C_fiber)``, where ``proj`` clamps negative
eigenvalues to 0. A sum of PSD matrices is PSD, so this is a valid
Newton surrogate, but it is *not* the projection of the sum
``proj(C_iso + C_fiber)`` (that is what :func:`project_psd` computes):
where the fiber term is indefinite (compressed fiber) the two differ.
For ``"neo_hookean"`` (a single term) the two coincide up to round-off.

* Isotropic neo-Hookean term, with ``F = U diag(σ1, σ2) Vᵀ`` (U, V
  rotations, σ1 >= σ2 > 0), ``g = J^(-2/3)``, ``S = σ1² + σ2² + 1``,
  ``s = κ (J − 1) − μ g S / (3 J)`` (the cofactor factor of P). Four
  orthonormal eigenmatrices of ``d²Ψ/dvec(F)²``:

  - twist ``U [[0,−1],[1,0]] Vᵀ/√2``, ``λ = (Ψ_1+Ψ_2)/(σ1+σ2) = μ g + s``
    (≈ 0 and negative in compression: the common case);
  - flip ``U [[0,1],[1,0]] Vᵀ/√2``, ``λ = (Ψ_1−Ψ_2)/(σ1−σ2) = μ g − s``
    (closed form, no 0/0 at σ1 = σ2);
  - two scaling modes ``U diag(z) Vᵀ``, z the eigenvectors of the 2x2
    Hessian of Ψ(σ1, σ2). Written in the basis ``r = U Vᵀ/√2`` (the
    polar rotation: dilation) and ``d = U diag(1,−1) Vᵀ/√2``, that
    block is ``[[m + h, a], [a, m − h]]`` with
    ``m = (Ψ_11+Ψ_22)/2 = μ g (5 S (S−1)/(18 J²) − 1/3) + κ (S−1)/2``,
    ``h = Ψ_12 = μ g (2 − 4 (S−1))/(9 J) + κ (2J − 1)``,
    ``a = (Ψ_11−Ψ_22)/2 = −(σ1² − σ2²) γ/2``,
    ``γ = κ + (5/9) μ g S/J²``; its negative part is taken in closed
    form (no eigenvectors needed).

* Fiber term ``η/2 (I4 − 1)²`` (``"neo_hookean_fiber"``), ``v = F a0``,
  ``t = 2η (I4 − 1)``: on span{e_i ⊗ a0} it is ``t I + 4η v vᵀ``, with
  eigenvalue ``t`` along ``v⊥ ⊗ a0`` and ``t + 4η I4 = 2η (3 I4 − 1)``
  along ``v̂ ⊗ a0``; zero elsewhere. With ``tension_only`` it is zero
  where ``I4 <= 1``. Negative only in fiber compression (``I4 < 1``).

Implementation: ``C_proj = C − Σ_k min(λ_k, 0) e_k e_kᵀ`` over both
terms, so wherever every term is already PSD, ``C_proj`` is ``C``
bit-for-bit. Everything is written in the rotation / reflection parts
of F (``F = Q rot(ω) + R refl(ρ)``, ``σ1,2 = Q ± R``), which needs no
trigonometric functions and only one square root per element.

Invalid rows (psi = +inf: ``J <= 0``, overflow, NaN in F), rows with
``0 < J <= J_FLOOR`` and rows whose closed forms overflow (``|F|``
far beyond any physical value) get :func:`project_psd` of their (clipped,
meaningless) tangent, or 0 where that is not finite. The extra scratch
rows grow the shared workspace to ``_N_ROWS + _N_PROJ_ROWS`` = 63 rows of M.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.mechanics.materials.params import J_FLOOR, _check_F
from scissor_cli.mechanics.materials.plane_strain import (
    _N_ROWS,
    _addmul,
    _eval_linear,
    _eval_neo_hookean,
    _fiber_block,
    _scratch,
    _submul,
    _tangent_from_rows,
)
from scissor_cli.mechanics.materials.psd import project_psd

#: Scratch rows used by _project_rows beyond the _N_ROWS of _eval_neo_hookean.
_N_PROJ_ROWS = 20

_TINY = float(np.finfo(np.float64).tiny)



def _evaluate_projected(F, params, clamp=True):
    """:func:`evaluate_projected`; ``clamp=False`` is a testing hook.

    With ``clamp=False`` the subtracted "negative parts" are the whole
    eigen-terms ``λ_k e_k e_kᵀ``, so for valid rows the returned matrix is
    ``C`` minus its own analytic reconstruction, i.e. ≈ 0: this checks the
    closed forms of the fast path against :func:`evaluate`'s tangent.
    """
    F = _check_F(F, params, dims=(2,))
    M = F.shape[0]
    with np.errstate(all="ignore"):
        if params.model == "linear":
            return _eval_linear(F, params, 2)
        rows = _N_ROWS + _N_PROJ_ROWS
        _scratch(rows, M)  # grow first, so the evaluation below uses this buffer
        psi, P, _ = _eval_neo_hookean(F, params, 2, keep_rows=True)
        S = _scratch(rows, M)
        bad = _project_rows(S, params, psi, clamp)
        C = _tangent_from_rows(S[8:24])
        if bad is not None:
            C[bad] = _fallback_projection(F[bad], params.take(bad))
    return psi, P, C


def _project_rows(S, params, psi, clamp):
    """Subtract the negative eigen-parts of each term from the tangent rows.

    ``S`` is the (``_N_ROWS + _N_PROJ_ROWS``, M) scratch view right after an
    order-2 ``_eval_neo_hookean(..., keep_rows=True)``; its tangent rows
    8-23 (upper triangle) are updated in place. Returns the indices of the
    rows that need :func:`_fallback_projection`, or None.
    """
    mul, add, sub = np.multiply, np.add, np.subtract
    minimum = np.minimum
    kappa = params.kappa
    f0, f1, f2, f3 = S[0:4]
    sq0, sq1, sq2, sq3 = S[4:8]
    H = S[8:24]
    alpha, s, gamma, p03, p12 = S[30], S[32], S[33], S[34], S[35]
    E, Hr, Fh, G = S[24:28]
    J, T2, iJ, t1, t2 = S[28], S[29], S[31], S[36], S[37]
    (Q2, R2, lt, ll, m, h, rad, l2, k1, c0,
     d1, d2, cc, cs, CC, CS, X, Y, Xp, Yp) = S[_N_ROWS:_N_ROWS + _N_PROJ_ROWS]

    sub(p03, p12, out=J)
    np.maximum(J, J_FLOOR, out=iJ)
    np.reciprocal(iJ, out=iJ)
    add(sq0, sq1, out=T2)  # tr FᵀF = σ1² + σ2² = I1 − 1
    T2 += sq2
    T2 += sq3
    # F = E I + Hr [[0,−1],[1,0]] + Fh diag(1,−1) + G [[0,1],[1,0]]
    #   = Q rot(ω) + R refl(ρ),  (E, Hr) = Q (cos ω, sin ω), (Fh, G) = R (cos ρ, sin ρ),
    # Q = (σ1+σ2)/2, R = (σ1−σ2)/2, rot(ω) = U Vᵀ, refl(ρ) = U diag(1,−1) Vᵀ.
    add(f0, f3, out=E)
    E *= 0.5
    sub(f2, f1, out=Hr)
    Hr *= 0.5
    sub(f0, f3, out=Fh)
    Fh *= 0.5
    add(f2, f1, out=G)
    G *= 0.5
    mul(E, E, out=Q2)
    _addmul(Q2, Hr, Hr, t1)
    mul(Fh, Fh, out=R2)
    _addmul(R2, G, G, t1)

    # Twist and flip eigenvalues: μg ± s.
    add(alpha, s, out=lt)
    sub(alpha, s, out=ll)
    # Scaling block [[m+h, a], [a, m−h]] in the (r, d) basis, a = −2QRγ.
    add(T2, 1.0, out=t1)  # I1
    t1 *= T2
    t1 *= iJ
    t1 *= iJ
    t1 *= 5.0 / 18.0
    t1 -= 1.0 / 3.0
    mul(alpha, t1, out=m)
    mul(kappa, T2, out=t1)
    t1 *= 0.5
    m += t1
    mul(T2, -4.0, out=h)
    h += 2.0
    h *= iJ
    h *= alpha
    h *= 1.0 / 9.0
    mul(J, 2.0, out=t1)
    t1 -= 1.0
    t1 *= kappa
    h += t1
    mul(Q2, R2, out=rad)  # rad = sqrt(h² + a²), a² = 4 Q² R² γ²
    mul(gamma, gamma, out=t1)
    rad *= t1
    rad *= 4.0
    mul(h, h, out=t1)
    rad += t1
    np.sqrt(rad, out=rad)

    # Negative parts. Block: with eigenvalues l1 >= l2 and n_i = min(l_i, 0),
    # N = n2 I + k1 (B − l2 I), k1 = (n1 − n2)/(l1 − l2) (0 if l1 = l2).
    sub(m, rad, out=l2)
    add(m, rad, out=k1)  # l1 for now
    if clamp:
        minimum(lt, 0.0, out=lt)
        minimum(ll, 0.0, out=ll)
        minimum(k1, 0.0, out=k1)
        minimum(l2, 0.0, out=c0)
    else:
        np.copyto(c0, l2)
    k1 -= c0  # n1 − n2
    mul(rad, 2.0, out=t1)
    np.maximum(t1, _TINY, out=t1)
    k1 /= t1
    mul(k1, l2, out=t1)
    c0 -= t1  # c0 = n2 − k1 l2;  N_rr = c0 + k1 (m+h), N_dd = c0 + k1 (m−h)
    # Halved coefficients of the (unit-free) outer products below:
    # d1 = (N_rr − n_twist)/2 and d2 = (N_dd − n_flip)/2, with
    # a_r = N_rr/2 = n_twist/2 + d1 and b_d = N_dd/2 = n_flip/2 + d2.
    add(m, h, out=d1)
    d1 *= k1
    d1 += c0
    d1 -= lt
    d1 *= 0.5
    sub(m, h, out=d2)
    d2 *= k1
    d2 += c0
    d2 -= ll
    d2 *= 0.5
    lt *= 0.5  # a_t
    ll *= 0.5  # b_l
    # cos²ω, cos ω sin ω and cos²ρ, cos ρ sin ρ (ρ undefined for R = 0: 45°,
    # where the block is isotropic in the reflection plane anyway).
    np.reciprocal(Q2, out=t1)
    mul(E, E, out=cc)
    cc *= t1
    mul(E, Hr, out=cs)
    cs *= t1
    np.maximum(R2, _TINY, out=t1)
    np.reciprocal(t1, out=t1)
    mul(Fh, Fh, out=CC)
    CC *= t1
    mul(Fh, G, out=CS)
    CS *= t1
    degenerate = R2 < _TINY
    np.copyto(CC, 0.5, where=degenerate)
    np.copyto(CS, 0.0, where=degenerate)
    # Rotation plane (r, twist): X = a_t + δ cos²ω, Y = a_t + δ sin²ω,
    # Z = δ cos ω sin ω with δ = d1; reflection plane (d, flip): X', Y', Z'
    # likewise with b_l, d2 and ρ.
    mul(d1, cc, out=X)
    add(lt, d1, out=Y)
    Y -= X
    X += lt
    cs *= d1  # Z
    mul(d2, CC, out=Xp)
    add(ll, d2, out=Yp)
    Yp -= Xp
    Xp += ll
    CS *= d2  # Z'
    # Cross terms N_rd (r dᵀ + d rᵀ), N_rd = k1 a = −2 k1 γ Q R; the Q R
    # cancels against cos ω cos ρ = E Fh / (Q R) etc.:
    # eu = −k1γ E Fh, ev = −k1γ Hr G, ep = −k1γ (E G − Hr Fh), eq = −k1γ (E G + Hr Fh).
    mul(k1, gamma, out=t1)
    np.negative(t1, out=t1)
    eu, ev, ep, eq = cc, CC, l2, m
    mul(E, Fh, out=eu)
    eu *= t1
    mul(Hr, G, out=ev)
    ev *= t1
    mul(E, G, out=t2)
    mul(Hr, Fh, out=h)
    sub(t2, h, out=ep)
    ep *= t1
    add(t2, h, out=eq)
    eq *= t1
    # Subtract N (upper triangle; row 4i+j = C_ij). With Z = cs, Z' = CS:
    #   N00 = X+X'+2eu  N01 = Z'−Z+ep  N02 = Z+Z'+eq  N03 = X−X'
    #   N11 = Y+Y'−2ev  N12 = Y'−Y     N13 = eq−Z−Z'
    #   N22 = Y+Y'+2ev  N23 = Z−Z'+ep  N33 = X+X'−2eu
    eu *= 2.0
    ev *= 2.0
    add(X, Xp, out=t2)
    H[0] -= t2
    H[0] -= eu
    H[15] -= t2
    H[15] += eu
    add(Y, Yp, out=t2)
    H[5] -= t2
    H[5] += ev
    H[10] -= t2
    H[10] -= ev
    sub(X, Xp, out=t2)
    H[3] -= t2
    sub(Yp, Y, out=t2)
    H[6] -= t2
    sub(CS, cs, out=t2)
    H[1] -= t2
    H[1] -= ep
    H[11] += t2
    H[11] -= ep
    add(cs, CS, out=t2)
    H[2] -= t2
    H[2] -= eq
    H[7] += t2
    H[7] -= eq

    if params.model == "neo_hookean_fiber":
        v0, v1, I4m1, teta, e4 = S[38:43]
        # Fiber block t I + 4η v vᵀ on span{e_i ⊗ a0}: eigenvalues t (v⊥) and
        # t + 4η I4 (v̂). Negative part nf1 I + (nf2 − nf1) v vᵀ / I4.
        if not clamp or (teta < 0.0).any():
            _, _, aa, ab, bb = params._fib
            nf1, nf2, q, I4 = X, Y, Xp, Yp
            add(I4m1, 1.0, out=I4)
            mul(e4, I4, out=nf2)
            nf2 += teta
            np.copyto(nf1, teta)
            if clamp:
                minimum(nf1, 0.0, out=nf1)
                minimum(nf2, 0.0, out=nf2)
            sub(nf2, nf1, out=q)
            np.maximum(I4, _TINY, out=I4)
            q /= I4
            _fiber_block(H, _submul, v0, v1, q, nf1, aa, ab, bb, t2, t1)

    # Rows to hand to the fallback: J <= J_FLOOR, psi = +inf, or anything
    # non-finite in the result (overflow of the closed forms).
    add(H[0], H[1], out=t1)
    for i in (2, 3, 5, 6, 7, 10, 11, 15):
        t1 += H[i]
    good = np.isfinite(t1)
    good &= J > J_FLOOR
    good &= psi < np.inf
    if good.all():
        return None
    return np.flatnonzero(~good)


def _fallback_projection(F, params) -> np.ndarray:
    """PSD projection of evaluate's tangent for rows the closed forms cannot take.

    Each matrix is scaled by its largest entry before :func:`project_psd`
    (the projection is positively homogeneous), so huge finite entries do
    not overflow inside ``eigh``; non-finite matrices become 0.
    """
    _, _, C = _eval_neo_hookean(F, params, 2)
    C[~np.isfinite(C).all(axis=(1, 2))] = 0.0
    scale = np.abs(C).max(axis=(1, 2))
    scale[scale == 0.0] = 1.0
    C /= scale[:, None, None]
    C = project_psd(C)
    C += np.swapaxes(C, 1, 2)  # eigh's V w Vᵀ is symmetric only to round-off
    C *= 0.5 * scale[:, None, None]
    C[~np.isfinite(C).all(axis=(1, 2))] = 0.0
    return C


def _eigensystem(F, params):
    """Reference analytic eigensystems of the two energy terms (for tests).

    Straightforward (allocating, σ-based) evaluation of the closed forms in
    the :func:`evaluate_projected` docstring, independent of its fast path.
    Nonlinear models and ``J > 0`` only (other rows give meaningless values).

    Returns
    -------
    lam_iso : (M, 4)
        Eigenvalues of the isotropic term's tangent: the two scaling modes
        (larger first), twist, flip.
    vec_iso : (M, 4, 4)
        ``vec_iso[e, k]`` is the unit eigenvector (as vec) of ``lam_iso[e, k]``.
    lam_fib : (M, 2)
        Fiber term eigenvalues ``t`` (along ``v⊥ ⊗ a0``) and ``t + 4η I4``
        (along ``v̂ ⊗ a0``); zero for ``"neo_hookean"`` and where
        ``tension_only`` switches the fiber off. The fiber term is zero on
        the orthogonal complement of these two vectors.
    vec_fib : (M, 2, 4)
    """
    if params.model == "linear":
        raise ValueError("_eigensystem is for the nonlinear models")
    F = _check_F(F, params, dims=(2,))
    mu, kappa = params.mu, params.kappa
    with np.errstate(all="ignore"):
        f00, f01, f10, f11 = F[:, 0, 0], F[:, 0, 1], F[:, 1, 0], F[:, 1, 1]
        E, Hr = (f00 + f11) / 2, (f10 - f01) / 2
        Fh, G = (f00 - f11) / 2, (f10 + f01) / 2
        Q, R = np.hypot(E, Hr), np.hypot(Fh, G)
        s1, s2 = Q + R, Q - R
        cw, sw = E / Q, Hr / Q
        zero = R == 0.0
        cr = np.where(zero, 1.0, Fh / np.where(zero, 1.0, R))
        sr = np.where(zero, 0.0, G / np.where(zero, 1.0, R))
        rot = np.stack([cw, -sw, sw, cw], -1)  # vec(U Vᵀ)
        refl = np.stack([cr, sr, sr, -cr], -1)  # vec(U diag(1,−1) Vᵀ)
        D1, D2 = (rot + refl) / 2, (rot - refl) / 2  # vec(U diag(1,0) Vᵀ), vec(U diag(0,1) Vᵀ)
        twist = np.stack([-sw, -cw, cw, -sw], -1) / np.sqrt(2.0)
        flip = np.stack([-sr, cr, cr, sr], -1) / np.sqrt(2.0)

        J = s1 * s2
        g = J ** (-2.0 / 3.0)
        Sg = s1 * s1 + s2 * s2 + 1.0
        lam_twist = mu * g * (1.0 - Sg / (3 * J)) + kappa * (J - 1)
        lam_flip = mu * g * (Sg / (3 * J) + 1.0) - kappa * (J - 1)
        p11 = mu * g * (-1.0 / 3 + 5 * Sg / (9 * s1 * s1)) + kappa * s2 * s2
        p22 = mu * g * (-1.0 / 3 + 5 * Sg / (9 * s2 * s2)) + kappa * s1 * s1
        p12 = mu * g * (2 * Sg / (9 * J) - 2 * (s1 * s1 + s2 * s2) / (3 * J)) + kappa * (2 * J - 1)
        mean, rad = (p11 + p22) / 2, np.hypot((p11 - p22) / 2, p12)
        th = 0.5 * np.arctan2(2 * p12, p11 - p22)
        c, s = np.cos(th), np.sin(th)
        e1 = c[:, None] * D1 + s[:, None] * D2
        e2 = -s[:, None] * D1 + c[:, None] * D2
        lam_iso = np.stack([mean + rad, mean - rad, lam_twist, lam_flip], -1)
        vec_iso = np.stack([e1, e2, twist, flip], 1)

        a0 = params.fiber
        # v and I4 − 1 exactly as evaluate computes them (same tension_only switch).
        v = np.stack([f00 * a0[:, 0] + f01 * a0[:, 1], f10 * a0[:, 0] + f11 * a0[:, 1]], -1)
        I4m1 = v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] - 1.0
        I4 = I4m1 + 1.0
        eta = params.eta * (I4m1 > 0.0) if params.tension_only else params.eta
        t = 2 * eta * I4m1
        vh = v / np.sqrt(I4)[:, None]
        vp = np.stack([-vh[:, 1], vh[:, 0]], -1)
        lam_fib = np.stack([t, t + 4 * eta * I4], -1)
        vec_fib = np.stack([
            (vp[:, :, None] * a0[:, None, :]).reshape(-1, 4),
            (vh[:, :, None] * a0[:, None, :]).reshape(-1, 4),
        ], 1)
    return lam_iso, vec_iso, lam_fib, vec_fib

