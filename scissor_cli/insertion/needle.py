"""One quasi-static step of a rigid straight needle in the layer or the slab (docs/model.md §12, §14).

The needle enters at `entry` p0 along the unit axis n; at depth d its tip is
p0 + d n. A step advances it by Δd and finds the tissue's equilibrium with

* the captured nodes held by the shaft: across the axis always (the
  transverse offset they had at capture), and along it too while they
  *stick* (they move axially with the needle);
* *slipping* captured nodes pulled along the axis by the kinetic friction
  f_k l_i, l_i their share of the inserted shaft;
* the tip force F_tip along n on the tissue just ahead of the tip
  (`tip_zone`: the kernel (1 − (r/R)²)² over the half-disc or half-ball
  of radius R = `tip_zone_mm`, as consistent nodal loads).

The same code serves the layer (d = 2 dofs per node) and the slab (d = 3,
`tissue.dim`): across the axis means the d − 1 unit vectors of
`transverse_basis`, the tip zone is a half-disc or a half-ball.

Stick or slip is an active set with state (Karnopp's law, docs/model.md §12):
each captured node starts a step in the state the last step left it in (a
node captured in this step starts stuck, riding from where the tip passed
it). A stuck node whose axial reaction exceeds f_s l_i in magnitude is
released, with the kinetic friction in the reaction's direction; a slipping
node that would catch up with the needle (move along the axis at least as
far as the needle in the step: its slip would reverse) sticks again and is
tested against f_s from then on. The step is solved again until no node
changes. A node that catches up RESTICKS times in one step stays stuck for
the rest of it, so the loop ends; a step still changing after
MAX_ACTIVE_SET passes is reported as unsettled (the last pass allowed is
always solved to the tolerance, so it still returns an equilibrium).

Every pass is solved on one kept factorisation (`chord.ChordSolver`: the
hold as Schur-complement rows, chord steps to Newton's residual and
tolerance), warm started from the previous equilibrium, with Newton through
`solvers.equilibrium.solve_equilibrium` and `Conditions` (held dofs for
stuck nodes, `along_nodes` across the axis for slipping ones, loads) as the
fallback. A pass's decisions are taken from the chord step's prediction of
its converged reactions and lags when none lies within the prediction's
error of its threshold (EARLY_DECISIONS); otherwise, and for the settled
set, from the solve converged to PASS_TOL (and again to STEP_TOL when a
caller's `NeedleParams.step_tol` asks for less; the layer's STEP_TOL is
PASS_TOL, the slab's STEP_TOL_3D is PASS_TOL_3D).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from scissor_cli.config import InsertionConfig, MeshConfig, NeedleConfig
from scissor_cli.config.body_sections import BodyMeshConfig
from scissor_cli.insertion import kernels
from scissor_cli.insertion.capture import capture, capture_radii, shaft_lengths
from scissor_cli.insertion.chord import ChordFailed, ChordSolver, Hold, hold_conditions
from scissor_cli.insertion.tip_zone import ZoneMesh, tip_weights, zone_mesh
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.solvers.common import Conditions, SolverError
from scissor_cli.solvers.equilibrium import solve_equilibrium

#: the active-set passes are solved to this relative residual (Newton's)
PASS_TOL = 1e-5
#: the settled set's relative residual in the layer; when it is below PASS_TOL the settled set is solved
#: again to it and checked once more. At PASS_TOL itself the settled pass is the step's last: over a
#: 50 mm insertion on configs/example_insertion.yaml and on configs/example_3d.yaml's layer (T1, 0.5 mm
#: steps) the target stays within 6e-6 mm of the 1e-8 solution at every step, with the same stuck and
#: slipping counts at every step and the needle force within 6e-3 mN (of 600), for 19 chord steps a step
#: instead of 24 (benchmarks/bench_insertion.py; docs/model.md §12)
STEP_TOL = PASS_TOL
#: In the slab (3-D) a triangular solve on the kept factor and a factorisation cost
#: tens of times the layer's (benchmarks/bench_insertion3d.py). There a step is solved
#: to 1e-4: over a 30 mm insertion
#: of the test slab (tests/test_insertion3d.py, 0.5 mm steps) the target stays within
#: 6e-6 mm of the 1e-8 solution, the stick–slip counts are the same at every step and
#: the needle force within 3e-8; on the stale factor the chord steps stall between 1e-4
#: and 1e-5 (contraction > 0.9), so 1e-5 cost a refactorisation nearly every step.
#: `NeedleParams.step_tol` overrides.
STEP_TOL_3D = 1e-4
PASS_TOL_3D = 1e-4
#: A body's passes and steps (`NeedleParams.from_config` of a body's mesh): its insertion is the
#: trials' inner loop, and 3e-4 instead of 1e-4 moves the lesion far below what a camera resolves
#: for fewer chord steps (benchmarks/bench_body_insertion.py's speed against error; docs/performance.md)
STEP_TOL_BODY = 3e-4
#: decide a pass from its chord step's prediction of the converged reactions and
#: lags once no decision lies within GUARD_FORCE·res·(force scale) mN or
#: GUARD_POSITION·res mm of its threshold (res the relative residual there)
EARLY_DECISIONS = True
#: measured on the example (50 mm, 0.5 mm steps, every prediction of a pass whose
#: rows are met): the error is at most 0.36·res·scale (reactions) and 0.95·res mm
#: (positions). A closing step's prediction (rows still open: the first of a step)
#: errs by what the rows move, far beyond res; no decision is taken on it.
GUARD_FORCE = 1.0
GUARD_POSITION = 3.0
#: in the slab, measured the same way (example_full's slab, the first 5 mm, res from 1e-5 to 1): at most
#: 0.15·res·scale and 0.50·res mm (its residual norm spreads over 25× the layer's dofs, the error at a
#: captured node does not); the guards keep the layer's margin (≈ 3×)
GUARD_FORCE_3D = 0.4
GUARD_POSITION_3D = 1.5
#: no early decision on a prediction in which a captured node moves more than this many steps along the
#: axis beyond the needle's ride: such a lurch (the nearly incompressible hard case, ν = 0.499: 4.4 mm in
#: a 0.5 mm step) lies outside the kept factor's linearisation, whose errors the guards were measured on;
#: deciding on it there changed the step's path (docs/model.md §12, "No decision on a lurch")
LURCH_STEPS = 2.0
#: active-set passes per step before the step is reported as unsettled
MAX_ACTIVE_SET = 50
#: a node that catches up with the needle this many times in one step stays stuck for the rest of the step
RESTICKS = 2
#: halvings of a step whose start would invert an element (a 0.5 mm step
#: on 1 mm elements never needs one; 10× friction or a coarse mesh may)
MAX_SPLITS = 6
#: a start must keep every element's area above this fraction of its area in
#: the last equilibrium (a nearly flat element makes K_ff numerically
#: singular); else the step is split
MIN_START_J = 0.2


@dataclass(frozen=True)
class NeedleParams:
    """The needle–tissue parameters of docs/model.md §12 (mm, mN, mN/mm)."""

    step_mm: float = 0.5
    friction_static_mN_per_mm: float = 15.0
    friction_kinetic_mN_per_mm: float = 10.0
    tip_force_mN: float = 100.0
    tip_zone_mm: float = 2.0
    #: None: half the mean edge at each node (`capture.capture_radii`, a body's default)
    capture_radius_mm: float | None = 2.0
    radius_mm: float = 0.6  # half the needle diameter: obstacle clearance
    #: every pass's and the settled set's relative residual; None: by dimension (PASS_TOL and STEP_TOL,
    #: PASS_TOL_3D and STEP_TOL_3D)
    step_tol: float | None = None

    def tolerances(self, d: int) -> tuple[float, float]:
        """(pass, step) relative residuals of an insertion step in dimension d."""
        if self.step_tol is not None:
            return self.step_tol, self.step_tol
        return (PASS_TOL, STEP_TOL) if d == 2 else (PASS_TOL_3D, STEP_TOL_3D)

    @classmethod
    def from_config(cls, ins: InsertionConfig, needle: NeedleConfig, mesh: MeshConfig | BodyMeshConfig
                    ) -> "NeedleParams":
        """From the `insertion`, `needle` and `tissue.mesh` sections.

        The capture radius defaults to half the coarsest edge in the layer and
        the slab, and to half the mean edge at each node in a body (mesh a
        `BodyMeshConfig`; `capture.capture_radii`); a body's steps are solved
        to STEP_TOL_BODY.
        """
        body = isinstance(mesh, BodyMeshConfig)
        capture = ins.capture_radius_mm
        if capture is None and not body:
            capture = 0.5 * mesh.max_edge_mm * mesh.scale
        return cls(ins.step_mm, ins.friction_static_mN_per_mm, ins.friction_kinetic_mN_per_mm, ins.tip_force_mN,
                   ins.tip_zone_mm, capture, 0.5 * needle.diameter_mm, STEP_TOL_BODY if body else None)


@dataclass
class NeedleState:
    """The needle and what it holds: entry p0 (d,), axis n (d,), depth d (mm), captured nodes.

    captured (P,) node indices, offset mm their transverse offset at
    capture ((P,) in 2-D, (P, d − 1) in 3-D: the components along
    `transverse`), stuck (P,) bool after the last step, lengths (P,) mm their
    shares of the shaft.
    """

    entry: np.ndarray
    direction: np.ndarray
    depth_mm: float = 0.0
    captured: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    offset: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stuck: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    lengths: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: direction of the kinetic friction on each slipping node (+1 along n, −1 against; 0 stuck)
    sign: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: the last step's node increment per mm of advance (N, d), the next step's predictor
    rate: np.ndarray | None = None
    #: the kept factorisation of the needle's solves (`chord.ChordSolver`), shared across steps
    solver: ChordSolver | None = field(default=None, repr=False)
    #: (x, ∇U at x) of the last step's equilibrium: the next step, if it starts there, need not evaluate it again
    equilibrium: tuple | None = field(default=None, repr=False)
    #: the tissue's `tip_zone.ZoneMesh`, made at the first step
    zone: ZoneMesh | None = field(default=None, repr=False)
    #: each node's capture radius (N,) mm (`capture.capture_radii`), made at the first step
    radii_mm: np.ndarray | None = field(default=None, repr=False)

    @property
    def across(self) -> np.ndarray:
        """t (2,): the unit normal of the axis, n rotated by +90° (2-D; in 3-D see `transverse`)."""
        return np.array([-self.direction[1], self.direction[0]])

    @property
    def transverse(self) -> np.ndarray:
        """(d − 1, d): unit vectors across the axis, orthogonal to it and to each other (`transverse_basis`)."""
        return transverse_basis(self.direction)

    @property
    def tip(self) -> np.ndarray:
        return self.entry + self.depth_mm * self.direction


@dataclass
class StepOutcome:
    """One step: positions x (N, d) mm, axial needle force (mN), stuck/slipping counts, loads (dN,) mN.

    settled is False when the active set still changed after MAX_ACTIVE_SET
    passes; passes counts the solves.
    """

    x: np.ndarray
    force_mN: float
    stuck: int
    slipping: int
    loads: np.ndarray
    settled: bool
    passes: int
    iterations: int
    #: numeric factorisations the step made
    factorizations: int = 0


def transverse_basis(direction: np.ndarray) -> np.ndarray:
    """(d − 1, d) orthonormal unit vectors across the unit axis n (d,), d = 2 or 3 (docs/model.md §14).

    2-D: [t], t = n rotated by +90° (`NeedleState.across`). 3-D: the two
    components a captured node keeps across the axis; for an axis in the
    layer (n_z = 0) they are (t, 0), t the in-plane normal as in 2-D, and
    e_z, so a slab's transverse offset is the layer's plus the height.
    Otherwise the in-plane normal is made orthogonal to n (Gram–Schmidt)
    and the second is n × the first.
    """
    n = np.asarray(direction, float)
    if n.shape == (2,):
        return np.array([[-n[1], n[0]]])
    if n.shape != (3,):
        raise ValueError(f"the needle axis must be a 2- or 3-vector; got shape {n.shape}")
    t = np.array([-n[1], n[0], 0.0])
    if np.linalg.norm(t) < 1e-12:  # an axis along z: any horizontal pair will do
        t = np.array([1.0, 0.0, 0.0])
    t = t - (t @ n) * n
    t /= np.linalg.norm(t)
    return np.stack([t, np.cross(n, t)])


def advance(
    tissue: Tissue, state: NeedleState, x: np.ndarray, strokes: np.ndarray, step_mm: float, params: NeedleParams,
    candidates: np.ndarray,
) -> StepOutcome:
    """Advance the needle by step_mm from the equilibrium x (N, d) at cup strokes (C,) mm; updates `state`.

    A step whose start (stuck nodes moved with the needle) would invert an
    element is split into 2, 4, … equal parts (at most 2^MAX_SPLITS), the
    state restored before each retry: Newton never sees an inverted start
    (it would restart from rest and lose the needle's hold). Raises
    SolverError when a solve fails or no split is feasible.
    """
    parts = 1
    while True:
        saved = dataclasses.replace(state)
        try:
            out, y = None, x
            for _ in range(parts):
                out = _advance_once(tissue, state, y, strokes, step_mm / parts, params, candidates)
                y = out.x
            return out
        except _Infeasible:
            for f in dataclasses.fields(state):
                setattr(state, f.name, getattr(saved, f.name))
            parts *= 2
            if parts > 2 ** MAX_SPLITS:
                raise SolverError(
                    f"the needle step inverts an element even when split into {parts // 2} parts") from None


class _Infeasible(Exception):
    """A step's start inverts an element (so Newton would not start from it): split the step."""


def _flattens(tissue: Tissue, start: np.ndarray, J_now: np.ndarray) -> bool:
    """Whether the start shrinks some element's area below MIN_START_J of its area in the equilibrium."""
    return bool(np.min(tissue.jacobians(start) / J_now) <= MIN_START_J)


def _newton_start(tissue: Tissue, J_now: np.ndarray, *starts: np.ndarray) -> np.ndarray:
    """The first of starts (N, d) that flattens no element (`_flattens`); `_Infeasible` when each does."""
    for start in starts:
        if not _flattens(tissue, start, J_now):
            return start
    raise _Infeasible


def _advance_once(tissue, state, x, strokes, step_mm, params, candidates) -> StepOutcome:
    n, t = state.direction, state.transverse  # t (d − 1, d)
    d = x.shape[1]
    old = state.captured.copy()
    state.depth_mm += step_mm
    if state.radii_mm is None:
        state.radii_mm = capture_radii(tissue, params.capture_radius_mm)
    new = capture(x, candidates, state.entry, n, state.depth_mm, old, state.radii_mm)
    captured = np.concatenate([old, new]).astype(np.int64)
    offset_new = (x[new] - state.entry) @ t.T
    offset = (np.concatenate([state.offset, offset_new[:, 0]]) if d == 2
              else np.concatenate([state.offset.reshape(-1, d - 1), offset_new]))
    rel = x[captured] - state.entry
    lengths = shaft_lengths(rel @ n, state.depth_mm)
    if state.zone is None:
        state.zone = zone_mesh(tissue)
    tip_nodes, w = tip_weights(tissue, x, state.tip, np.vstack([n, t]), params.tip_zone_mm, candidates, state.zone)
    base = np.zeros(x.size)
    base.reshape(-1, d)[tip_nodes] += (params.tip_force_mN * w)[:, None] * n  # the zone's nodes are distinct
    # Each node starts in the state the last step left it in (Karnopp: friction has
    # state); a node captured in this step starts stuck. A stuck node rides Δd with
    # the needle, a node captured in this step from where the tip passed it (d − s_i).
    stuck = np.concatenate([state.stuck, np.ones(new.size, bool)])
    sign = np.concatenate([np.where(state.stuck, 1.0, state.sign), np.ones(new.size)])
    ride = np.concatenate([np.full(old.size, step_mm),
                           np.clip(state.depth_mm - (x[new] - state.entry) @ n, 0.0, step_mm)])
    J_now = tissue.jacobians(x)
    # Newton's start: the tissue moving on as in the last step, else from x
    start = _newton_start(tissue, J_now, *(
        [_placed(x + state.rate * step_mm, x, captured, stuck, ride, n)] if state.rate is not None else []),
        _placed(x.copy(), x, captured, stuck, ride, n))
    fs, fk = params.friction_static_mN_per_mm, params.friction_kinetic_mN_per_mm
    limit = fs * lengths * (1.0 + 1e-9)  # f_s l_i, with round-off: a rule adds 1e-9 of the force scale
    # A slipping node that catches up with the needle sticks again and is tested
    # against f_s from then on. A node that sticks again for the RESTICKS-th time in
    # one step (its neighbours' releases pushing it back and forth) stays stuck for
    # the rest of the step: that bounds the loop.
    resticks = np.zeros(captured.size, np.int64)
    locked = np.zeros(captured.size, bool)
    if state.solver is None:
        state.solver = ChordSolver(tissue)
    solver, n_factor = state.solver, state.solver.factorizations
    pass_tol, step_tol = params.tolerances(d)
    guard_force, guard_position = (GUARD_FORCE, GUARD_POSITION) if d == 2 else (GUARD_FORCE_3D, GUARD_POSITION_3D)
    passes, iterations, settled, tol = 0, 0, False, pass_tol
    result_x, loads, axial = start, base, np.zeros(captured.size)
    base_x = x[captured]
    hold = None
    # The chord solver starts the first pass from the last equilibrium itself: its
    # first step is the tangent response to the needle's ride (2 steps to a
    # decision instead of 4 from `start`); `start` is where Newton would start.
    chord_x = x
    if state.equilibrium is not None and np.array_equal(state.equilibrium[0], x):
        grad_u = state.equilibrium[1]
    else:
        _, grad_u = tissue.energy_gradient(chord_x)
    while passes < MAX_ACTIVE_SET:
        loads = base.copy()
        slip = ~stuck
        friction = fk * lengths[slip] * sign[slip]
        loads.reshape(-1, d)[captured[slip]] += friction[:, None] * n  # captured nodes are distinct: no repeated index
        if hold is None or (hold.stuck is not stuck and not np.array_equal(hold.stuck, stuck)):  # kept while the set is
            hold = Hold(captured, base_x, stuck, ride, n, t)
        scale = tissue.force_scale(grad_u)
        rule = _Rule(limit, stuck, locked, sign, 1e-9 * step_mm, 1e-9 * scale)

        def early(xc, d_captured, mu, res, rule=rule, scale=scale):
            # the converged state's reactions and lags, predicted by this chord step (its Schur forces)
            axial_p, lag_p = np.empty(captured.size), np.empty(captured.size)
            kernels.predicted_reactions(mu, rule.stuck, d_captured, xc, captured, base_x, n, ride, axial_p, lag_p)
            if np.max(np.abs(lag_p), initial=0.0) > LURCH_STEPS * step_mm:
                return None  # a lurch: the linearisation is out of its range, decide on the converged state
            release, against, changed = rule.apply(axial_p, lag_p, guard_force * res * scale, guard_position * res)
            return (release, against, axial_p) if changed > 0 else None  # nothing to do, or unclear (−1)

        r_x, g, its, verdict = _solve_pass(tissue, solver, strokes, chord_x, grad_u - loads, hold, loads, tol,
                                           early if EARLY_DECISIONS and passes < MAX_ACTIVE_SET - 1 else None, start)
        grad_u = g + loads
        passes += 1
        iterations += its
        result_x, result_grad = r_x, grad_u
        if verdict is None:  # converged to tol: the exact rule
            axial = g.reshape(-1, d)[captured] @ n  # what the needle must supply
            # Kinetic friction opposes the slip: a node pulled forward (+n) must lag the needle, and the reverse.
            lag = (r_x[captured] - x[captured]) @ n - ride
            release, against, _ = _Rule(limit, stuck, locked, sign, 1e-9 * step_mm,
                                        1e-9 * tissue.force_scale(grad_u)).apply(axial, lag)
            if not (release.any() or against.any()):  # (the exact rule: no error, nothing unclear)
                if tol <= step_tol:
                    settled = True
                    break
                tol, start = step_tol, r_x
                chord_x = start
                continue
        else:
            release, against, axial = verdict
        sign[release] = np.sign(axial[release])
        restick = against
        resticks += restick
        locked |= resticks >= RESTICKS
        stuck = (stuck & ~release) | restick
        start = r_x
        if restick.any():  # a node that catches up sticks where the needle has carried it in this step
            placed = r_x.copy()
            placed[captured[restick]] = x[captured[restick]] + ride[restick, None] * n
            # Placed alone in r_x it may flatten an element a neighbour's release stretched (a coarse mesh): then
            # the step's own start with the set as it now stands
            start = _newton_start(tissue, J_now, placed, _placed(x.copy(), x, captured, stuck, ride, n))
            _, grad_u = tissue.energy_gradient(start)
        chord_x = start
    force = float(axial[stuck].sum() + (fk * lengths[~stuck] * sign[~stuck]).sum() + params.tip_force_mN)
    state.captured, state.offset, state.stuck, state.lengths = captured, offset, stuck, lengths
    state.sign = np.where(stuck, 0.0, sign)
    state.rate = (result_x - x) / step_mm
    state.equilibrium = (result_x.copy(), result_grad)
    return StepOutcome(result_x, force, int(stuck.sum()), int((~stuck).sum()), loads, settled, passes, iterations,
                       solver.factorizations - n_factor)


def _placed(start: np.ndarray, x: np.ndarray, captured: np.ndarray, stuck: np.ndarray, ride: np.ndarray,
            n: np.ndarray) -> np.ndarray:
    """start (N, d) with the captured nodes on the needle's hold: the stuck ones ridden along from x by ride (P,)
    mm, the slipping ones at their position in x plus the start's advance along the axis n (d,) (across it they
    keep their offset)."""
    along = np.where(stuck, ride, (start[captured] - x[captured]) @ n)
    start[captured] = x[captured] + along[:, None] * n
    return start


class _Rule:
    """The active-set rule of one pass: which stuck nodes are released, which slipping ones catch up with the needle.

    limit (P,) mN: f_s l_i (and round-off); stuck, locked (P,) bool; sign
    (P,) the kinetic friction's direction; lag_tol mm.
    """

    def __init__(self, limit, stuck, locked, sign, lag_tol, floor=0.0):
        self.limit, self.stuck, self.sign, self.lag_tol = limit + floor, stuck, sign, lag_tol
        self.free = stuck & ~locked  # a locked node stays stuck for the rest of the step
        # a node whose static limit f_s l_i is zero holds nothing: it never sticks again (else at f_s = 0, or at a
        # share l_i of 0, it caught up, stuck, was released, ... until locked stuck holding a force beyond its limit)
        self.slip = ~stuck & (limit > 0.0)

    def apply(self, axial, lag, force_error=0.0, position_error=0.0):
        """release, against (P,) bool from the axial reactions (P,) mN and lags (P,) mm; and how many nodes change.

        The count is −1 when a decision is unclear: its quantity lies within
        the given error (mN, mm) of its threshold, so an estimate may not
        decide it.
        """
        release, against = np.empty(axial.size, bool), np.empty(axial.size, bool)
        changed = kernels.friction_rule(axial, lag, self.limit, self.free, self.slip, self.sign, self.lag_tol,
                                        force_error, position_error, release, against)
        if changed > 0 and release.any():
            # Releases first: a node held beyond f_s drags its neighbours along, so a slipping one may seem to
            # catch up only because of it. Catching up is judged once every stuck node is within f_s.
            against[:] = False
        return release, against, changed


def _solve_pass(tissue, solver, strokes, x, g, hold, loads, tol, decide, start):
    """One pass's equilibrium under the hold: (x, g, iterations, verdict).

    The kept factorisation's chord steps (`chord.ChordSolver`) from x (N, d)
    with objective gradient g (dN,), which `decide` may end early with a
    verdict; when they fail, Newton with the same hold as `Conditions` from
    start (N, d), the hold's placed start (`_newton_start`).
    """
    try:
        return solver.converge(x, g, hold, tol, loads, decide)
    except ChordFailed:
        pass
    r = solve_equilibrium(tissue, strokes, start=start, start_strokes=strokes, conditions=hold.conditions(loads),
                          tol=tol)
    _, grad = tissue.energy_gradient(r.x)
    return r.x, grad - loads, r.iterations, None


def needle_conditions(state: NeedleState, loads: np.ndarray | None = None) -> Conditions:
    """The needle's hold on the tissue as it stands (stuck: every dof; slipping: across the axis)."""
    return hold_conditions(state.captured, state.stuck, state.transverse, loads)
