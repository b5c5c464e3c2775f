"""Solver-scaling benchmark: scissor's Newton and ADMM against a scikit-fem peer, 1k to 64k triangles.

    python benchmarks/bench_solvers.py            # 1k, 4k, 16k, 64k elements (≈ 2 min on 2 cores)
    python benchmarks/bench_solvers.py --quick    # stops after the 16k mesh (≈ 35 s)
    options: --profile (cProfile of each solver on the largest mesh), --blas-threads N

Problem: configs/example.yaml (fiber-reinforced neo-Hookean, plane strain,
P1 triangles, docs/model.md §2–3), quasi-static, one 5 mm push of the cup. The
meshes are the example's own graded meshes, `build_model(cfg, mesh_scale=s)`
with s = 2.0 / 0.75 / 0.33 / 0.155 (≈ 1.05k / 4.0k / 15.7k / 62k elements):
the project's refinement path (every feature — targets, obstacles, the cup's
grip ends — refined together). A 10 mm push is not benchmarked: on the fine
meshes the stress singularity at the cup's grip ends makes Newton's tangent
predictor invert elements, and load continuation (many substeps) would
dominate every time.

Measure ("time to 1e-3 relative target error"). The reference is scissor's
Newton to a relative force residual of 1e-10; the targets are the scene's
targets carried by their rest triangles (`jacobian.probe_targets`). The
error of a solution x is

    e(x) = ‖p(x) − p_ref‖ / ‖p_ref − p_rest‖      (all targets stacked)

* scissor Newton, ADMM, ADMM + Anderson(5): each solver is run from scratch
  with the tolerances of LADDER, loosest first; the first (loosest) one
  whose result has e ≤ 1e-3 is timed: median of the repeats (5; 3 on the
  64k mesh). ADMM times include building the AdmmSolver (weights, D, the
  factorisation of the global matrix) and its weight-boost refactorisations.
* peer: a plain scikit-fem implementation of the same energy (`SkfemPeer`,
  below): Newton with the exact tangent assembled from a `BilinearForm`, the
  residual from a `LinearForm`, the energy from a `Functional` (all written
  with `skfem.helpers`), `condense` + `solve` (scipy's spsolve, SuperLU) and
  a backtracking line search keeping every J > 0 and not increasing the
  energy. Its time to e ≤ 1e-3 is the wall time at which its first iterate
  with e ≤ 1e-3 is accepted (start of the solve → end of that line search);
  its time to its own relative force residual 1e-10 (scissor's measure) is
  reported as well. Its first Newton step from rest carries the Dirichlet
  increment, i.e. it is the linear-elastic predictor scissor's Newton starts
  from too; where that inverts an element the peer halves the whole step
  (boundary increment included; the rest follows in later iterations), while
  scissor cuts it at the closed-form feasible fraction. Building the Basis
  (like building scissor's Tissue) is not timed; the peer's timestamp does not
  include assembling the residual at the accepted iterate (a slight favour).
  Fair use: one-point (centroid) quadrature, exact for P1 (scikit-fem's
  smallest built-in triangle rule has 3 points; using it would triple the
  form evaluations for nothing).

Output: a table per mesh size, the least-squares growth exponent of each
solver's time against the element count, and the ratio peer / best scissor
solver. Wall times are `time.perf_counter` medians; the machine line says
how many cores the run saw.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import platform
import sys
import time
from dataclasses import dataclass, field


def _blas_threads_from_argv(argv) -> str | None:
    """`--blas-threads N` must act before numpy loads OpenBLAS: read it from argv first."""
    for i, a in enumerate(argv):
        if a == "--blas-threads" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--blas-threads="):
            return a.split("=", 1)[1]
    return None


if __name__ == "__main__" and _blas_threads_from_argv(sys.argv) is not None:
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[_var] = _blas_threads_from_argv(sys.argv)

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from scissor_cli import runtime  # noqa: E402

runtime.match_blas_kernels()  # before scissor's modules load cvxopt; threads are set in __main__
sys.path.append(os.path.dirname(os.path.abspath(__file__)))  # results_io, also when tests/ loads this file
import results_io  # noqa: E402

from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.experiments.simulate import build_model  # noqa: E402
from scissor_cli.experiments.study import timed  # noqa: E402
from scissor_cli.mechanics.tissue import Tissue  # noqa: E402
from scissor_cli.mesh.probe import probe_targets, target_positions  # noqa: E402
from scissor_cli.solvers.admm.solver import AdmmSolver  # noqa: E402
from scissor_cli.solvers.common import SolverError  # noqa: E402
from scissor_cli.solvers.newton import solve_newton  # noqa: E402

CONFIG = os.path.join(ROOT, "configs", "example.yaml")
#: mesh_scale → elements of the example's graded mesh (1050 / 4016 / 15708 / 62k)
SCALES = (2.0, 0.75, 0.33, 0.155)
STROKE = np.array([5.0])  # mm, a push
TARGET_ERROR = 1e-3
REFERENCE_TOL = 1e-10
#: tolerances tried, loosest first (each solver's own relative residual measure)
LADDER = (1.0, 0.5, 0.2, 1e-1, 5e-2, 2e-2, 1e-2, 5e-3, 2e-3, 1e-3, 5e-4, 2e-4, 1e-4, 5e-5, 1e-5, 1e-6, 1e-8)


# --------------------------------------------------------------------------- the peer


@dataclass
class PeerResult:
    """A scikit-fem solve: positions x (N, 2) mm, iterations, final relative residual,
    wall time, and per accepted iterate its time since the start (s) and positions."""

    x: np.ndarray
    iterations: int
    residual: float
    time_s: float
    converged: bool
    iterate_times: list[float] = field(default_factory=list)
    iterate_x: list[np.ndarray] = field(default_factory=list)
    history: list[float] = field(default_factory=list)


class SkfemPeer:
    """The tissue problem of docs/model.md §2–3 written with scikit-fem, as its docs show.

    Vector P1 (`ElementVector(ElementTriP1())`) on `MeshTri(nodes.T, triangles.T)`;
    per-element μ, κ, η as P0 fields (`basis.with_element(ElementTriP0())`
    interpolated); fiber a0 from the config's global angle; thickness h
    multiplies every form. Dirichlet: `tissue.fixed_nodes` held, each cup's
    gripped nodes moved by stroke × axis. Only the scene's own model
    (neo_hookean_fiber or neo_hookean, fiber on in tension and compression).
    """

    def __init__(self, tissue: Tissue):
        import skfem
        from skfem.helpers import ddot, det, dot, grad, identity, inv, mul, prod, transpose

        m = tissue.scene.material
        if tissue.params.tension_only:
            raise NotImplementedError("the peer has no tension-only fibers")
        if tissue.params.model not in ("neo_hookean", "neo_hookean_fiber"):
            raise NotImplementedError(f"the peer implements the neo-Hookean models, not {tissue.params.model!r}")
        self.tissue = tissue
        mesh = tissue.mesh
        self.mesh = skfem.MeshTri(mesh.nodes.T.copy(), mesh.triangles.T.copy())
        # P1: F is constant per element, so the centroid rule is exact.
        centroid_rule = (np.array([[1.0 / 3.0], [1.0 / 3.0]]), np.array([0.5]))
        self.basis = skfem.Basis(self.mesh, skfem.ElementVector(skfem.ElementTriP1()), quadrature=centroid_rule)
        basis0 = self.basis.with_element(skfem.ElementTriP0())
        E = tissue.element_E_kPa
        eta = m.eta_kPa if tissue.params.model == "neo_hookean_fiber" else 0.0
        self.fields = {
            "mu": basis0.interpolate(E / (2.0 * (1.0 + m.nu))),
            "kappa": basis0.interpolate(E / (3.0 * (1.0 - 2.0 * m.nu))),
            "eta": basis0.interpolate(np.full(mesh.n_elements, eta)),
        }
        h = float(tissue.scene.thickness_mm)
        a0 = np.array([np.cos(m.fiber_angle_rad), np.sin(m.fiber_angle_rad)])[:, None, None]

        def kinematics(w):
            dudX = grad(w["displacement"])
            F = dudX + identity(dudX)
            J = det(F)
            iF = inv(F)
            Fa = mul(F, a0)
            return F, J, iF, ddot(F, F) + 1.0, J ** (-2.0 / 3.0), Fa, dot(Fa, Fa)

        @skfem.Functional
        def energy(w):
            _, J, _, I1, g, _, I4 = kinematics(w)
            return h * (0.5 * w.mu * (g * I1 - 3.0) + 0.5 * w.kappa * (J - 1.0) ** 2 + 0.5 * w.eta * (I4 - 1.0) ** 2)

        @skfem.LinearForm
        def residual(v, w):
            F, J, iF, I1, g, Fa, I4 = kinematics(w)
            iFT = transpose(iF)
            P = (w.mu * g * F - (w.mu / 3.0) * g * I1 * iFT + w.kappa * (J - 1.0) * J * iFT
                 + 2.0 * w.eta * (I4 - 1.0) * prod(Fa, a0))
            return h * ddot(P, grad(v))

        @skfem.BilinearForm
        def tangent(u, v, w):
            F, J, iF, I1, g, Fa, I4 = kinematics(w)
            iFT = transpose(iF)
            DF, dF = grad(u), grad(v)
            trA, trB = ddot(iFT, DF), ddot(iFT, dF)  # F⁻ᵀ:ΔF, F⁻ᵀ:δF
            c = ddot(transpose(mul(DF, iF)), mul(dF, iF))  # tr(ΔF F⁻¹ δF F⁻¹) = −d(F⁻ᵀ)[ΔF]:δF
            dI1 = 2.0 * ddot(F, DF)
            DFa, dFa = mul(DF, a0), mul(dF, a0)
            return h * (
                w.mu * g * ddot(DF, dF)
                - (2.0 / 3.0) * w.mu * g * trA * ddot(F, dF)
                - (w.mu / 3.0) * (g * (dI1 - (2.0 / 3.0) * I1 * trA) * trB - g * I1 * c)
                + w.kappa * ((2.0 * J - 1.0) * J * trA * trB - (J - 1.0) * J * c)
                + 2.0 * w.eta * (2.0 * dot(Fa, DFa) * dot(Fa, dFa) + (I4 - 1.0) * dot(DFa, dFa))
            )

        self.energy, self.residual, self.tangent = energy, residual, tangent
        self._kinematics = kinematics
        nd = self.basis.nodal_dofs  # (2, N): dof of component c at node n
        self.nodal_dofs = nd
        self.cup_disp = self.basis.zeros()
        for c, nodes in enumerate(tissue.cup_nodes):
            self.cup_disp[nd[0, nodes]] = tissue.cup_axes[c, 0]
            self.cup_disp[nd[1, nodes]] = tissue.cup_axes[c, 1]
        held = np.unique(np.concatenate([tissue.fixed_nodes, *tissue.cup_nodes]))
        self.D = np.sort(nd[:, held].ravel())
        self.I = self.basis.complement_dofs(self.D)
        size = float(np.ptp(mesh.nodes, axis=0).max())
        self.force_floor = 1e-3 * float(E.max()) * h * size  # as Tissue.force_scale

    def positions(self, u: np.ndarray) -> np.ndarray:
        """Deformed node positions (N, 2) mm of a displacement vector u."""
        return self.tissue.mesh.nodes + u[self.nodal_dofs].T

    def relative_residual(self, f: np.ndarray) -> float:
        """‖f_free‖ / max(‖Dirichlet reactions‖, floor): scissor's `relative_residual`."""
        return float(np.linalg.norm(f[self.I])) / max(float(np.linalg.norm(f[self.D])), self.force_floor)

    def solve(self, strokes, tol: float = 1e-10, max_iter: int = 100, stop=None) -> PeerResult:
        """Newton on the displacement u from rest to the strokes (C,) mm.

        `stop(x)`, if given, is called on every accepted iterate's positions
        and ends the solve when it returns True (the target-error criterion).
        """
        import skfem

        t0 = time.perf_counter()
        strokes = np.atleast_1d(np.asarray(strokes, float))
        u_target = self.basis.zeros()
        for c, nodes in enumerate(self.tissue.cup_nodes):
            axis = self.tissue.cup_axes[c]
            u_target[self.nodal_dofs[0, nodes]] = strokes[c] * axis[0]
            u_target[self.nodal_dofs[1, nodes]] = strokes[c] * axis[1]
        u = self.basis.zeros()
        uv = self.basis.interpolate(u)
        E0 = self.energy.assemble(self.basis, displacement=uv, **self.fields)
        out = PeerResult(self.positions(u), 0, np.nan, 0.0, False)
        for it in range(max_iter + 1):
            f = self.residual.assemble(self.basis, displacement=uv, **self.fields)
            boundary_left = np.abs(u_target[self.D] - u[self.D]).max() > 0
            res = self.relative_residual(f)
            out.history.append(res)
            if not boundary_left and res <= tol:
                out.converged = True
                break
            if it == max_iter:
                break
            K = self.tangent.assemble(self.basis, displacement=uv, **self.fields)
            du = skfem.solve(*skfem.condense(K, -f, x=u_target - u, D=self.D))
            # backtracking: every J > 0, then the energy must not rise (once the boundary is in place)
            alpha = 1.0
            while True:
                trial = u + alpha * du
                uv_t = self.basis.interpolate(trial)
                if self._kinematics({"displacement": uv_t})[1].min() > 0:
                    E_t = self.energy.assemble(self.basis, displacement=uv_t, **self.fields)
                    if boundary_left or E_t <= E0 + 1e-12 * max(abs(E0), 1.0):
                        break
                alpha *= 0.5
                if alpha < 1e-12:
                    raise RuntimeError(f"peer line search failed at iteration {it} (residual {res:.3g})")
            u, uv, E0 = trial, uv_t, E_t
            out.iterations = it + 1
            out.iterate_times.append(time.perf_counter() - t0)
            x = self.positions(u)
            out.iterate_x.append(x)
            if stop is not None and stop(x):
                break
        out.x, out.residual, out.time_s = self.positions(u), out.history[-1], time.perf_counter() - t0
        return out


# --------------------------------------------------------------------------- measurements


def target_error_fn(probe, p_ref, p_rest):
    scale = float(np.linalg.norm(p_ref - p_rest))

    def err(x):
        return float(np.linalg.norm(target_positions(probe, x) - p_ref)) / scale

    return err


def first_passing(run, err, ladder=LADDER):
    """The loosest tolerance whose solve has e ≤ TARGET_ERROR: (tol, result, error), or None."""
    for tol in ladder:
        try:
            r = run(tol)
        except SolverError:  # e.g. ADMM stopped at a loose tolerance with an inverted element: not a result
            continue
        e = err(r.x)
        if e <= TARGET_ERROR and getattr(r, "converged", True):
            return tol, r, e
    return None


def admm_run(tissue, memory, tol):
    solver = AdmmSolver(tissue, anderson_memory=memory)  # construction + factorisation included in the time
    result, _ = solver.solve(STROKE, tol=tol, max_iter=5000)
    return result


@dataclass
class Row:
    elements: int
    nodes: int
    times: dict = field(default_factory=dict)  # solver → seconds to e ≤ 1e-3
    iters: dict = field(default_factory=dict)
    tols: dict = field(default_factory=dict)
    errors: dict = field(default_factory=dict)
    ref_time: float = np.nan
    ref_iters: int = 0
    peer_full_time: float = np.nan
    peer_full_iters: int = 0
    peer_full_error: float = np.nan
    load1: float = np.nan


SOLVERS = ("newton", "admm", "admm+AA5", "peer")


def bench_mesh(cfg, scale, log, profile: bool = False) -> Row:
    scene, mesh, tissue = build_model(cfg, mesh_scale=scale)
    M = mesh.n_elements
    repeats = 5 if M < 40_000 else 3
    row = Row(M, mesh.n_nodes)
    probe = probe_targets(mesh, np.array([t.rest for t in scene.targets]))
    p_rest = target_positions(probe, mesh.nodes)

    t0 = time.perf_counter()
    ref = solve_newton(tissue, STROKE, tol=REFERENCE_TOL)
    row.ref_time, row.ref_iters = time.perf_counter() - t0, ref.iterations
    if not ref.converged:
        raise RuntimeError(f"reference Newton did not converge on {M} elements: {ref.message}")
    p_ref = target_positions(probe, ref.x)
    err = target_error_fn(probe, p_ref, p_rest)
    log(f"  {M} elements, {mesh.n_nodes} nodes: reference Newton {row.ref_time:.2f} s, {ref.iterations} it "
        f"({ref.message}), target displacement {np.linalg.norm(p_ref - p_rest):.3f} mm")

    runs = {
        "newton": lambda tol: solve_newton(tissue, STROKE, tol=tol),
        "admm": lambda tol: admm_run(tissue, 0, tol),
        "admm+AA5": lambda tol: admm_run(tissue, 5, tol),
    }
    for name, run in runs.items():
        found = first_passing(run, err)
        if found is None:
            log(f"  {name}: no tolerance of the ladder reached e ≤ {TARGET_ERROR:g}")
            row.times[name] = np.nan
            continue
        tol, _, _ = found
        r, t = timed(lambda run=run, tol=tol: run(tol), repeats, math.inf)
        row.times[name], row.iters[name], row.tols[name], row.errors[name] = t, r.iterations, tol, err(r.x)
        log(f"  {name:9s} tol {tol:<6g} {t:7.3f} s  {r.iterations:4d} it  e = {err(r.x):.2e}")

    peer = SkfemPeer(tissue)
    peer.solve(STROKE, stop=lambda x: err(x) <= TARGET_ERROR)  # warm-up (imports, first-touch memory)
    t_stop, iters, errs = [], [], []
    for _ in range(repeats):
        r = peer.solve(STROKE, stop=lambda x: err(x) <= TARGET_ERROR)
        e = err(r.x)
        if e > TARGET_ERROR:
            raise RuntimeError(f"peer stopped at e = {e:.2e} on {M} elements")
        t_stop.append(r.iterate_times[-1])
        iters.append(r.iterations)
        errs.append(e)
    row.times["peer"], row.iters["peer"], row.errors["peer"] = float(np.median(t_stop)), iters[-1], errs[-1]
    log(f"  {'peer':9s}            {row.times['peer']:7.3f} s  {iters[-1]:4d} it  e = {errs[-1]:.2e}")
    full = [peer.solve(STROKE, tol=REFERENCE_TOL) for _ in range(1 if M >= 40_000 else 3)]
    row.peer_full_time = float(np.median([r.time_s for r in full]))
    row.peer_full_iters = full[-1].iterations
    row.peer_full_error = err(full[-1].x)
    log(f"  peer to its residual 1e-10: {row.peer_full_time:.3f} s, {full[-1].iterations} it "
        f"(residual {full[-1].residual:.1e}, converged {full[-1].converged}), e vs scissor = {row.peer_full_error:.1e}")
    if profile:
        profile_solvers(tissue, peer, row, err, log)
    return row


def profile_solvers(tissue, peer, row, err, log, top=12):
    """cProfile of one run of each solver at the tolerance it needed: the functions with the most own time."""
    import cProfile
    import io
    import pstats

    runs = {
        "newton": lambda: solve_newton(tissue, STROKE, tol=row.tols["newton"]),
        "admm+AA5": lambda: admm_run(tissue, 5, row.tols["admm+AA5"]),
        "admm": lambda: admm_run(tissue, 0, row.tols["admm"]),
        "peer": lambda: peer.solve(STROKE, stop=lambda x: err(x) <= TARGET_ERROR),
    }
    for name, fn in runs.items():
        if name != "peer" and name not in row.tols:
            continue
        prof = cProfile.Profile()
        prof.enable()
        fn()
        prof.disable()
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(top)
        lines = [ln for ln in buf.getvalue().splitlines() if ln.strip()]
        start = next(i for i, ln in enumerate(lines) if ln.lstrip().startswith("ncalls"))
        total = next(ln for ln in lines if "function calls" in ln).split("in")[-1].strip()
        log(f"  profile {name} ({total}), by own time:")
        for ln in lines[start:]:
            log("    " + ln.replace(ROOT + os.sep, "").replace(os.path.dirname(np.__path__[0]) + os.sep, ""))


def growth_exponent(elements, times) -> float:
    ok = np.isfinite(times) & (np.asarray(times) > 0)
    if ok.sum() < 2:
        return np.nan
    return float(np.polyfit(np.log(np.asarray(elements)[ok]), np.log(np.asarray(times)[ok]), 1)[0])


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            names = [ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    import scipy
    import skfem

    return (f"{os.cpu_count()} cores ({cpu}), Python {platform.python_version()}, numpy {np.__version__}, "
            f"scipy {scipy.__version__}, scikit-fem {skfem.__version__}")


def _loadavg() -> str:
    try:
        with open("/proc/loadavg") as fh:
            return " ".join(fh.read().split()[:3])
    except OSError:
        return "n/a"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="stop after the ~16k mesh")
    parser.add_argument("--profile", action="store_true", help="cProfile one run of each solver on the largest mesh")
    parser.add_argument("--blas-threads", type=int, default=None,
                        help="set OPENBLAS/OMP_NUM_THREADS (default: leave the environment alone)")
    args = parser.parse_args(argv)
    try:
        import skfem  # noqa: F401
    except ImportError:
        print("scikit-fem is not installed (pip install scikit-fem); the peer cannot run", file=sys.stderr)
        return 2
    t_start = time.perf_counter()
    variant = ".".join(p for p in ("quick" if args.quick else None, "profile" if args.profile else None,
                                   None if args.blas_threads is None else f"blas{args.blas_threads}") if p)
    res = results_io.Results("bench_solvers", variant or None)
    cfg = load_config(CONFIG)
    print(f"bench_solvers: {cfg.name!r}, quasi-static {STROKE[0]:g} mm push, model {cfg.material.model}; "
          f"time to relative target error ≤ {TARGET_ERROR:g} vs Newton at {REFERENCE_TOL:g}")
    print(f"machine: {machine()}")
    print(f"BLAS threads: OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}; "
          f"load average before: {_loadavg()} (other processes on the cores slow every solver, OpenBLAS-threaded "
          "code most)")
    rows = []
    scales = SCALES[:3] if args.quick else SCALES
    for scale in scales:
        print(f"\nmesh_scale {scale:g} (graded):", flush=True)
        row = bench_mesh(cfg, scale, lambda s: print(s, flush=True), profile=args.profile and scale == scales[-1])
        rows.append(row)
        print(f"  load average: {_loadavg()}", flush=True)
        row.load1 = results_io.load1()

    print("\nTime to relative target error ≤ 1e-3 (s, median of 5 repeats; 3 on the 64k mesh), iterations in ()")
    head = (f"{'elements':>9} | {'newton':>14} | {'admm':>14} | {'admm+AA5':>14} | {'peer (skfem)':>14} | "
            f"{'peer/best':>9} | {'best':>8} | {'peer→1e-10':>14}")
    print(head)
    print("-" * len(head))
    for r in rows:
        cells = []
        for s in SOLVERS:
            t = r.times.get(s, np.nan)
            cells.append(f"{t:8.3f} ({r.iters.get(s, 0):3d})" if np.isfinite(t) else f"{'—':>14}")
        sc = {s: r.times[s] for s in SOLVERS[:3] if np.isfinite(r.times.get(s, np.nan))}
        best = min(sc, key=sc.get)
        ratio = r.times["peer"] / sc[best]
        print(f"{r.elements:9d} | " + " | ".join(cells) + f" | {ratio:8.1f}x | {best:>8} | "
              f"{r.peer_full_time:8.3f} ({r.peer_full_iters:3d})")
    print("\nTolerance each solver needed (its own relative residual), and the target error reached:")
    for r in rows:
        print(f"{r.elements:9d}: " + ", ".join(
            f"{s} tol {r.tols[s]:g} → e {r.errors[s]:.1e}" for s in SOLVERS[:3] if s in r.tols)
            + f", peer e {r.errors['peer']:.1e}; scissor Newton to 1e-10: {r.ref_time:.3f} s ({r.ref_iters} it); "
            f"peer at 1e-10 vs scissor reference: e {r.peer_full_error:.1e}")
    elements = [r.elements for r in rows]
    print(f"\nGrowth exponent of time with elements (least-squares slope of log t vs log M over {len(rows)} "
          "sizes; goal ≤ 1.3):")
    series = {s: [r.times.get(s, np.nan) for r in rows] for s in SOLVERS}
    series["newton→1e-10"] = [r.ref_time for r in rows]
    series["peer→1e-10"] = [r.peer_full_time for r in rows]
    pairs = [f"{a // 1000}k→{b // 1000}k" for a, b in itertools.pairwise(elements)]
    print("  (fit: over all sizes; then the local slope between consecutive sizes)")
    print(f"  {'solver':13s} {'fit':>5} " + " ".join(f"{p:>10}" for p in pairs))
    for s, t in series.items():
        local = [growth_exponent(elements[i:i + 2], t[i:i + 2]) for i in range(len(pairs))]
        print(f"  {s:13s} {growth_exponent(elements, t):5.2f} " + " ".join(f"{v:10.2f}" for v in local))
    r16 = min(rows, key=lambda r: abs(r.elements - 16_000))
    sc = min(r16.times[s] for s in SOLVERS[:3] if np.isfinite(r16.times.get(s, np.nan)))
    print(f"\nAt {r16.elements} elements: peer / best scissor = {r16.times['peer'] / sc:.1f}x (goal ≥ 10x, "
          "docs/performance.md)")
    print(f"total {time.perf_counter() - t_start:.0f} s; load average after: {_loadavg()}")
    table = []
    for r in rows:
        ours = {s: r.times[s] for s in SOLVERS[:3] if np.isfinite(r.times.get(s, np.nan))}
        best = min(ours, key=ours.get)
        out = {"elements": r.elements, "nodes": r.nodes, "best": best, "peer_over_best": r.times["peer"] / ours[best],
               "newton_1e10_s": r.ref_time, "newton_1e10_iterations": r.ref_iters,
               "peer_1e10_s": r.peer_full_time, "peer_1e10_iterations": r.peer_full_iters,
               "peer_1e10_error": r.peer_full_error, "load1": r.load1}
        for s in SOLVERS:
            out[f"{s}_s"] = r.times.get(s, np.nan)
            out[f"{s}_iterations"] = r.iters.get(s)
            out[f"{s}_tol"] = r.tols.get(s)
            out[f"{s}_error"] = r.errors.get(s)
        table.append(out)
    res.table("sizes", table, {**{f"{s}_s": "s (to target error 1e-3)" for s in SOLVERS},
                               "newton_1e10_s": "s", "peer_1e10_s": "s", "peer_over_best": "ratio"})
    res.table("growth", [{"solver": s, "exponent": growth_exponent(elements, t)} for s, t in series.items()],
              {"exponent": "slope of log t vs log elements"})
    res.figure("peer_over_best_16k", r16.times["peer"] / sc, "ratio", elements=r16.elements, goal=">= 10")
    res.figure("total_s", time.perf_counter() - t_start, "s")
    res.write()
    return 0


if __name__ == "__main__":
    runtime.keep_freed_memory()
    if _blas_threads_from_argv(sys.argv) is None:  # else the environment set above decides
        runtime.limit_blas_threads()
    raise SystemExit(main())
