"""The 3-D body mesher (scissor_cli/mesh/body_mesh.py, docs/model.md §19): time, quality, regions; not a test.

The example's dome (radius 60 mm, height 35 mm; lesions of radius 2 mm at
(10, 20, 15) and (-5, 8, 15), a vessel of radius 1.5 mm from (26, 23, 15) to
(45, 23, 15), a cyst of radius 5 mm at (20, -20, 12), a cup patch of radius
5 mm at the skin point nearest (0, 57.5, 10)) meshed at the sizings whose
estimate is about 10k, 30k and 100k tetrahedra (min_edge_mm found by
bisection on estimate_tetrahedra, max_edge_mm = 10 min_edge_mm, grading 0.3):
tetrahedra, nodes, the dihedral angles' distribution, each region's volume
against its analytic one, the meshing time (median of --repeat runs) and the
time of the same call served from the cache. Goal: <= 5 s at ~30k.

* --fit: the estimate's fit set (domes with and without a skin at four
  gradings and two sizes, spheres and boxes from surfaces): real over
  estimated tetrahedra, and the ESTIMATE_FACTOR and SHELL_FACTOR that bring
  the worst case closest (estimate_tetrahedra's docstring);
* --random N: N random domes (inclusions, a bent vessel, a skin or not,
  min_edge_mm 0.3 to 0.7 of the smallest radius): the distribution of their
  smallest dihedral angles, what MIN_DIHEDRAL_DEG is chosen from.

    PYTHONPATH=. python3 benchmarks/bench_body_mesh.py [--repeat 3] [--fit] [--random 30]

Writes benchmarks/results/bench_body_mesh.json (with --fit or --random: a variant of its own) through
results_io: the figures, the machine, the load, date, commit and the command.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import results_io  # noqa: E402
from scenes.body_surfaces import box, icosphere  # noqa: E402

from scissor_cli.config.surface_file import checked_surface  # noqa: E402
from scissor_cli.mesh import body_geometry, body_mesh, body_quality  # noqa: E402
from scissor_cli.mesh.body_field import density_integral, polyline_distance  # noqa: E402
from scissor_cli.mesh.body_mesh import BodyShape, BodySizing, Sphere, Tube, estimate_tetrahedra  # noqa: E402

A, H = 60.0, 35.0
INCLUSIONS = (Sphere("lesion", np.array([10.0, 20.0, 15.0]), 2.0), Sphere("lesion_2", np.array([-5.0, 8.0, 15.0]), 2.0),
              Tube("vessel", np.array([[26.0, 23.0, 15.0], [45.0, 23.0, 15.0]]), 1.5),
              Sphere("cyst", np.array([20.0, -20.0, 12.0]), 5.0))
GRADING, MAX_PER_MIN = 0.3, 10.0


def nearest_on_dome(q: np.ndarray, a: float = A, h: float = H) -> np.ndarray:
    """The point of the half-spheroid's curved surface nearest q: a coarse grid of angles, then a fine one."""
    best, span = None, (np.pi, np.pi / 2)
    center = np.array([0.0, np.pi / 4])
    for _ in range(4):  # each pass: 181 x 91 angles around the best so far, the span cut by 30
        t = center[0] + np.linspace(-span[0], span[0], 181)
        u = np.clip(center[1] + np.linspace(-span[1], span[1], 91), 0.0, np.pi / 2)
        tt, uu = np.meshgrid(t, u, indexing="ij")
        p = np.stack([a * np.cos(uu) * np.cos(tt), a * np.cos(uu) * np.sin(tt), h * np.sin(uu)], axis=-1).reshape(-1, 3)
        k = int(np.argmin(np.linalg.norm(p - q, axis=1)))
        best, center = p[k], np.array([tt.ravel()[k], uu.ravel()[k]])
        span = (span[0] / 30, span[1] / 30)
    return best


def sizing_for(target: int, shape: BodyShape, inclusions: tuple, refine: tuple) -> BodySizing:
    """The sizing of the family (min, 10 min, grading 0.3) whose estimate is `target` tetrahedra."""
    lo, hi = 0.05, 20.0
    for _ in range(40):  # bisection on log(min_edge): the estimate falls as min_edge grows
        mid = np.sqrt(lo * hi)
        if estimate_tetrahedra(shape, inclusions, BodySizing(mid, MAX_PER_MIN * mid, GRADING, refine)) > target:
            lo = mid
        else:
            hi = mid
    m = float(np.sqrt(lo * hi))
    return BodySizing(round(m, 4), round(MAX_PER_MIN * m, 4), GRADING, refine)


def region_volumes(mesh) -> dict:
    """Each region's volume (mm³), its analytic or Monte Carlo volume, and the relative error."""
    volumes = np.bincount(mesh.region, weights=body_quality.signed_volumes(mesh.nodes, mesh.tetrahedra),
                          minlength=len(mesh.region_names))
    exact = {"all": 2 / 3 * np.pi * A**2 * H}
    for inc in INCLUSIONS:
        if isinstance(inc, Sphere):
            exact[inc.name] = 4 / 3 * np.pi * inc.radius_mm**3
        else:  # the capsules along the polyline inside the dome, by Monte Carlo (2e6 points: 0.2 % noise)
            rng = np.random.default_rng(0)
            lo, hi = inc.points_mm.min(axis=0) - inc.radius_mm, inc.points_mm.max(axis=0) + inc.radius_mm
            q = rng.uniform(lo, hi, (2_000_000, 3))
            inside = (polyline_distance(q, inc.points_mm) <= inc.radius_mm) & body_geometry.dome_inside(A, H)(q)
            exact[inc.name] = float(np.prod(hi - lo) * inside.mean())
    out = {}
    for name, reference in exact.items():
        got = float(volumes.sum()) if name == "all" else float(volumes[mesh.region_names.index(name)])
        out[name] = {"mesh_mm3": round(got, 3), "exact_mm3": round(reference, 3),
                     "error_percent": round(100 * (got - reference) / reference, 2)}
    return out


def dihedral_summary(mesh) -> dict:
    angles = body_quality.min_dihedral_deg(mesh.nodes, mesh.tetrahedra)
    q = np.percentile(angles, [0.1, 1, 5, 50])
    return {"min_deg": round(float(angles.min()), 2), "p0.1_deg": round(float(q[0]), 2),
            "p1_deg": round(float(q[1]), 2), "p5_deg": round(float(q[2]), 2), "median_deg": round(float(q[3]), 2),
            "below_10deg": int(np.sum(angles < 10))}


def bench_example(targets, repeat: int) -> list:
    shape = BodyShape("dome", A, H)
    refine = ((nearest_on_dome(np.array([0.0, 57.5, 10.0])), 5.0),)
    rows = []
    for target in targets:
        sizing = sizing_for(target, shape, INCLUSIONS, refine)
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            mesh = body_mesh.body_mesh(shape, INCLUSIONS, sizing)
            times.append(time.perf_counter() - start)
        with tempfile.TemporaryDirectory() as cache:
            body_mesh.body_mesh(shape, INCLUSIONS, sizing, cache_dir=Path(cache))
            cached = []
            for _ in range(repeat):
                start = time.perf_counter()
                body_mesh.body_mesh(shape, INCLUSIONS, sizing, cache_dir=Path(cache))
                cached.append(time.perf_counter() - start)
        start = time.perf_counter()
        estimate = estimate_tetrahedra(shape, INCLUSIONS, sizing)
        estimate_s = time.perf_counter() - start
        row = {"target_tetrahedra": target, "min_edge_mm": sizing.min_edge_mm, "max_edge_mm": sizing.max_edge_mm,
               "grading": sizing.grading, "tetrahedra": mesh.n_elements, "nodes": mesh.n_nodes,
               "estimate": estimate, "real_over_estimate": round(mesh.n_elements / estimate, 3),
               "mesh_s_median": round(float(np.median(times)), 3), "mesh_s_all": [round(t, 3) for t in times],
               "cached_s_median": round(float(np.median(cached)), 4), "estimate_s": round(estimate_s, 3),
               "dihedral": dihedral_summary(mesh), "regions": region_volumes(mesh)}
        rows.append(row)
        print(f"~{target // 1000}k: {mesh.n_elements} tets, {mesh.n_nodes} nodes, estimate {estimate}; "
              f"mesh {row['mesh_s_median']:.2f} s (median of {repeat}), cached {row['cached_s_median'] * 1e3:.1f} ms; "
              f"min dihedral {row['dihedral']['min_deg']}°, "
              + ", ".join(f"{k} {v['error_percent']:+.1f}%" for k, v in row["regions"].items()), flush=True)
    return rows


def fit_cases() -> list:
    """(name, shape, inclusions, sizing) of the estimate's fit set."""
    cases = []
    for skin in (None, 1.5):
        for m, big in ((0.8, 8.0), (1.5, 15.0)):
            for g in (0.15, 0.3, 0.6, 1.0):
                cases.append((f"dome skin={skin} {m}/{big}/{g}", BodyShape("dome", A, H, skin_thickness_mm=skin),
                              INCLUSIONS, BodySizing(m, big, g)))
    sphere = checked_surface(*icosphere(30.0, subdivisions=3))
    cuboid = checked_surface(*box((-40, -30, 0), (40, 30, 35)))
    inside = (Sphere("lesion", np.array([5.0, 5.0, 10.0]), 3.0),
              Tube("vessel", np.array([[-10.0, -5.0, 5.0], [10.0, -5.0, 8.0], [45.0, -5.0, 12.0]]), 1.5))
    for name, (nodes, triangles) in (("sphere", sphere), ("box", cuboid)):
        for skin in (None, 1.5):
            for m, big, g in ((1.0, 8.0, 0.3), (0.6, 5.0, 0.6)):
                cases.append((f"{name} skin={skin} {m}/{big}/{g}",
                              BodyShape("surface", surface_nodes=nodes, surface_triangles=triangles,
                                        skin_thickness_mm=skin), inside, BodySizing(m, big, g)))
    return cases


def fit_estimate() -> dict:
    """Mesh the fit set; the factors that minimise the worst |log(real / estimate)|."""
    rows = []
    for name, shape, inclusions, sizing in fit_cases():
        real = body_mesh.body_mesh(shape, inclusions, sizing).n_elements
        shape_c, inclusions_c, sizing_c = body_mesh._checked(shape, inclusions, sizing)
        features = body_mesh._features(shape_c, inclusions_c, sizing_c)
        if shape.kind == "dome":
            inside, lo, hi = body_geometry.dome_inside(A, H), np.array([-A, -A, 0.0]), np.array([A, A, H])
        else:
            inside = body_geometry.surface_inside(shape_c.surface_nodes, shape_c.surface_triangles)
            lo, hi = shape_c.surface_nodes.min(axis=0), shape_c.surface_nodes.max(axis=0)
        plain = density_integral(features, inside, lo, hi, 0.0)
        per_shell = density_integral(features, inside, lo, hi, 1.0) - plain if shape.skin_thickness_mm else 0.0
        rows.append((name, real, plain, per_shell))
        print(f"  {name}: {real} tetrahedra", flush=True)

    def integral(row, shell):
        # a shell's weight is max(1, shell · h / t) with h = 2 t there (SKIN_EDGE_PER_THICKNESS, unclipped in this
        # set): the integral at shell = 1 less the plain one is the shell's part at weight 1
        _, _, plain, per_shell = row
        return plain + max(2.0 * shell - 1.0, 0.0) * per_shell

    best = None
    for shell in np.arange(0.5, 4.001, 0.05):
        logs = np.array([np.log(real / integral(row, shell)) for row in rows for real in [row[1]]])
        factor = float(np.exp(0.5 * (logs.max() + logs.min())))
        worst = float(np.max(np.abs(logs - np.log(factor))))
        if best is None or worst < best[0]:
            best = (worst, float(shell), factor)
    worst, shell, factor = best
    cases = [{"case": row[0], "tetrahedra": row[1], "fitted_estimate": int(round(factor * integral(row, shell)))}
             for row in rows]
    print(f"fit: ESTIMATE_FACTOR {factor:.3f}, SHELL_FACTOR {shell:.2f}: every case within a factor "
          f"{np.exp(worst):.3f}")
    return {"estimate_factor": round(factor, 3), "shell_factor": round(shell, 2),
            "worst_factor": round(float(np.exp(worst)), 3), "cases": cases}


def random_domes(n: int, seed: int = 1) -> dict:
    """Smallest dihedral angle of n random dome scenes."""
    rng = np.random.default_rng(seed)
    minima, failures = [], []
    for _ in range(n):
        a, h = rng.uniform(45, 75), rng.uniform(25, 45)

        def inside_point(margin, a=a, h=h):
            while True:
                p = rng.uniform([-a, -a, 0], [a, a, h])
                if (p[0] ** 2 + p[1] ** 2) / (a - margin) ** 2 + p[2] ** 2 / (h - margin) ** 2 < 1 and p[2] > margin:
                    return p

        radii = rng.uniform(1.5, 6, rng.integers(1, 4))
        inclusions = [Sphere(f"s{k}", inside_point(r + 3), r) for k, r in enumerate(radii)]
        r = rng.uniform(1.0, 2.5)
        start, d = inside_point(5), rng.normal(size=3)
        d[2] *= 0.3
        d /= np.linalg.norm(d)
        inclusions.append(Tube("v", np.array([start, start + 15 * d, start + 30 * d + rng.normal(size=3) * 3]), r))
        smallest = min(inc.radius_mm for inc in inclusions)
        m = rng.uniform(0.3, 0.7) * smallest
        skin = rng.uniform(1.0, 3.0) if rng.random() < 0.5 else None
        patch = np.array([rng.uniform(-0.5, 0.5) * a, 0.0, 0.0])
        patch[2] = 0.9 * h * np.sqrt(max(1 - patch[0] ** 2 / a**2, 0.0))
        sizing = BodySizing(m, m * rng.uniform(6, 12), rng.uniform(0.2, 0.5), ((patch, 5.0),))
        try:
            mesh = body_mesh.body_mesh(BodyShape("dome", a, h, skin_thickness_mm=skin), tuple(inclusions), sizing)
            minima.append(mesh.min_dihedral_deg)
        except body_mesh.MeshError as exc:
            failures.append(str(exc)[:200])
    minima = np.array(minima)
    summary = {"scenes": n, "meshed": len(minima), "failures": failures,
               "min_dihedral_deg": sorted(round(float(x), 2) for x in minima)}
    if len(minima):
        print(f"random domes: {len(minima)} of {n} meshed; smallest dihedral angle per mesh: min "
              f"{minima.min():.2f}°, 10th percentile {np.percentile(minima, 10):.2f}°, median {np.median(minima):.2f}°")
    return summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3, help="meshing runs per sizing (the median is reported)")
    ap.add_argument("--targets", type=int, nargs="*", default=[10_000, 30_000, 100_000])
    ap.add_argument("--fit", action="store_true", help="also mesh the estimate's fit set and fit its factors")
    ap.add_argument("--random", type=int, default=0, metavar="N", help="also mesh N random domes (dihedral angles)")
    args = ap.parse_args()
    import gmsh

    variant = "+".join(v for v, on in (("fit", args.fit), (f"random{args.random}", args.random)) if on) or None
    res = results_io.Results("bench_body_mesh", variant)
    print(f"machine: {res.record['machine']['cpu']}, {res.record['machine']['cores']} cores; load "
          f"{res.record['load1_before']:.2f}; gmsh {gmsh.__version__}", flush=True)
    rows = bench_example(args.targets, args.repeat)
    res.table("example", [{k: v for k, v in r.items() if k not in ("dihedral", "regions", "mesh_s_all")}
                          | {"min_dihedral_deg": r["dihedral"]["min_deg"],
                             "worst_region_error_percent": max(abs(v["error_percent"]) for v in r["regions"].values())}
                          for r in rows],
              units={"min_edge_mm": "mm", "max_edge_mm": "mm", "mesh_s_median": "s", "cached_s_median": "s",
                     "estimate_s": "s", "min_dihedral_deg": "deg", "worst_region_error_percent": "%"})
    res.data("example", {"rows": rows, "gmsh": gmsh.__version__})
    if args.fit:
        res.data("estimate_fit", fit_estimate())
    if args.random:
        res.data("random_domes", random_domes(args.random))
    res.write()
    print(f"written to {res.path}")

if __name__ == "__main__":
    main()
