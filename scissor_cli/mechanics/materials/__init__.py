"""Hyperelastic material models for P1 elements: 2-D plane strain and 3-D (docs/model.md §3).

Units: stresses and moduli in kPa; energy densities in kPa = µJ/mm³ (multiply
by the element volume in mm³, ``h * A_e`` for a plane-strain triangle of
thickness h, to get the element energy in µJ).

Conventions
-----------
* ``F`` is a stack of deformation gradients, shape ``(M, d, d)`` with
  d = 2 (plane strain) or d = 3, ``F[e, i, j] = dx_i/dX_j``; every kernel
  dispatches on the shape.
* ``vec(F)`` is row-major, ``F.reshape(M, d*d)``: ``[F00, F01, F10, F11]``
  in 2-D; tangents are ``(M, d², d²)`` in that ordering,
  ``C[e] = d²Ψ/dvec(F)²`` (symmetric). P has the shape of F.
* ``J = det F``, ``Ī1 = J^(-2/3) I1``, ``I4 = a0ᵀ FᵀF a0`` with the unit
  reference fiber ``a0`` of each element. 3-D: ``I1 = tr(FᵀF)``. Plane
  strain: ``F3 = diag(F, 1)``, so ``I1 = tr(FᵀF) + 1``.
* Fibers are (M, 3) or in-plane (M, 2); in 3-D a 2-component ``a0`` means
  ``(a0, 0)`` (a layer's fiber ``(cos θ, sin θ, 0)``), 2-D needs (M, 2).

Models
------
* ``"linear"``: ``ε = sym(F − I)``, ``Ψ = μ ε:ε + λ/2 (tr ε)²`` with the
  Lamé ``λ = E ν / ((1+ν)(1−2ν)) = κ − 2μ/3``. Defined for every F (it is
  not rotation invariant — by design of small-strain theory).
* ``"neo_hookean"``: ``Ψ = μ/2 (Ī1 − 3) + κ/2 (J − 1)²``,
  ``μ = E/(2(1+ν))``, ``κ = E/(3(1−2ν))``.
* ``"neo_hookean_fiber"``: the above ``+ η/2 (I4 − 1)²``; with
  ``tension_only`` the fiber term acts only where ``I4 > 1`` (its tangent
  jumps across ``I4 = 1``).

At ``F = I`` all models have zero energy and zero stress, and the
neo-Hookean tangent equals the linear one (small-strain consistency). For
``F = diag(F2, 1)`` the 3-D kernels reproduce the plane-strain Ψ, the
in-plane block of P and the in-plane 4x4 block of the tangent.

The neo-Hookean tangent is indefinite in much of the working range (its
twist eigenvalue ``μ g + s`` is ≈ 0 and negative under compression; the
fiber term is indefinite in fiber compression). For Newton's method
:func:`evaluate_projected` returns Ψ, P and a PSD surrogate tangent built
in 2-D from closed-form eigensystems of each energy term (no ``eigh``),
in 3-D by a batched ``eigh`` of the whole tangent;
:func:`project_psd` is the general (slower) batched projection of any
symmetric stack.

Inverted elements
-----------------
The nonlinear models are undefined for ``J <= 0``. There ``energy_density``
returns ``+inf`` (never NaN); stress and tangent are computed with J clipped
to ``J_FLOOR`` in the singular factors so they stay finite, but they are
meaningless. Callers must check ``jacobian_det(F) > 0`` (the solvers do) or
test ``np.isinf(psi)``. For ``0 < J < J_FLOOR`` all three outputs are those
at ``J_FLOOR`` (finite and huge). Rows whose arithmetic overflows
(``|F|`` around 1e154 or more) or whose F holds NaN also get ``psi = +inf``;
their P and C may then be inf/NaN. No floating-point warnings are ever
emitted. The ``linear`` model has no invalid region (NaN in gives NaN out).
The same policy holds in 2-D and 3-D.

Modules
-------
* :mod:`.params`: :data:`MODELS`, :class:`MaterialParams`, :func:`material_params`.
* :mod:`.evaluation`: the public kernels (:func:`evaluate` and friends),
  dispatching on d.
* :mod:`.plane_strain`: the fast 2-D row kernels and their scratch buffer.
* :mod:`.plane_strain_projection`: closed-form PSD projection in 2-D.
* :mod:`.solid3d`: the 3-D kernels (vectorised numpy).
* :mod:`.psd`: :func:`project_psd`, batched projection by ``eigh``.
"""

from scissor_cli.mechanics.materials.evaluation import (
    energy_density,
    evaluate,
    evaluate_projected,
    jacobian_det,
    stress,
    tangent,
)
from scissor_cli.mechanics.materials.params import J_FLOOR, MODELS, MaterialParams, material_params
from scissor_cli.mechanics.materials.plane_strain import release_workspace
from scissor_cli.mechanics.materials.psd import project_psd

__all__ = [
    "MODELS",
    "J_FLOOR",
    "MaterialParams",
    "material_params",
    "energy_density",
    "stress",
    "tangent",
    "evaluate",
    "evaluate_projected",
    "project_psd",
    "jacobian_det",
    "release_workspace",
]
