"""The slab as the closed loop's true tissue (`trials.truth: slab`, docs/model.md §13).

The controller keeps its 2-D model; the plant (`control.Plant`) settles the
3-D slab instead, through a `control.TruthView`: the target the camera sees
is the in-plane part of the slab's target at the layer's height, and the
layer's nodes (for the corridor check) are the slab's points at that level
(`slab.layer_probe`). A trial's perturbation reaches the slab as it would
the layer: the E field (one value per 2-D triangle) is carried to the
tetrahedra each triangle became (on a coarser slab plane, the triangle of
the layer that holds the plane triangle's centroid); ν, η and the fiber
angle as they are.

Speed (docs/performance.md, "Slab truth"): the slab is built once per
worker; each target's nominal slab equilibrium at the plan's strokes is
solved once per worker and starts every trial's first, big move (the
perturbed slab is near it: a few chord steps instead of a load
continuation from rest); the truth settles to SLAB_TRUTH_TOL.
"""

from __future__ import annotations

import numpy as np

from scissor_cli.control.plant import TruthPerturbation, TruthView, true_tissue
from scissor_cli.layer3d.slab import SlabSpec, build_slab, layer_probe, slab_probe
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.mesh import locate
from scissor_cli.solvers.equilibrium import solve_equilibrium

#: The slab truth's relative residual. The loop reads the target to a camera's noise (σ ≈ 0.15 mm at the
#: default camera); over a loop's moves on the paper's prosthesis slab the target is within 8e-7 mm of its
#: 1e-10 solution at 1e-5 (1e-8 mm at 1e-7, 1.4e-5 mm at 1e-4), and a settle costs less than at 1e-7
#: (benchmarks/bench_slab_truth.py).
SLAB_TRUTH_TOL = 1e-5


class SlabTruth:
    """Builds the slab of a 2-D model once; called with a perturbation it gives (true slab, view) for a target."""

    def __init__(self, model: Tissue, spec: SlabSpec):
        self.model = model
        self.slab = build_slab(model.scene, model.mesh, spec, model=model.params.model, element=model.element.name)
        sm = self.slab.mesh
        self._layer = layer_probe(self.slab, model.mesh)
        self._triangle = sm.element_triangle  # the layer's triangle of each tetrahedron
        if sm.plane is not model.mesh:
            self._triangle = locate(model.mesh, sm.plane.nodes[sm.plane.triangles].mean(axis=1))[0][self._triangle]
        self._starts: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def start(self, strokes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nominal slab's equilibrium (strokes (C,), x (N3, 3)) at these strokes, solved once per process."""
        strokes = np.asarray(strokes, float)
        key = tuple(strokes)
        if key not in self._starts:
            self._starts[key] = (strokes, solve_equilibrium(self.slab, strokes, tol=SLAB_TRUTH_TOL).x)
        return self._starts[key]

    def remember(self, strokes: np.ndarray, x: np.ndarray) -> None:
        """Take `start`'s answer at these strokes (C,) mm from elsewhere: x (N3, 3) mm, solved by `start`
        in another process (`experiments.slab_starts`)."""
        strokes = np.asarray(strokes, float)
        self._starts.setdefault(tuple(strokes), (strokes, np.asarray(x, float)))

    def for_target(self, target_rest: np.ndarray, plan_strokes: np.ndarray | None = None):
        """The truth factory (`control.TruthFactory`) of one target, rest (2,) mm; its first move starts
        from the nominal slab at the plan's strokes (C,) mm when given (and not all zero)."""
        probe = slab_probe(self.slab, np.asarray(target_rest, float)[None])
        guesses = ()
        if plan_strokes is not None and np.any(plan_strokes):
            guesses = (self.start(plan_strokes),)
        view = TruthView(target=lambda x: probe.positions(x)[0, :2], layer=lambda x: self._layer.positions(x)[:, :2],
                         tol=SLAB_TRUTH_TOL, guesses=guesses)

        def factory(truth: TruthPerturbation) -> tuple[Tissue, TruthView]:
            return self.perturbed(truth), view

        return factory

    def perturbed(self, truth: TruthPerturbation) -> Tissue:
        """The slab with a trial's perturbation (the slab itself when nothing differs)."""
        E = np.asarray(truth.E_scale, float)
        E_scale = E[self._triangle] if E.ndim else float(E)
        return true_tissue(self.slab, TruthPerturbation(E_scale, truth.fiber_offset_rad, truth.nu, truth.eta_kPa,
                                                        truth.eta_scale))
