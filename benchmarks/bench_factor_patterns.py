"""What a factorisation costs on each form's sparsity pattern: `p1`, `nodal`, and the mixed forms that would give
`nodal` a one-ring pattern (docs/model.md §21, "What it does not do yet"); a measurement, not a test.

`nodal`'s tangent couples each node with its neighbours' neighbours: the averaged F̄_a (its volume J̄_a and, for
the share 1 − α of the deviatoric energy, the rest of it) is a sum over node a's ring of elements. A mixed form
would keep the pattern one-ring by making the averaged quantity an unknown per node:

* u–p: a pressure per node (lumped), with the deviatoric energy per element: the built element at α = 1;
* u–F̄: the averaged deformation gradient per node (9 unknowns), the built element at any α.

Eliminating the node's own block gives back `nodal`'s two-ring K_ff, so the mixed system is the same physics.
It is indefinite (quasi-definite: a static-pivot LDLᵀ exists in any ordering). CHOLMOD's supernodal LLᵀ on the
same pattern bounds what a supernodal LDLᵀ would cost (the same flops; cvxopt's CHOLMOD has no supernodal LDLᵀ),
so each mixed pattern is timed as LLᵀ on a positive definite matrix of that pattern (seeded values: the time of a
factorisation without pivoting depends on the pattern only), ordered as scissor orders a 3-D factor (METIS by node,
each node's unknowns together, or AMD where sparser: `solvers.linear.Factorization`). `p1` and `nodal` are the
scene's own K_ff at rest. qdldl, the indefinite LDLᵀ scissor has (simplicial), is timed on the u–p system.

    PYTHONPATH=. python benchmarks/bench_factor_patterns.py [--scales 1.0 0.7] [--repeats 5]
"""

from __future__ import annotations

import argparse
from functools import partial
from pathlib import Path

import numpy as np
import results_io
import scipy.sparse as sp

from scissor_cli import runtime

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"
SEED = 0


def mixed_pattern(G: sp.csr_matrix, per_node: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """The pattern of a u–field system (3 displacements and `per_node` field unknowns per node): u–u and u–field
    coupled over the one-ring G (the node graph (n, n) of `p1`'s K_ff, `ordering.node_graph`), the field coupled
    within its node only; and each unknown's node (n,)."""
    n = G.shape[0]
    G = (G + sp.identity(n)).tocsr()
    G.data[:] = 1.0
    uu, uf = sp.kron(G, np.ones((3, 3))), sp.kron(G, np.ones((3, per_node)))
    ff = sp.kron(sp.identity(n), np.ones((per_node, per_node)))
    groups = np.concatenate([np.repeat(np.arange(n), 3), np.repeat(np.arange(n), per_node)])
    return sp.bmat([[uu, uf], [uf.T, ff]]).tocsr(), groups


def valued(pattern: sp.csr_matrix, rng: np.random.Generator, negative_from: int | None = None) -> sp.csr_matrix:
    """A symmetric matrix of `pattern`: small seeded off-diagonal values and a dominant diagonal, positive
    definite; with `negative_from`, the unknowns from that index on get a negative diagonal (quasi-definite)."""
    A = sp.triu(pattern, 1).tocsr()
    A.data = rng.uniform(-1e-3, 1e-3, A.nnz)
    diagonal = np.full(pattern.shape[0], 10.0)
    if negative_from is not None:
        diagonal[negative_from:] = -10.0
    return (A + A.T + sp.diags(diagonal)).tocsr()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 0.7],
                    help="mesh scales (1: the default; 0.7: the insertion goal's ~30k tetrahedra)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    runtime.configure()
    import qdldl

    from scissor_cli.config import load_config
    from scissor_cli.experiments.build import body_model
    from scissor_cli.mechanics.body_tissue import build_body
    from scissor_cli.solvers.linear import Factorization
    from scissor_cli.solvers.ordering import node_graph

    res = results_io.Results("bench_factor_patterns")
    cfg = load_config(CONFIG)
    if cfg.tissue.mesh.element != "nodal":
        raise SystemExit(f"{CONFIG.name}: the default element nodal expected, found {cfg.tissue.mesh.element}")
    rng = np.random.default_rng(SEED)
    rows = []
    for scale in args.scales:
        scene, mesh, nodal = body_model(cfg, cache=ROOT / "runs" / ".mesh-cache", scale=scale)
        p1 = build_body(scene, mesh, element="p1")
        node_of_dof = nodal.free_dofs // 3
        K_p1 = p1.stiffness_free(p1.rest, upper=True)
        G, _ = node_graph(K_p1, node_of_dof)
        forms = [("p1", K_p1, node_of_dof, "the scene's K_ff"),
                 ("nodal", nodal.stiffness_free(nodal.rest, upper=True), node_of_dof, "the scene's K_ff")]
        patterns = {name: mixed_pattern(G, per_node) for name, per_node in (("u–p", 1), ("u–F̄", 9))}
        for name, (pattern, groups) in patterns.items():
            forms.append((name, sp.triu(valued(pattern, rng)).tocsr(), groups, "LLᵀ on its pattern"))
        print(f"scale {scale:g}: {mesh.n_elements} tetrahedra, {G.shape[0]} free nodes", flush=True)
        for name, K_upper, groups, what in forms:
            factor = Factorization(K_upper, definite=True, upper=True, ordering="nested_dissection", groups=groups)
            factor_s = results_io.median_s(partial(factor.refactor, K_upper), args.repeats)
            b = rng.standard_normal(K_upper.shape[0])
            solve_s = results_io.median_s(partial(factor.solve, b), args.repeats)
            row = {"scale": scale, "tetrahedra": int(mesh.n_elements), "form": name, "matrix": what,
                   "unknowns": int(K_upper.shape[0]), "nnz_upper": int(K_upper.nnz),
                   "nnz_factor": int(factor.nnz_factor), "factor_s": factor_s, "solve_s": solve_s,
                   "qdldl_s": None}
            if name == "u–p":  # the quasi-definite system itself, through the LDLᵀ scissor has
                A = sp.triu(valued(patterns[name][0], rng, negative_from=3 * G.shape[0])).tocsc()
                solver = qdldl.Solver(A, upper=True)  # (its analysis once, as `refactor` keeps CHOLMOD's)
                row["qdldl_s"] = results_io.median_s(partial(solver.update, A), max(1, args.repeats // 2))
            rows.append(row)
            print(f"  {name} ({what}): {row['unknowns']} unknowns, factor {row['nnz_factor'] / 1e6:.2f} M, "
                  f"factorisation {1e3 * factor_s:.1f} ms, solve {1e3 * solve_s:.2f} ms"
                  + (f", qdldl {1e3 * row['qdldl_s']:.0f} ms" if row["qdldl_s"] else ""), flush=True)
    res.table("forms", rows, {"factor_s": "s", "solve_s": "s", "qdldl_s": "s"})
    res.write()


if __name__ == "__main__":
    main()
