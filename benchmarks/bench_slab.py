"""Speed of the 3-D slab's Newton solve (docs/model.md §13) against scikit-fem on the same energy.

The example scene's layer_check slab (height 40 mm, layer at 20 mm, chest
wall held, the cup holding z, prism layers up to max_layer_mm), its 2-D mesh
at mesh scales 2, 1.5, 1.08 and 1 (37.8k, 53.0k, 99.9k and 128k tetrahedra;
the goal names ~50k and 100k); a 5 mm push. scissor: `solve_equilibrium`
(the one Newton, projected far from the solution, exact near it; in 3-D a
CHOLMOD factor ordered by nested dissection, most steps by conjugate
gradients preconditioned with an earlier factor). The peer: the neo-Hookean fiber
energy written with scikit-fem (`MeshTet`, `ElementVector(ElementTetP1())`,
forms with `skfem.helpers`), Newton with `condense` + `solve` and a
backtracking line search keeping J > 0 — as `bench_solvers.py` does in 2-D.
Both solve to the relative residual 1e-8 (scissor's measure); the table
gives the wall times, iterations, factorisations, CG iterations, the
factor's nonzeros, the largest target difference and the 1-minute load
average when each size finished (2 cores shared: compare ratios, counts).

    PYTHONPATH=. python benchmarks/bench_slab.py [--quick] [--no-peer]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from scissor_cli import runtime  # noqa: E402

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels
import results_io  # noqa: E402

from scissor_cli.config import load_config  # noqa: E402
from scissor_cli.experiments.build import build_model  # noqa: E402
from scissor_cli.layer3d.slab import SlabSpec, build_slab, slab_probe  # noqa: E402
from scissor_cli.mechanics.tissue import Tissue  # noqa: E402
from scissor_cli.solvers.equilibrium import solve_equilibrium  # noqa: E402

CONFIG = os.path.join(ROOT, "scissor_cli", "scenes", "example.yaml")
SPEC = SlabSpec(40.0, 20.0, chest_wall_fixed=True, cup_holds_z=True, max_layer_mm=5.0)
#: (mesh scale, max_layer_mm) → 37.8k, 53.0k, 99.9k, 128k tetrahedra (the example at scale 1 is the default slab)
SIZES = ((2.0, 5.0), (1.5, 5.0), (1.08, 5.0), (1.0, 5.0))
STROKE = np.array([5.0])
TOL = 1e-8


class SkfemSlabPeer:
    """The slab's energy (docs/model.md §3 with 3x3 F) in scikit-fem; the slab tissue's Dirichlet dofs."""

    def __init__(self, slab: Tissue):
        import skfem
        from skfem.helpers import ddot, det, dot, grad, identity, inv, mul, prod, transpose

        m = slab.scene.material
        if slab.params.model not in ("neo_hookean", "neo_hookean_fiber") or slab.params.tension_only:
            raise NotImplementedError("the peer implements the neo-Hookean models with two-sided fibers")
        self.slab = slab
        mesh = slab.mesh
        self.mesh = skfem.MeshTet(mesh.nodes.T.copy(), mesh.tetrahedra.T.copy())
        rule = (np.full((3, 1), 0.25), np.array([1.0 / 6.0]))  # P1: F constant, the centroid rule is exact
        self.basis = skfem.Basis(self.mesh, skfem.ElementVector(skfem.ElementTetP1()), quadrature=rule)
        b0 = self.basis.with_element(skfem.ElementTetP0())
        E = slab.element_E_kPa
        eta = m.eta_kPa if slab.params.model == "neo_hookean_fiber" else 0.0
        self.fields = {"mu": b0.interpolate(E / (2 * (1 + m.nu))), "kappa": b0.interpolate(E / (3 * (1 - 2 * m.nu))),
                       "eta": b0.interpolate(np.full(mesh.n_elements, eta))}
        a0 = np.array([np.cos(m.fiber_angle_rad), np.sin(m.fiber_angle_rad), 0.0])[:, None, None]

        def kin(w):
            F = grad(w["displacement"]) + identity(grad(w["displacement"]))
            J = det(F)
            Fa = mul(F, a0)
            return F, J, inv(F), ddot(F, F), J ** (-2.0 / 3.0), Fa, dot(Fa, Fa)

        @skfem.Functional
        def energy(w):
            _, J, _, I1, g, _, I4 = kin(w)
            return 0.5 * w.mu * (g * I1 - 3.0) + 0.5 * w.kappa * (J - 1.0) ** 2 + 0.5 * w.eta * (I4 - 1.0) ** 2

        @skfem.LinearForm
        def residual(v, w):
            F, J, iF, I1, g, Fa, I4 = kin(w)
            iFT = transpose(iF)
            P = (w.mu * g * F - (w.mu / 3.0) * g * I1 * iFT + w.kappa * (J - 1.0) * J * iFT
                 + 2.0 * w.eta * (I4 - 1.0) * prod(Fa, a0))
            return ddot(P, grad(v))

        @skfem.BilinearForm
        def tangent(u, v, w):
            F, J, iF, I1, g, Fa, I4 = kin(w)
            iFT = transpose(iF)
            DF, dF = grad(u), grad(v)
            trA, trB = ddot(iFT, DF), ddot(iFT, dF)
            c = ddot(transpose(mul(DF, iF)), mul(dF, iF))
            dI1 = 2.0 * ddot(F, DF)
            DFa, dFa = mul(DF, a0), mul(dF, a0)
            return (w.mu * g * ddot(DF, dF) - (2.0 / 3.0) * w.mu * g * trA * ddot(F, dF)
                    - (w.mu / 3.0) * (g * (dI1 - (2.0 / 3.0) * I1 * trA) * trB - g * I1 * c)
                    + w.kappa * ((2.0 * J - 1.0) * J * trA * trB - (J - 1.0) * J * c)
                    + 2.0 * w.eta * (2.0 * dot(Fa, DFa) * dot(Fa, dFa) + (I4 - 1.0) * dot(DFa, dFa)))

        self.energy, self.residual, self.tangent, self.kin = energy, residual, tangent, kin
        nd = self.basis.nodal_dofs  # (3, N)
        self.to_skfem = nd.T.ravel()  # scissor dof 3n + c → skfem dof
        self.D = np.sort(self.to_skfem[slab.dirichlet_dofs])
        self.I = self.basis.complement_dofs(self.D)
        self.floor = slab.force_floor

    def solve(self, strokes, tol: float = TOL, max_iter: int = 100):
        import skfem

        t0 = time.perf_counter()
        target = np.zeros(self.basis.N)
        u_dir = (self.slab.apply_strokes(self.slab.rest, strokes) - self.slab.rest).ravel()
        target[self.to_skfem] = u_dir
        u = self.basis.zeros()
        uv = self.basis.interpolate(u)
        E0 = self.energy.assemble(self.basis, displacement=uv, **self.fields)
        it = 0
        for it in range(max_iter + 1):
            f = self.residual.assemble(self.basis, displacement=uv, **self.fields)
            left = np.abs(target[self.D] - u[self.D]).max() > 0
            res = float(np.linalg.norm(f[self.I])) / max(float(np.linalg.norm(f[self.D])), self.floor)
            if not left and res <= tol:
                break
            K = self.tangent.assemble(self.basis, displacement=uv, **self.fields)
            du = skfem.solve(*skfem.condense(K, -f, x=target - u, D=self.D))
            alpha = 1.0
            while True:
                trial = u + alpha * du
                uv_t = self.basis.interpolate(trial)
                with np.errstate(invalid="ignore"):  # J^(-2/3) of an inverted trial: rejected on J
                    feasible = self.kin({"displacement": uv_t})[1].min() > 0
                if feasible:
                    E_t = self.energy.assemble(self.basis, displacement=uv_t, **self.fields)
                    if left or E_t <= E0 + 1e-12 * max(abs(E0), 1.0):
                        break
                alpha *= 0.5
                if alpha < 1e-12:
                    raise RuntimeError(f"peer line search failed at iteration {it}")
            u, uv, E0 = trial, uv_t, E_t
        x = self.slab.rest + u[self.to_skfem].reshape(-1, 3)
        return x, it, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="only the 37.8k and 53.0k slabs")
    ap.add_argument("--no-peer", action="store_true", help="scissor only")
    args = ap.parse_args()
    res = results_io.Results("bench_slab", ".".join(p for p in ("quick" if args.quick else None,
                                                                 "no-peer" if args.no_peer else None) if p) or None)
    cfg = load_config(CONFIG)
    print(f"bench_slab: example scene, slab {SPEC.height_mm:g} mm, layer at {SPEC.layer_z_mm:g} mm, "
          f"{STROKE[0]:g} mm push, both Newton to relative residual {TOL:g}; machine: {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}")
    rows = []
    for scale, max_layer in SIZES[:2] if args.quick else SIZES:
        scene, mesh, tissue = build_model(cfg, mesh_scale=scale)
        t0 = time.perf_counter()
        slab = build_slab(scene, mesh, SlabSpec(SPEC.height_mm, SPEC.layer_z_mm, True, True, max_layer))
        build_s = time.perf_counter() - t0
        probe = slab_probe(slab, np.array([t.rest for t in scene.targets]))
        r = solve_equilibrium(slab, STROKE, tol=TOL)
        factor = slab.factor_cache["free"]
        row = {"tets": slab.mesh.n_elements, "dofs": len(slab.free_dofs), "build_s": build_s, "scissor_s": r.time_s,
               "scissor_it": r.iterations, "factor": r.factorizations, "cg": factor.cg_iterations,
               "nnz_L_M": factor.nnz_factor / 1e6}
        if not args.no_peer:
            peer = SkfemSlabPeer(slab)
            xp, itp, tp = peer.solve(STROKE)
            row |= {"peer_s": tp, "peer_it": itp,
                    "diff_mm": float(np.abs(probe.positions(xp) - probe.positions(r.x)).max())}
        row["load"] = os.getloadavg()[0]
        rows.append(row)
        print("  " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()),
              flush=True)
    print("\n tetrahedra |   free dofs |  build s | scissor s (it, factorisations, CG) | nnz(L) |  peer s (it) "
          "| peer/scissor | target diff mm | load")
    for row in rows:
        peer = f"{row['peer_s']:8.1f} ({row['peer_it']:2d})" if "peer_s" in row else "       -     "
        ratio = f"{row['peer_s'] / row['scissor_s']:11.1f}x" if "peer_s" in row else "           -"
        diff = f"{row['diff_mm']:.1e}" if "diff_mm" in row else "-"
        print(f" {row['tets']:10d} | {row['dofs']:11d} | {row['build_s']:8.1f} | {row['scissor_s']:9.1f} "
              f"({row['scissor_it']:2d}, {row['factor']:2d}, {row['cg']:3d})           | {row['nnz_L_M']:5.1f}M | "
              f"{peer} "
              f"| {ratio} | {diff:>14} | {row['load']:.2f}")
    print(f"goals (docs/model.md §13): peer/scissor ≥ 5x at ~50k, scissor ≤ 10 s at 100k; load average "
          f"{os.getloadavg()[0]:.2f}")
    for row in rows:
        if "peer_s" in row:
            row["peer_over_scissor"] = row["peer_s"] / row["scissor_s"]
    res.table("sizes", rows, {"build_s": "s", "scissor_s": "s", "peer_s": "s", "nnz_L_M": "million nonzeros",
                              "diff_mm": "mm", "load": "1-minute load average", "peer_over_scissor": "ratio"})
    res.write()


if __name__ == "__main__":
    main()
