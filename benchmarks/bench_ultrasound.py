"""Speed and accuracy of the ultrasound sensor's core (docs/ultrasound.md): fast frames, tracking, SIMUS, PSF.

At the default probe (L11-5v) and depth (70 mm), one thread (BLAS limited
by runtime.configure, numba loops serial):

* the PSF's build (pymust's import apart) and the fast model's tables;
* one fast frame of the whole 38 x 70 mm image at the default scatterer
  density, in-plane and with an elevation band (median over --repeats);
* tracking one frame (SpeckleTracker.update) and the first-frame
  localisation (medians);
* SIMUS on the validation patch (a few repeats), and its time per scatterer;
* accuracy: fast vs SIMUS (envelope correlation, tracked displacement),
  the envelope's mean/std against the scatterer density (Rayleigh: 1.913),
  the time-of-flight law, rigid and smooth-motion tracking errors and the
  localisation error.

    python benchmarks/bench_ultrasound.py [--repeats 30] [--skip-accuracy]

The machine has 2 cores and other work may share them: the numbers are
wall-clock medians, not CPU time.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np
import results_io

from scissor_cli import runtime

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels

DEPTH_MM = 70.0
LESION = np.array([0.0, 30.0])


def stats(times) -> dict:
    """median, p10, p90 (ms) and count of times (s), as `median_ms` prints them."""
    t = np.asarray(times) * 1e3
    p10, p50, p90 = np.percentile(t, [10, 50, 90])
    return {"median_ms": p50, "p10_ms": p10, "p90_ms": p90, "n": len(t)}


def median_ms(times) -> str:
    t = np.asarray(times) * 1e3
    p10, p50, p90 = np.percentile(t, [10, 50, 90])
    return f"median {p50:7.2f} ms  (p10 {p10:.2f}, p90 {p90:.2f}, n={len(t)})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=30, help="fast frames and tracking steps timed")
    ap.add_argument("--simus-repeats", type=int, default=2)
    ap.add_argument("--skip-accuracy", action="store_true")
    args = ap.parse_args()
    res = results_io.Results("bench_ultrasound", ".".join(p for p in (
        None if args.repeats == 30 else f"repeats{args.repeats}",
        None if args.simus_repeats == 2 else f"simus{args.simus_repeats}",
        "skip-accuracy" if args.skip_accuracy else None) if p) or None)
    timings = []
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")

    t0 = time.perf_counter()
    import pymust  # noqa: F401  (its import, matplotlib included, is a one-off per process)
    print(f"import pymust                 : {time.perf_counter() - t0:.2f} s")
    from scissor_cli.sensing import ultrasound as us
    from scissor_cli.sensing.ultrasound.simus_ref import simus_frame

    probe = us.probe_params("L11-5v")
    grid = us.image_grid(probe, DEPTH_MM, 1540.0)
    t0 = time.perf_counter()
    psf = us.build_psf(probe, 1540.0, DEPTH_MM)
    t_psf = time.perf_counter() - t0
    t0 = time.perf_counter()
    kernels = us.frame_kernels(psf, grid)
    t_k = time.perf_counter() - t0
    lat, ax = psf.resolution_cell_mm()
    print(f"PSF build (SIMUS + fits)      : {t_psf:.2f} s;  frame tables: {t_k:.2f} s;  grid {grid.shape}, "
          f"pixels {grid.dx_mm:.3f} x {grid.dz_mm:.4f} mm; cell {lat:.3f} x {ax:.3f} mm, f-number {psf.fnumber:.2f}")
    res.figure("psf_build_s", t_psf, "s")
    res.figure("frame_tables_s", t_k, "s")
    res.data("grid", {"shape": list(grid.shape), "dx_mm": grid.dx_mm, "dz_mm": grid.dz_mm, "cell_mm": [lat, ax],
                      "fnumber": psf.fnumber, "probe": "L11-5v", "depth_mm": DEPTH_MM})

    region = np.array([[grid.lateral_mm[0] - 1.5, -1.0], [grid.lateral_mm[-1] + 1.5, DEPTH_MM + 1.0]])

    def draw(seed, band=0.0, per_cell=20.0, lesion=LESION):
        scale = max(1.0, 2 * band / float(psf.elevation_fwhm_mm(30.0)))
        return us.draw_scatterers(np.random.default_rng(seed), region, psf.density_per_mm2(per_cell) * scale, band,
                                  lesion, 2.0, -10.0)

    def frame(sc, pos=None, rng=None, c_t=1540.0, snr=30.0):
        p = sc.positions_mm if pos is None else pos
        return us.fast_frame(kernels, p[:, 0], p[:, 1], sc.elevation_mm, sc.amplitude, c_t,
                             snr_db=snr if rng is not None else None, rng=rng)

    for label, sc in (("in-plane", draw(0)), ("elevation band +-1 mm", draw(1, band=1.0))):
        rng = np.random.default_rng(0)
        frame(sc, rng=rng)  # compile / warm
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            frame(sc, rng=rng)
            times.append(time.perf_counter() - t0)
        print(f"fast frame, {label:21s} : {median_ms(times)}   S = {len(sc)} scatterers, SNR 30 dB")
        timings.append(dict(measurement=f"fast frame, {label}", scatterers=len(sc), **stats(times)))

    sc = draw(2)
    rng = np.random.default_rng(1)
    first = frame(sc, rng=rng)
    moves = [sc.positions_mm + np.array([0.05 * k, 0.04 * k]) for k in range(1, args.repeats + 1)]
    frames = [frame(sc, m, rng) for m in moves]
    tracker = us.SpeckleTracker(first, grid, LESION)
    tracker.update(frames[0])
    tracker = us.SpeckleTracker(first, grid, LESION)
    times = []
    for f in frames:
        t0 = time.perf_counter()
        tracker.update(f)
        times.append(time.perf_counter() - t0)
    print(f"tracking one frame            : {median_ms(times)}")
    timings.append(dict(measurement="tracking one frame", **stats(times)))
    times = []
    for _ in range(max(5, args.repeats // 3)):
        t0 = time.perf_counter()
        us.localise_lesion(first, grid, LESION + 0.7, 2.0)
        times.append(time.perf_counter() - t0)
    print(f"first-frame localisation      : {median_ms(times)}")
    timings.append(dict(measurement="first-frame localisation", **stats(times)))

    # SIMUS on the validation patch's scatterers (the cost grows with their number)
    rng = np.random.default_rng(7)
    n = 1500
    pos = LESION + (2 * rng.random((n, 2)) - 1) * np.array([3.5, 2.4])
    amp = rng.standard_normal(n)
    sub = us.ImageGrid(grid.lateral_mm[np.abs(grid.lateral_mm) <= 2.5],
                       grid.depth_mm[np.abs(grid.depth_mm - 30) <= 1.9])
    times = []
    for _ in range(args.simus_repeats):
        t0 = time.perf_counter()
        simus_frame(probe, sub, pos[:, 0], pos[:, 1], np.zeros(n), amp, 1540.0, 1540.0)
        times.append(time.perf_counter() - t0)
    per = np.median(times) / n
    print(f"SIMUS frame, {n} scatterers  : {median_ms(times)}  ({per * 1e3:.2f} ms per scatterer: "
          f"a whole {len(sc)}-scatterer frame would take about {per * len(sc) / 60:.0f} min)")
    timings.append(dict(measurement=f"SIMUS, {n} scatterers", scatterers=n, **stats(times)))
    res.figure("simus_per_scatterer_ms", per * 1e3, "ms")
    res.figure("simus_whole_frame_min", per * len(sc) / 60, "min", scatterers=len(sc))
    res.table("timings", timings, {"median_ms": "ms", "p10_ms": "ms", "p90_ms": "ms"})
    if not args.skip_accuracy:
        accuracy(us, probe, psf, kernels, grid, draw, frame, res)
        print(f"load average now {os.getloadavg()[0]:.2f}")
    res.write()


def accuracy(us, probe, psf, kernels, grid, draw, frame, res) -> None:
    """The model's and the tracker's agreement numbers (module docstring)."""
    from scissor_cli.sensing.ultrasound.simus_ref import simus_frame

    rows = []
    for shift, strain, band in (((0.23, 0.17), None, 0.0), ((0.3, -0.25), np.array([[0.02, 0.01], [0.0, -0.03]]), 0.0),
                                ((-0.15, 0.12), None, 0.5)):
        t0 = time.perf_counter()
        v = us.validate_fast(probe, psf, kernels, np.random.default_rng(7), np.array([1.0, 30.0]), np.array(shift),
                             strain, elevation_half_mm=band)
        print(f"fast vs SIMUS, shift {shift}, strain {'yes' if strain is not None else 'no'}, band +-{band} mm: "
              f"envelope correlation {v.envelope_correlation:.3f}, tracked fast {np.round(v.tracked_fast_mm, 4)} "
              f"SIMUS {np.round(v.tracked_simus_mm, 4)} -> difference {v.tracking_difference_mm * 1e3:.1f} um "
              f"({v.scatterer_count} scatterers, {time.perf_counter() - t0:.1f} s)")
        rows.append({"shift_mm": list(shift), "strain": strain is not None, "band_mm": band,
                     "envelope_correlation": v.envelope_correlation,
                     "tracking_difference_um": v.tracking_difference_mm * 1e3, "scatterers": v.scatterer_count})
    res.table("fast_vs_simus", rows, {"shift_mm": "mm", "band_mm": "mm", "tracking_difference_um": "µm"})

    rows = (grid.depth_mm > 15) & (grid.depth_mm < 55)
    cols = np.abs(grid.lateral_mm) < 12
    for per_cell in (5, 10, 20, 40):
        r = []
        for seed in range(3):
            e = frame(draw(10 + seed, per_cell=per_cell, lesion=None))[rows][:, cols].astype(float)
            e /= np.sqrt(np.mean(e ** 2, axis=1, keepdims=True))
            r.append(e.mean() / e.std())
        print(f"envelope mean/std, {per_cell:2d} scatterers per cell: {np.mean(r):.3f} "
              f"(Rayleigh {math.sqrt(math.pi / (4 - math.pi)):.3f})")
        res.figure(f"envelope_mean_over_std_{per_cell}", np.mean(r), "ratio", scatterers_per_cell=per_cell,
                   rayleigh=math.sqrt(math.pi / (4 - math.pi)))

    for c_t in (1450.0, 1540.0):
        env = us.fast_frame(kernels, np.zeros(1), np.array([50.0]), np.zeros(1), np.ones(1), c_t)
        sub = us.ImageGrid(np.arange(-10, 11) * 0.15, 50 * 1540 / c_t - 1.0 + np.arange(21) * 0.1)
        ref = simus_frame(probe, sub, np.zeros(1), np.array([50.0]), np.zeros(1), np.ones(1), c_t, 1540.0)
        print(f"time of flight, tissue {c_t:.0f} m/s, point at 50 mm: expected {50 * 1540 / c_t:.3f} mm, "
              f"fast {_peak(env, grid.depth_mm):.3f} mm, SIMUS {_peak(ref, sub.depth_mm):.3f} mm")
        res.figure(f"time_of_flight_{c_t:.0f}", _peak(env, grid.depth_mm), "mm", expected=50 * 1540 / c_t,
                   simus=_peak(ref, sub.depth_mm))

    sc = draw(20)
    rng = np.random.default_rng(3)
    ref = frame(sc, rng=rng)
    errs = []
    for shift in ((0.037, 0.051), (-0.11, 0.023), (0.21, -0.077), (0.0, 0.33), (-0.42, -0.19)):
        d, _ = us.block_match(ref, frame(sc, sc.positions_mm + shift, rng), grid, LESION)
        errs.append(np.hypot(*(d - shift)))
    print(f"rigid sub-pixel shifts: tracking error max {max(errs) * 1e3:.1f} um over 5 directions")
    res.figure("rigid_tracking_error_max_um", max(errs) * 1e3, "µm")
    c = LESION

    def affine(p, t):
        return p + t * ((p - c) @ np.array([[0.03, 0.02], [-0.01, -0.05]]).T + np.array([3.0, 4.0]))

    def bump(p, t):
        w = np.exp(-np.sum((p - c - np.array([-4.0, 3.0])) ** 2, axis=1) / (2 * 15.0 ** 2))
        return p + t * w[:, None] * np.array([6.0, 4.0])

    for name, field in (("affine", affine), ("Gaussian bump", bump)):
        p95 = []
        for seed in range(3):
            sc = draw(30 + seed)
            rng = np.random.default_rng(seed)
            tracker = us.SpeckleTracker(frame(sc, rng=rng), grid, c)
            e = [np.hypot(*(tracker.update(frame(sc, field(sc.positions_mm, k / 20), rng)).position_mm
                          - field(c[None], k / 20)[0])) for k in range(1, 21)]
            p95.append(np.percentile(e, 95))
        print(f"20-frame {name} sequence (lesion moves {np.hypot(*(field(c[None], 1.0)[0] - c)):.1f} mm): "
              f"accumulated error p95 {np.round(np.array(p95) * 1e3, 1)} um (3 seeds)")
        res.figure(f"sequence_{name.split()[-1].lower()}_p95_um", np.array(p95) * 1e3, "µm (per seed)")

    errs = []
    for seed in range(12):
        rr = np.random.default_rng(100 + seed)
        true = np.array([rr.uniform(-5, 5), rr.uniform(20, 50)])
        env = frame(draw(40 + seed, lesion=true), rng=rr)
        errs.append(np.hypot(*(us.localise_lesion(env, grid, true + rr.uniform(-1.5, 1.5, 2), 2.0) - true)))
    print(f"localisation, -10 dB lesion of 2 mm, 12 draws: rms {np.sqrt(np.mean(np.square(errs))) * 1e3:.0f} um, "
          f"max {max(errs) * 1e3:.0f} um")
    res.figure("localisation_rms_um", np.sqrt(np.mean(np.square(errs))) * 1e3, "µm")
    res.figure("localisation_max_um", max(errs) * 1e3, "µm")


def _peak(env: np.ndarray, depth_mm: np.ndarray) -> float:
    col = env.max(axis=1).astype(float)
    i = int(np.argmax(col))
    return float(depth_mm[i] + (depth_mm[1] - depth_mm[0]) * 0.5 * (col[i - 1] - col[i + 1])
                 / (col[i - 1] - 2 * col[i] + col[i + 1]))


if __name__ == "__main__":
    main()
