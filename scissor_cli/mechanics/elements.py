"""The elements, a class each behind one interface (docs/model.md §21).

An element answers two kinds of question:

* **Its geometry**, what probes, the needle, point location and export ask:
  nodes per element, shape functions and their gradients, the quadrature,
  which element holds a point, and the meshio cell type.
* **Where its energy's terms live**, what `Tissue` and the solvers ask:
  the parameters the per-element kernels take, and what it adds beyond
  them to the energy, the gradient, the element Hessians, the assembled
  tangent (with the extra sparse pairs that needs) and the tangent's
  products. `per_element` says whether every term is a sum over elements,
  which ADMM's splitting and the tracker's cup-local products need.

scissor's two elements are siblings on the same linear simplices
(`LinearSimplex`: d + 1 nodes, N_a = λ_a, constant ∇N, one quadrature point
at the centroid): `P1` keeps every term per element; `Nodal` moves the
volumetric term and half the deviatoric one onto the nodes (the math in
`mechanics.nodal`). A new element is a new class here and a name in
`ELEMENTS`, not a branch in each layer.

Every instance is made for one mesh's operators and one material
(`build`); `with_material` gives the same element for another material,
sharing what depends only on the mesh. Arrays as in `Tissue`: positions x
(N, d) mm, vectors (dN,), packed element Hessians (21 or 78, M) mN/mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import ClassVar

import numpy as np

from scissor_cli.mechanics import fem, materials, nodal, nodal_gradient
from scissor_cli.mesh.mesh import meshio_cell_type
from scissor_cli.mesh.probe import TargetProbe, locate_in_simplices, probe_points


@dataclass(frozen=True)
class LinearSimplex:
    """What every element on straight linear simplices shares: the geometry, and every term per element.

    ops: the mesh's operators (`fem.simplex_operators`); params: the material per element.
    """

    #: the name `tissue.mesh.element` gives (docs/model.md §21)
    name: ClassVar[str] = ""
    #: whether every energy term is a sum over elements (ADMM can split it; a cup's stroke touches only its elements)
    per_element: ClassVar[bool] = True

    ops: fem.FEOperators
    params: materials.MaterialParams

    # -- geometry ---------------------------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        return self.ops.dim

    @property
    def nodes_per_element(self) -> int:
        """d + 1."""
        return self.dim + 1

    @property
    def cell_type(self) -> str:
        """meshio's name of the cell: "triangle" or "tetra"."""
        return meshio_cell_type(self.dim, self.nodes_per_element)

    @staticmethod
    def shape_functions(bary: np.ndarray) -> np.ndarray:
        """N_a (K, d + 1) at points given by barycentric coordinates (K, d + 1): N_a = λ_a."""
        return np.asarray(bary, float)

    def shape_gradients(self) -> np.ndarray:
        """∂N_a/∂X_j (M, d + 1, d) in 1/mm, constant over each element."""
        return self.ops.grad_n

    def quadrature(self) -> tuple[np.ndarray, np.ndarray]:
        """Points (Q, d + 1) in barycentric coordinates and weights (Q,) summing to 1: the centroid (exact for the
        constant integrands of a linear simplex)."""
        n = self.nodes_per_element
        return np.full((1, n), 1.0 / n), np.ones(1)

    def locate(self, nodes: np.ndarray, points: np.ndarray, extrapolate: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The element (K,) holding each point (K, d) mm of a mesh whose nodes are `nodes` (N, d), and the
        barycentric coordinates (K, d + 1) there (`mesh.probe.locate_in_simplices`; ValueError for a point
        outside, unless `extrapolate`)."""
        return locate_in_simplices(nodes, self.ops.triangles, points, extrapolate=extrapolate)

    @classmethod
    def on(cls, ops: fem.FEOperators, params: materials.MaterialParams) -> "LinearSimplex":
        """The element on a mesh's operators with a material."""
        return cls(ops, params)

    def probe(self, nodes: np.ndarray, points: np.ndarray, extrapolate: bool = False) -> TargetProbe:
        """The probe of rest points (K, d) mm: the element holding each, its nodes and its shape functions there
        (`mesh.probe.target_positions` carries them; `locate` says what a point outside does)."""
        located = probe_points(nodes, self.ops.triangles, points, extrapolate)  # its weights: the coordinates
        return replace(located, bary=self.shape_functions(located.bary))

    def mean_probe(self, nodes: np.ndarray, cells: np.ndarray, center: np.ndarray) -> TargetProbe:
        """The probe (one row) of the mean position over a region, the elements `cells` (R,) of a mesh whose rest
        nodes are `nodes` (N, d) mm, that reads `center` (d,) mm at rest.

        The weights are ∫ N_a dV / V over the region (this element's quadrature and shape functions): the mean of
        the interpolated positions. The region is faceted, so its rest centroid lies off `center` by a fraction
        of an edge: each weight is then scaled by 1 + λ·(1, X_a − center), the least relative change that makes
        the weights sum to 1 and read `center` at rest, so the probe carries any affine map of the region
        exactly, as a point's does. Its `tri_idx` is the region's first element (`Tissue.probe` gives the
        element holding the centre instead). ValueError for an empty region, or one whose centroid is so far off
        `center` that a weight would turn negative.
        """
        cells = np.asarray(cells, np.int64)
        if cells.size == 0:
            raise ValueError("a region's mean needs at least one element")
        points, weights = self.quadrature()
        shape = self.shape_functions(points)  # (Q, d + 1)
        per_corner = (weights @ shape)[None, :] * self.ops.volume[cells, None]  # (R, d + 1) mm³: ∫_e N_a dV
        corners = self.ops.triangles[cells]
        ids, where = np.unique(corners, return_inverse=True)
        w = np.bincount(where.ravel(), per_corner.ravel(), len(ids))
        w /= w.sum()
        center = np.asarray(center, float)
        A = np.vstack([np.ones(len(ids)), (nodes[ids] - center).T])  # (d + 1, P): Σ w = 1, Σ w (X − c) = 0
        lam = np.linalg.solve((A * w) @ A.T, np.r_[1.0, np.zeros(self.dim)] - A @ w)
        w = w * (1.0 + lam @ A)
        if not np.all(w > 0.0):
            raise ValueError(f"the region's centroid is too far from {center.tolist()} mm for its mean to read it")
        return TargetProbe(tri_idx=np.array([cells[0]]), nodes=ids[None, :], bary=w[None, :])

    # -- the energy's terms beyond the per-element kernels (none here) -----------------------------------------
    @property
    def element_params(self) -> materials.MaterialParams:
        """The material the per-element kernels take."""
        return self.params

    def with_material(self, params: materials.MaterialParams) -> "LinearSimplex":
        """The same element on the same mesh with another material."""
        return replace(self, params=params)

    def extra_pairs(self, dof_index: np.ndarray, upper: bool) -> tuple[np.ndarray, np.ndarray] | None:
        """Rows and columns the tangent has beyond the elements' (`fem.sparse_pattern`'s `extra`), or None."""
        return None

    def added_energy(self, x: np.ndarray, F: np.ndarray) -> float:
        """What the element adds to the per-element energy at x (N, d), F (M, d, d) its elements' gradients."""
        return 0.0

    def compiled_energy_gradient(self, x: np.ndarray) -> tuple[float, np.ndarray] | None:
        """U (µJ) and ∇U (dN,) mN of every term in one compiled call, where the element has one; None: the per-element
        kernels' answer plus `add_gradient`'s."""
        return None

    def add_gradient(self, x: np.ndarray, U: float, grad: np.ndarray,
                     require_positive_J: bool = False) -> tuple[float, np.ndarray | None]:
        """U and ∇U (dN,) with the element's terms added; with require_positive_J, (inf, None) where its own
        volumes invert."""
        return U, grad

    def added_hessians(self, ops: fem.FEOperators, x: np.ndarray, elements: np.ndarray | None = None
                       ) -> np.ndarray | None:
        """The element-local part of its terms' Hessian, packed like the kernels' (P, E), on `ops` (the elements
        `elements` of the mesh, all if None), or None."""
        return None

    def add_tangent(self, x: np.ndarray, pattern: fem.SparsePattern, data: np.ndarray, free_index: np.ndarray,
                    project: bool) -> None:
        """Add the tangent's part beyond the element Hessians into K's CSR data on `pattern` (from `extra_pairs`)."""

    def add_times(self, x: np.ndarray, v: np.ndarray, Kv: np.ndarray) -> np.ndarray:
        """Kv (dN,) plus that part times v (dN,)."""
        return Kv


@dataclass(frozen=True)
class P1(LinearSimplex):
    """Linear simplices with every term per element: cheap, and locking as ν → 1/2."""

    name: ClassVar[str] = "p1"


@dataclass(frozen=True)
class Nodal(LinearSimplex):
    """Linear simplices with the volume and a share 1 − α of the deviatoric energy averaged over each node's
    elements (`mechanics.nodal`): they do not lock. `volume` is the mesh's nodal structure, shared by every
    material; the state at the last x is kept (a Newton step asks for it from the gradient, the Hessians, the
    coupling and the products)."""

    name: ClassVar[str] = "nodal"
    per_element: ClassVar[bool] = False

    volume: nodal.NodalVolume
    cache: dict = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def on(cls, ops: fem.FEOperators, params: materials.MaterialParams) -> "Nodal":
        return cls(ops, params, nodal.nodal_volume(ops))

    def with_material(self, params: materials.MaterialParams) -> "Nodal":
        return replace(self, params=params, cache={})

    def with_share(self, element_share: float) -> "Nodal":
        """The element with another α (`nodal.ELEMENT_SHARE`; the benchmark that chose it varies it)."""
        return replace(self, volume=replace(self.volume, element_share=element_share), cache={})

    @property
    def _linear(self) -> bool:
        """Whether the material is small-strain (its nodal volumes linearised)."""
        return self.params.model == "linear"

    @cached_property
    def element_params(self) -> materials.MaterialParams:
        """α times the material's deviatoric part (κ = 0; for `linear` λ − κ = −2μ/3, so its term is
        μ dev ε : dev ε; docs/model.md §21)."""
        p, a = self.params, self.volume.element_share
        return materials.MaterialParams(p.model, a * p.mu, np.zeros_like(p.kappa), a * (p.lam - p.kappa), a * p.eta,
                                        p.fiber, p.tension_only)

    @cached_property
    def averaged_params(self) -> materials.MaterialParams:
        """The material of the nodes' averaged F̄: (1 − α) times the rest-volume average of the elements'
        deviatoric part, their fibers averaged and normalised."""
        p, nv = self.params, self.volume
        share = 1.0 - nv.element_share
        mu = nodal.nodal_average(self.ops, p.mu, nv.rest_volume)
        eta = nodal.nodal_average(self.ops, p.eta, nv.rest_volume)
        fiber = nodal.nodal_average(self.ops, p.fiber, nv.rest_volume)
        norm = np.linalg.norm(fiber, axis=1)
        fiber = np.where(norm[:, None] > 1e-12, fiber / np.maximum(norm, 1e-300)[:, None], np.eye(fiber.shape[1])[0])
        return materials.MaterialParams(p.model, share * mu, np.zeros_like(mu), share * (-2.0 / 3.0) * mu, share * eta,
                                        fiber, p.tension_only)

    @cached_property
    def kappa(self) -> np.ndarray:
        """κ_a (N,) kPa of the nodal volume term."""
        return nodal.nodal_kappa(self.ops, self.params.kappa, self.volume.rest_volume)

    def state(self, x: np.ndarray, F: np.ndarray | None = None) -> nodal.NodalState:
        """The nodal volumes and pressures at x (N, d), kept for the last x."""
        last = self.cache.get("state")
        if last is not None and last[0].shape == x.shape and np.array_equal(last[0], x):
            return last[1]
        F = fem.deformation_gradients(self.ops, x) if F is None else F
        state = nodal.nodal_state(self.ops, self.volume, self.kappa, F, self._linear)
        self.cache["state"] = (np.array(x, dtype=float, copy=True), state)
        return state

    def _averaged(self, x: np.ndarray, order: int, project: bool = False):
        """ψ (N,) weighted by V_a, P (N, d, d) and C (N, d², d²) at the nodes' F̄."""
        return nodal.averaged_material(self.volume, self.averaged_params, x, order, project)

    def _coupling(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """B's data at x and the weights κ_a / V_a of the nodal coupling Bᵀ W B."""
        return nodal.b_data(self.ops, self.volume, self.state(x)), self.kappa / self.volume.rest_volume

    def extra_pairs(self, dof_index: np.ndarray, upper: bool) -> tuple[np.ndarray, np.ndarray]:
        return nodal.pairs(self.volume, dof_index, upper)

    def added_energy(self, x: np.ndarray, F: np.ndarray) -> float:
        return (nodal.energy(self.volume, self.kappa, self.state(x, F))
                + float(self._averaged(x, order=0)[0].sum()))

    def compiled_energy_gradient(self, x):
        """In 3-D, every term in three compiled passes over the mesh (`nodal_gradient.energy_gradient`) where the
        term-by-term path makes seven: the insertion's and the line searches' cost. The state is not kept: a
        tangent at x forms it (`state`)."""
        return nodal_gradient.energy_gradient(self.ops, self.element_params, self.averaged_params,
                                              self.volume.rest_volume, self.kappa, x)

    def add_gradient(self, x, U, grad, require_positive_J=False):
        if not np.isfinite(U):
            return U, grad
        state = self.state(x)
        psi, P, _ = self._averaged(x, order=1)
        U = U + nodal.energy(self.volume, self.kappa, state) + float(psi.sum())
        if require_positive_J and not np.isfinite(U):  # a node's averaged F̄ inverted, as for an element
            return float("inf"), None
        return U, grad + nodal.gradient(self.ops, state) + nodal.averaged_forces(self.volume, P)

    def added_hessians(self, ops, x, elements=None):
        F = fem.deformation_gradients(ops, x)
        state = self.state(x, F) if elements is None else self.state(x).take(elements)
        return nodal.element_hessians(ops, F, state, self._linear)

    def add_tangent(self, x, pattern, data, free_index, project):
        """+ Bᵀ W B and Āᵀ C̄ Ā, the nodal terms' coupling, in the joined pattern's slots."""
        coupling, weight = self._coupling(x)
        C = self._averaged(x, order=2, project=project)[2]
        nodal.add_tangent(self.volume, coupling, weight, C, free_index, pattern, data)

    def add_times(self, x, v, Kv):
        """Kv + (Bᵀ W B + Āᵀ C̄ Ā) v."""
        coupling, weight = self._coupling(x)
        C = self._averaged(x, order=2)[2]
        d = self.dim
        dF = nodal.averaged_gradients(self.volume, v.reshape(-1, d)).reshape(-1, d * d)
        stress = np.einsum("akl,al->ak", C, dF).reshape(-1, d, d)
        return Kv + nodal.coupling_times(self.volume, coupling, weight, v) + nodal.averaged_forces(self.volume, stress)


#: every element by its name in `tissue.mesh.element`
ELEMENTS: dict[str, type[LinearSimplex]] = {cls.name: cls for cls in (P1, Nodal)}


def build(name: str, ops: fem.FEOperators, params: materials.MaterialParams) -> LinearSimplex:
    """The element `name` on a mesh's operators with a material (ValueError naming the allowed names)."""
    if name not in ELEMENTS:
        raise ValueError(f"unknown element {name!r}; allowed values: {', '.join(ELEMENTS)}")
    return ELEMENTS[name].on(ops, params)
