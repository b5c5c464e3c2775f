"""The discrete tissue: mesh + material + boundary conditions (docs/model.md §1–3).

A `Tissue` is everything a solver needs: the FE operators, per-element
material parameters, the Dirichlet nodes (fixed sides and cup-gripped
nodes) and the sparse pattern of the free–free stiffness. It is immutable;
`with_material` gives a tissue that shares the mesh but not the material,
which is how the simulated "true" tissue of a trial differs from the
controller's model.

The same class holds the 3-D slab of docs/model.md §13 (`layer3d`): then
`mesh` is a tetrahedral mesh (nodes (N, 3), `triangles` its tetrahedra
(M, 4)), `ops` are P1 tetrahedra and every (N, 2) below reads (N, 3), every
2N reads 3N. `dim` says which.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from scissor_cli.mechanics import compiled, compiled3d, elements, fem, materials
from scissor_cli.mesh.mesh import Mesh
from scissor_cli.mesh.probe import TargetProbe, stacked_probes
from scissor_cli.scene.scene import Scene


@dataclass(frozen=True)
class Tissue:
    scene: Scene
    mesh: Mesh
    element_E_kPa: np.ndarray  # (M,)
    fiber: np.ndarray  # (M, 2) unit, reference frame
    fixed_nodes: np.ndarray  # (F,)
    cup_nodes: tuple[np.ndarray, ...]  # per cup, gripped nodes
    cup_axes: np.ndarray  # (C, 2) unit
    dirichlet_dofs: np.ndarray  # (Nd,) sorted
    free_dofs: np.ndarray  # (Nf,) sorted
    free_index: np.ndarray  # (2N,) position in free_dofs or -1
    pattern_free_upper: fem.SparsePattern  # K_ff's upper triangle, what a Cholesky factorisation reads
    mass: np.ndarray  # (2N,) kg, lumped
    #: the element on this mesh and material (`mechanics.elements`, docs/model.md §21): where the energy's terms
    #: live beyond the per-element kernels, and the geometry probes and export ask
    element: elements.LinearSimplex
    #: one symbolic factorisation of K_ff's pattern, reused by every solve on this mesh
    factor_cache: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def rest(self) -> np.ndarray:
        return self.mesh.nodes

    @cached_property
    def pattern_free(self) -> fem.SparsePattern:
        """K_ff's pattern, both triangles (the Jacobian's, the grip planner's), built on first use: the solvers read
        only the upper one, and on a 3-D slab this one costs as much to build as the rest of the slab."""
        return free_pattern(self.ops, self.free_index, self.element, upper=False)

    @property
    def ops(self) -> fem.FEOperators:
        """The mesh's FE operators (the element is made on them)."""
        return self.element.ops

    @property
    def params(self) -> materials.MaterialParams:
        """The material per element (the element holds it: `with_material` swaps both together)."""
        return self.element.params

    @property
    def element_params(self) -> materials.MaterialParams:
        """What the per-element kernels take (`elements.LinearSimplex.element_params`)."""
        return self.element.element_params

    @property
    def dim(self) -> int:
        """d: 2 for the layer, 3 for the slab."""
        return self.ops.dim

    @property
    def n_cups(self) -> int:
        return len(self.cup_nodes)

    def cup_displacement(self, c: int) -> np.ndarray:
        """Column c of B, as a full vector (2N,): unit stroke of cup c moves its nodes by its axis."""
        d = self.dim
        b = np.zeros(d * self.mesh.n_nodes)
        nodes = self.cup_nodes[c]
        for k in range(d):
            b[d * nodes + k] = self.cup_axes[c, k]
        return b

    def boundary_positions(self, strokes: np.ndarray) -> np.ndarray:
        """Positions of the Dirichlet dofs (Nd,) in mm for cup strokes (C,) in mm."""
        x = self.mesh.nodes.copy()
        for c, nodes in enumerate(self.cup_nodes):
            x[nodes] += strokes[c] * self.cup_axes[c]
        return x.ravel()[self.dirichlet_dofs]

    def apply_strokes(self, x: np.ndarray, strokes: np.ndarray) -> np.ndarray:
        """A copy of positions x (N, 2) with the Dirichlet nodes placed for the strokes."""
        flat = np.array(x, dtype=float).ravel()
        flat[self.dirichlet_dofs] = self.boundary_positions(np.asarray(strokes, float))
        return flat.reshape(-1, self.dim)

    def probe(self, points: np.ndarray, extrapolate: bool = False) -> TargetProbe:
        """The probe of rest points (K, d) mm (`mesh.probe.target_positions` carries it).

        A point at a body's lesion (its centre, as the scene gives it) stands
        for the lesion, which is carried as its region's mean
        (`LinearSimplex.mean_probe`; docs/model.md §21, "The lesion is its
        region's mean"): the needle's friction acts along a line through the
        lesion, and the displacement at a point on that line has no limit
        under refinement, the region's mean has. Any other point, and every
        point of the layer and the slab (no lesion regions), is carried by
        the element holding it (`extrapolate` as in `LinearSimplex.locate`).
        """
        points = np.atleast_2d(np.asarray(points, float))
        located = self.element.probe(self.rest, points, extrapolate)
        regions = lesion_regions(self)
        if not regions:
            return located
        rows = []
        for k, point in enumerate(points):
            row = TargetProbe(located.tri_idx[k:k + 1], located.nodes[k:k + 1], located.bary[k:k + 1])
            cells = next((cells for center, cells in regions if np.allclose(center, point, rtol=0.0, atol=1e-9)), None)
            if cells is not None:
                row = replace(self.element.mean_probe(self.rest, cells, point), tri_idx=row.tri_idx)
            rows.append(row)
        return stacked_probes(rows)

    def jacobians(self, x: np.ndarray) -> np.ndarray:
        """J = det F (M,) of every element at positions x (N, d)."""
        kernel = compiled.jacobians_2d if self.dim == 2 else compiled3d.jacobians_3d
        return kernel(np.ascontiguousarray(x, dtype=np.float64), self.ops.corners, self.ops.grad_rows)

    def max_feasible_step(self, x: np.ndarray, dx: np.ndarray) -> float:
        """The largest α ≥ 0 (inf if unbounded) keeping every J > 0 along x + α dx, both (N, 2).

        J_e(α) = det(F + α dF) = J + α tr(cof(F)ᵀ dF) + α² det dF is a quadratic
        per element, so the first root is found in closed form, in one compiled
        loop (`compiled.max_feasible_step_2d`). In 3-D it is a cubic:
        `fem.max_feasible_step_3d`, its coefficients from one compiled pass (`compiled3d.feasibility_cubic_3d`).
        """
        if self.dim == 3:
            cubic = compiled3d.feasibility_cubic_3d(np.ascontiguousarray(x, dtype=np.float64),
                                                    np.ascontiguousarray(dx, dtype=np.float64),
                                                    self.ops.corners, self.ops.grad_rows)
            return fem.first_sign_change(*cubic)
        return float(compiled.max_feasible_step_2d(np.ascontiguousarray(x, dtype=np.float64),
                                                   np.ascontiguousarray(dx, dtype=np.float64),
                                                   self.ops.corners, self.ops.grad_rows))

    def energy(self, x: np.ndarray) -> float:
        """Strain energy U (µJ) at positions x (N, 2); +inf if an element is inverted."""
        F = fem.deformation_gradients(self.ops, x)
        psi, _, _ = materials.evaluate(F, self.element_params, order=0)
        U = float(np.dot(psi, self.ops.volume))
        return U + self.element.added_energy(x, F) if np.isfinite(U) else U

    def energy_gradient(self, x: np.ndarray, require_positive_J: bool = False) -> tuple[float, np.ndarray | None]:
        """U (µJ) and ∇U (2N,) in mN at positions x (N, 2).

        With require_positive_J, (inf, None) when an element has J ≤ 0 — one
        evaluation of F for the check and the energy (a solver's trial step).
        """
        if self.compiled:  # the compiled loop, unless an element needs the numpy path's policy
            whole = self.element.compiled_energy_gradient(x)
            if whole is not None:
                return whole
            fast = self._kernels.energy_gradient(self.ops, self.element_params, x)
            if fast is not None:
                return self.element.add_gradient(x, *fast, require_positive_J)
        F = fem.deformation_gradients(self.ops, x)
        if require_positive_J and not np.min(materials.jacobian_det(F), initial=np.inf) > 0:
            return float("inf"), None
        psi, P, _ = materials.evaluate(F, self.element_params, order=1)
        U = float(np.dot(psi, self.ops.volume))
        return self.element.add_gradient(x, U, fem.scatter_vector(self.ops, fem.element_forces(self.ops, P)),
                                         require_positive_J)

    def energy_gradient_stiffness(self, x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """U (µJ), ∇U (2N,) mN and the exact packed element Hessians (21, M) mN/mm at x (N, 2).

        What `energy_gradient` and `element_stiffness` give, in one compiled
        pass where the model has one (the tangent predictor needs all three).
        """
        if self.compiled:
            fast = self._kernels.energy_gradient_stiffness(self.ops, self.element_params, x, False)
            if fast is not None:
                U, grad, Ke = fast
                U, grad = self.element.add_gradient(x, U, grad)
                added = self.element.added_hessians(self.ops, x)
                return U, grad, Ke if added is None else Ke + added
        U, grad = self.energy_gradient(x)
        return U, grad, self.element_stiffness(x)

    def element_stiffness(self, x: np.ndarray, project: bool = False) -> np.ndarray:
        """Element Hessians, packed (21, M) in 2-D, (78, M) in 3-D (`fem.element_matrices`), in mN/mm;
        PSD-projected if asked.

        In 2-D the projection clamps each energy term's closed-form
        eigenvalues (`materials.evaluate_projected`): far cheaper than
        eigendecomposing the 4x4 tangents, and far from equilibrium most of
        them need it. In 3-D each tetrahedron's 9x9 tangent is clamped
        (`compiled3d.project_matrix`; `materials.psd` on the numpy path).
        """
        Ke = self._kernels.element_stiffness(self.ops, self.element_params, x, project) if self.compiled else None
        if Ke is None:
            F = fem.deformation_gradients(self.ops, x)
            if project:
                C = materials.evaluate_projected(F, self.element_params)[2]
            else:
                C = materials.evaluate(F, self.element_params, order=2)[2]
            Ke = fem.element_matrices(self.ops, C)
        if project:  # projected: an element's coupling alone is PSD (the nodal p̄ ∂²v is left out)
            return Ke
        added = self.element.added_hessians(self.ops, x)
        return Ke if added is None else Ke + added

    def stiffness_free(
        self, x: np.ndarray, project: bool = False, Ke: np.ndarray | None = None, upper: bool = False
    ) -> sp.csr_matrix:
        """K_ff (Nf, Nf), the Hessian over free dofs, or only its upper triangle.

        From the packed element Hessians Ke (21, M) if given.
        """
        pattern = self.pattern_free_upper if upper else self.pattern_free
        K = pattern.assemble(self.element_stiffness(x, project) if Ke is None else Ke)
        self.element.add_tangent(x, pattern, K.data, self.free_index, project)
        return K

    def stiffness_times(self, x: np.ndarray, v: np.ndarray, Ke: np.ndarray | None = None) -> np.ndarray:
        """K v (dN,) for a full vector v (dN,), element by element without assembling K.

        Ke (21 or 78, M), the exact packed element Hessians at x, saves evaluating them again.
        """
        Ke = self.element_stiffness(x) if Ke is None else Ke
        out = np.empty(v.size)  # one compiled pass (`compiled.packed_times`)
        compiled.packed_times(np.ascontiguousarray(Ke, dtype=np.float64), self.ops.corners,
                              np.ascontiguousarray(v, dtype=np.float64), out)
        return self.element.add_times(x, v, out)

    def stiffness_times_near(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """K v (dN,) for a v (dN,) that is zero but on a few nodes (a cup's unit stroke): the same product as
        `stiffness_times`, from the Hessians of only the elements touching those nodes (no other adds to it)."""
        d = self.dim
        nodes = np.zeros(self.mesh.n_nodes, bool)
        nodes[np.any(v.reshape(-1, d) != 0.0, axis=1)] = True
        touching = np.flatnonzero(nodes[self.ops.corners].any(axis=0))
        if not self.compiled:
            return self.stiffness_times(x, v)
        ops = fem.take_elements(self.ops, touching)
        Ke = self._kernels.element_stiffness(ops, self.element_params.take(touching), x, False)
        if Ke is None:  # an element it cannot take: the numpy path says why
            return self.stiffness_times(x, v)
        added = self.element.added_hessians(ops, x, touching)
        Ke = Ke if added is None else Ke + added
        out = np.empty(v.size)
        compiled.packed_times(Ke, ops.corners, np.ascontiguousarray(v, dtype=np.float64), out)
        return self.element.add_times(x, v, out)

    def force_scale(self, grad: np.ndarray) -> float:
        """A force (mN) to make residuals relative: the Dirichlet reactions.

        Floored at 1e-3·E·h·L (about the reaction of a 0.1 mm stroke), so
        a tiny stroke does not ask for a residual below round-off.
        """
        reactions = grad[self.dirichlet_dofs]
        return max(math.sqrt(float(reactions @ reactions)), self.force_floor)

    @cached_property
    def compiled(self) -> bool:
        """Whether gradient and stiffness run in compiled loops: `mechanics.compiled` (2-D) or `compiled3d`,
        neo-Hookean."""
        return self._kernels is not None

    @cached_property
    def _kernels(self):
        """The compiled loops' module for this dimension and material, or None (the numpy path serves)."""
        return next((m for m in (compiled, compiled3d) if m.supports(self.ops, self.params)), None)

    @cached_property
    def force_floor(self) -> float:
        """1e-3·E_max·h·L in mN (L the layer's largest extent): the floor of `force_scale`.

        In 3-D h is the slab's height.
        """
        extent = np.ptp(self.mesh.nodes, axis=0)
        size = float(extent[:2].max())
        h = self.ops.thickness_mm if self.dim == 2 else float(extent[2])
        return 1e-3 * float(self.element_E_kPa.max()) * h * size

    def with_material(
        self,
        E_scale: float | np.ndarray = 1.0,
        nu: float | None = None,
        eta_kPa: float | None = None,
        fiber_angle_rad: float | None = None,
    ) -> "Tissue":
        """The same mesh and boundary with other material constants (the trials' "true" tissue).

        E_scale multiplies the per-element E (scalar or (M,) for heterogeneity).
        fiber_angle_rad: the fibers' angle in the plane (a body's 3-D field is
        turned about z by its difference from the scene's angle).
        """
        m = self.scene.material
        fiber = self.fiber
        if fiber_angle_rad is not None and fiber.shape[1] == 3:  # a body's field (uniform or radial): turned about z
            turn = fiber_angle_rad - m.fiber_angle_rad
            c, s = np.cos(turn), np.sin(turn)
            fiber = np.column_stack([c * fiber[:, 0] - s * fiber[:, 1], s * fiber[:, 0] + c * fiber[:, 1], fiber[:, 2]])
        elif fiber_angle_rad is not None:
            fiber = np.tile([np.cos(fiber_angle_rad), np.sin(fiber_angle_rad)], (self.mesh.n_elements, 1))
        E = self.element_E_kPa * E_scale
        params = materials.material_params(
            m.model,
            E,
            m.nu if nu is None else nu,
            (m.eta_kPa if eta_kPa is None else eta_kPa) if m.model == "neo_hookean_fiber" else 0.0,
            fiber,
            m.tension_only,
        )
        return replace(self, element_E_kPa=E, fiber=fiber, element=self.element.with_material(params))


class BoundaryError(ValueError):
    """The boundary conditions cannot be built on this mesh."""


def lesion_regions(tissue: Tissue) -> list[tuple[np.ndarray, np.ndarray]]:
    """(centre (d,) mm, the region's elements (R,)) of each scene target whose region the mesh tags (a body's
    lesions: `mesh.body_mesh.BodyMesh.region_names`); empty for the layer and the slab."""
    names = getattr(tissue.mesh, "region_names", None)
    if names is None:
        return []
    out = []
    for target in tissue.scene.targets:
        if target.name in names:
            cells = np.flatnonzero(tissue.mesh.region == names.index(target.name))
            if cells.size:
                out.append((np.asarray(target.rest, float), cells))
    return out


def scene_material(scene: Scene, element_obstacle: np.ndarray, model: str | None = None):
    """Per-element E (M,) kPa, fibers (M, 2) and `MaterialParams` of a scene's material.

    element_obstacle (M,): the obstacle index of each element, -1 for plain
    tissue (obstacles may be stiffer); `model` overrides the material model.
    Shared by the 2-D layer and the 3-D slab (fibers lie in the layer's plane).
    """
    m = scene.material
    model = model or m.model
    factors = np.array([o.stiffness_factor for o in scene.obstacles] + [1.0])
    element_E = m.E_kPa * factors[element_obstacle]  # index -1 picks the trailing 1.0
    fiber = np.tile([np.cos(m.fiber_angle_rad), np.sin(m.fiber_angle_rad)], (len(element_obstacle), 1))
    params = materials.material_params(
        model, element_E, m.nu, m.eta_kPa if model == "neo_hookean_fiber" else 0.0, fiber, m.tension_only
    )
    return element_E, fiber, params


def build_tissue(scene: Scene, mesh: Mesh, model: str | None = None, element: str = "p1") -> Tissue:
    """The discrete tissue of a scene on a mesh; `model` overrides the material model; `element`: "p1" or
    "nodal" (docs/model.md §21)."""
    element_E, fiber, params = scene_material(scene, mesh.element_obstacle, model)
    fixed = mesh.boundary_nodes_on_sides(scene.fixed_sides)
    if len(fixed) == 0:
        raise BoundaryError(f"no mesh node lies on the fixed side(s) {list(scene.fixed_sides)}")
    cup_nodes = []
    for cup in scene.cups:
        nodes = mesh.boundary_nodes_near(cup.contact, cup.radius_mm)
        if len(nodes) == 0:
            raise BoundaryError(f"cup {cup.name!r} grips no boundary node within {cup.radius_mm} mm "
                                f"of {cup.contact.tolist()}")
        clash = np.intersect1d(nodes, fixed)
        if len(clash):
            raise BoundaryError(f"cup {cup.name!r} grips {len(clash)} node(s) of a fixed side; "
                                "move it or shrink radius_mm")
        for other, prev in zip(scene.cups, cup_nodes):
            if len(np.intersect1d(nodes, prev)):
                raise BoundaryError(f"cups {other.name!r} and {cup.name!r} grip the same nodes")
        cup_nodes.append(nodes)
    held = np.unique(np.concatenate([fixed, *cup_nodes]))
    dirichlet = np.sort(np.concatenate([2 * held, 2 * held + 1]))
    ops = fem.build_operators(mesh, scene.thickness_mm)
    cup_axes = np.array([c.axis for c in scene.cups]).reshape(-1, 2)
    return tissue_from_boundary(scene, mesh, ops, (element_E, fiber, params), fixed, cup_nodes, cup_axes, dirichlet,
                                element)


def free_pattern(ops: fem.FEOperators, free_index: np.ndarray, element: elements.LinearSimplex,
                 upper: bool) -> fem.SparsePattern:
    """K_ff's pattern (or its upper triangle): the elements' pairs, joined by the element's extra ones if any."""
    return fem.sparse_pattern(ops, free_index, upper=upper, extra=element.extra_pairs(free_index, upper))


def tissue_from_boundary(scene: Scene, mesh, ops, material, fixed, cup_nodes, cup_axes, dirichlet,
                         element: str = "p1") -> Tissue:
    """The `Tissue` once its Dirichlet dofs are known: the free-dof index, the K_ff patterns, the mass.

    material: (element_E (M,) kPa, fiber (M, 2), MaterialParams) as from
    `scene_material`; dirichlet (Nd,): every held dof, sorted. Shared by the
    2-D layer and the 3-D slab (whose held dofs depend on its options). `element`: "p1" or "nodal".
    """
    element_E, fiber, params = material
    formulation = elements.build(element, ops, params)
    n_dofs = mesh.nodes.size
    free_mask = np.ones(n_dofs, bool)
    free_mask[dirichlet] = False
    free = np.flatnonzero(free_mask)
    free_index = np.full(n_dofs, -1, np.int64)
    free_index[free] = np.arange(len(free))
    return Tissue(
        scene=scene,
        mesh=mesh,
        element_E_kPa=element_E,
        fiber=fiber,
        fixed_nodes=fixed,
        cup_nodes=tuple(cup_nodes),
        cup_axes=cup_axes,
        dirichlet_dofs=dirichlet,
        free_dofs=free,
        free_index=free_index,
        pattern_free_upper=free_pattern(ops, free_index, formulation, upper=True),
        mass=fem.lumped_mass(ops, scene.material.density_kg_per_mm3),
        element=formulation,
    )
