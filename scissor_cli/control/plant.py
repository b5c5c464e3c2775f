"""The two tissues of a manipulation: the simulated truth (plant) and the controller's model (docs/model.md §6, §10).

They are kept apart on purpose: a trial perturbs the truth (E, ν, η, fiber
angle, actuator, measurement) without touching the controller. When the
truth *is* the model (the same `Tissue` object) and the actuator realised
the command exactly, the controller adopts the plant's equilibrium instead
of solving it again.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from scissor_cli.control.actuator import Actuator
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import TargetProbe, apply_probe, target_positions
from scissor_cli.sensing.sensor import TrueState
from scissor_cli.solvers.tracking import TrackedEquilibrium, TrackerState


@dataclass(frozen=True)
class TruthView:
    """How the loop reads a true tissue that is not the layer itself (the 3-D slab, docs/model.md §13).

    target(x) -> (2,) mm: the target as the camera sees it (in-plane) for the
    truth's node positions x; layer(x) -> (N2, 2) mm: the layer's nodes there
    (for the corridor check on the controller's mesh). tol: the truth's
    relative residual (None: the loop's); guesses: known near-equilibria
    (strokes (C,), x) its first big move may start from.
    """

    target: Callable[[np.ndarray], np.ndarray]
    layer: Callable[[np.ndarray], np.ndarray]
    tol: Optional[float] = None
    guesses: tuple = ()


#: makes the true tissue and its view for a trial's perturbation (`trials.truth: slab`)
TruthFactory = Callable[["TruthPerturbation"], tuple[Tissue, TruthView]]


class Plant:
    """The simulated truth: tissue + actuator + current equilibrium + the target's probe.

    With a `view`, the truth is another discretisation than the controller's
    (the slab): the view reads its target and layer; the probe is unused.
    """

    def __init__(self, tissue: Tissue, actuator: Actuator, probe: TargetProbe, tol: float = 1e-10,
                 view: Optional[TruthView] = None):
        self.tissue, self.actuator, self.probe, self.view = tissue, actuator, probe, view
        self.eq = TrackedEquilibrium(tissue, tol if view is None or view.tol is None else view.tol)
        if view is not None:
            self.eq.guesses.extend(view.guesses)

    @property
    def position(self) -> np.ndarray:
        """The true target (2,) mm."""
        if self.view is not None:
            return self.view.target(self.eq.x)
        return target_positions(self.probe, self.eq.x)[0]

    def true_state(self) -> TrueState:
        """What a sensor sees: the true target (2,) mm and the truth's nodes on its mesh."""
        return TrueState(self.position, self.eq.x, self.tissue.mesh)

    @property
    def layer_x(self) -> np.ndarray:
        """The layer's node positions (N2, 2) mm in the true state."""
        return self.eq.x if self.view is None else self.view.layer(self.eq.x)

    @property
    def strokes(self) -> np.ndarray:
        return self.eq.strokes

    def apply(self, command: np.ndarray, tangent: bool = False) -> np.ndarray:
        """Actuate `command` (C,) mm and settle the truth; returns the actual strokes (C,) mm."""
        actual = self.actuator.apply(command)
        self.eq.move_to(actual, tangent=tangent)
        return actual


class Controller:
    """The controller's model: tissue + equilibrium at the commanded strokes + J there.

    lo, hi (C,) mm and resolution_mm are what it may command (the drives'
    nominal limits; it does not know the backlash).
    """

    def __init__(self, tissue: Tissue, probe: TargetProbe, lo, hi, resolution_mm: float = 0.0, tol: float = 1e-10,
                 paths: Optional["ModelPaths"] = None):
        self.tissue, self.probe = tissue, probe
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.resolution_mm = resolution_mm
        self.eq = TrackedEquilibrium(tissue, tol)
        self.paths, self._commands = paths, ()
        rest = paths.get(self._commands) if paths is not None else None
        if rest is None:  # J at rest: the model's tangent factored there
            self.eq.move_to(self.eq.strokes, tangent=True)
            if paths is not None:
                paths.put(self._commands, self.eq.snapshot())
        else:  # every loop of this model starts from the same rest state: taken over, as a later state is
            self.eq.restore(rest)

    @property
    def n_cups(self) -> int:
        return self.tissue.n_cups

    @property
    def jacobian(self) -> np.ndarray:
        """J (d, C) mm/mm of the target at the model equilibrium ((d, 0) without cups); d = tissue.dim."""
        if self.tissue.n_cups == 0:
            return np.zeros((self.tissue.dim, 0))
        return apply_probe(self.probe, self.eq.response, self.tissue.dim)

    @property
    def strokes(self) -> np.ndarray:
        return self.eq.strokes

    def shares(self, plant: Plant) -> bool:
        return plant.tissue is self.tissue

    def update(self, commanded: np.ndarray, plant: Optional[Plant] = None) -> None:
        """Move the model to the commanded strokes (C,) mm and update J there.

        When the plant is this very tissue and sits at exactly these strokes,
        its equilibrium (solved with its tangent) is taken over.
        """
        same_state = plant is not None and self.shares(plant) and np.array_equal(plant.strokes, commanded)
        if same_state and plant.eq.jacobian_is_current:
            self.eq.adopt(plant.eq)
        elif self.paths is None or (plant is not None and self.shares(plant)):
            self.eq.move_to(commanded, tangent=True)
        else:  # the same commands from rest as an earlier loop of this model: the same states, taken over
            self._commands = (self._commands, np.asarray(commanded, float).tobytes())
            state = self.paths.get(self._commands)
            if state is None:
                self.eq.move_to(commanded, tangent=True)
                self.paths.put(self._commands, self.eq.snapshot())
            else:
                self.eq.restore(state)


class ModelPaths:
    """The controller model's equilibria along the command sequences its loops have sent, in one process.

    A trial's truth differs from the model, but the controller's model does
    not: two loops that command the same strokes from rest (the drives'
    top speed on the way to a far lesion, as every trial of a target does)
    solve the same model states, bit for bit. A `Controller` given these
    paths takes a state solved before instead of solving it again
    (`TrackedEquilibrium.restore`: the loop goes on exactly as if it had
    solved it). Keyed by the whole command sequence from rest (the rest
    state itself, where each loop's J starts, by the empty one); keeps the
    `capacity` most recently used states (each holds the nodes and the
    tangent: a few hundred kB for a body). One per model tissue and target.
    """

    def __init__(self, capacity: int = 48):
        self.capacity = capacity
        self._states: OrderedDict[tuple, TrackerState] = OrderedDict()
        self.hits = self.misses = 0

    def get(self, commands: tuple) -> Optional[TrackerState]:
        state = self._states.get(commands)
        if state is None:
            self.misses += 1
        else:
            self.hits += 1
            self._states.move_to_end(commands)
        return state

    def put(self, commands: tuple, state: TrackerState) -> None:
        self._states[commands] = state
        self._states.move_to_end(commands)
        while len(self._states) > self.capacity:
            self._states.popitem(last=False)


@dataclass(frozen=True)
class TruthPerturbation:
    """How the simulated truth differs from the controller's model (docs/model.md §10).

    E_scale multiplies every element's E: a scalar or a field (M,) (e.g.
    `profiles.TrialDraw.E_field`); fiber_offset_rad turns the fiber (the
    model's global angle + offset); nu and eta_kPa replace the model's when
    given, eta_scale multiplies the model's η otherwise. The neutral
    perturbation leaves the truth = the model.

    Note: with displacement-controlled cups a uniform E scale alone does
    not change the equilibrium (U scales as a whole); it acts through the
    ratio to η, which is not scaled, and through heterogeneity.
    """

    E_scale: float | np.ndarray = 1.0
    fiber_offset_rad: float = 0.0
    nu: Optional[float] = None
    eta_kPa: Optional[float] = None
    eta_scale: float = 1.0


def true_tissue(model: Tissue, truth: TruthPerturbation) -> Tissue:
    """The trial's true tissue; the model itself when nothing differs (so one solve serves both)."""
    m = model.scene.material
    nu = None if truth.nu is None or truth.nu == m.nu else truth.nu
    if truth.eta_kPa is not None:
        eta = truth.eta_kPa
    else:
        eta = m.eta_kPa * truth.eta_scale if truth.eta_scale != 1 else None
    eta = None if eta == m.eta_kPa else eta
    E_uniform = np.all(np.asarray(truth.E_scale) == 1.0)
    if E_uniform and truth.fiber_offset_rad == 0 and nu is None and eta is None:
        return model
    angle = m.fiber_angle_rad + truth.fiber_offset_rad if truth.fiber_offset_rad else None
    return model.with_material(truth.E_scale, nu, eta, angle)
