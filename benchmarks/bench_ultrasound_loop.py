"""The ultrasound as the loop's sensor (docs/ultrasound.md §6): what a measurement costs, and how well it tracks.

On the example scene (the camera replaced by an L11-5v on the left side,
at (0, 30) mm looking along +x, 70 mm deep), one thread:

* the per-run tables: the PSF (SIMUS), the fast model's tables and the
  noise's reference power, and the fast model's validation against SIMUS;
* `UltrasoundSensor.measure` per call (median over --repeats): in the
  layer with the trial's window, in the layer with whole frames (the
  nominal record), in a slab (layer_check's default 40 mm slab, the
  example's mesh at --slab-scale) with its window and elevation band; the
  first call (scatterers drawn and located) apart; the first frame's
  localisation error at rest in the layer and in the slab;
* the closed loop of each target in the layer moving it 2 mm (ideal
  profile, whole frames):
  the first frame's localisation error, the tracking error of the
  displacement (tracked minus its first, against true minus its first)
  over the frames (p95, max), and the frame-to-frame jitter of the tracked
  position's error (its std: `imaging_sensor.TRACKING_JITTER_MM`).

    python benchmarks/bench_ultrasound_loop.py [--repeats 20] [--seeds 3]

The machine has 2 cores and other work may share them: wall-clock medians.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import numpy as np
import results_io
import yaml

from scissor_cli import runtime

runtime.configure()  # before scissor's modules load cvxopt: runtime.match_blas_kernels

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def stats(times) -> dict:
    """median, p10, p90 (ms) and count of times (s), as `median_ms` prints them."""
    t = np.asarray(times) * 1e3
    p10, p50, p90 = np.percentile(t, [10, 50, 90])
    return {"median_ms": p50, "p10_ms": p10, "p90_ms": p90, "n": len(t)}


def median_ms(times) -> str:
    t = np.asarray(times) * 1e3
    p10, p50, p90 = np.percentile(t, [10, 50, 90])
    return f"median {p50:7.2f} ms  (p10 {p10:.2f}, p90 {p90:.2f}, n={len(t)})"


def timed_measures(sensor, states, repeats):
    t0 = time.perf_counter()
    sensor.measure(states[0])
    first = time.perf_counter() - t0
    times = []
    for k in range(repeats):
        t0 = time.perf_counter()
        sensor.measure(states[k % len(states)])
        times.append(time.perf_counter() - t0)
    return first, times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--seeds", type=int, default=3, help="speckle draws of the nominal loops")
    ap.add_argument("--slab-scale", type=float, default=2.0, help="the slab's in-plane mesh scale")
    args = ap.parse_args()
    res = results_io.Results("bench_ultrasound_loop", ".".join(p for p in (
        None if args.repeats == 20 else f"repeats{args.repeats}", None if args.seeds == 3 else f"seeds{args.seeds}",
        None if args.slab_scale == 2.0 else f"slab{args.slab_scale:g}") if p) or None)
    rows = []
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")

    from scissor_cli import control
    from scissor_cli.config import TrialsConfig, parse_config
    from scissor_cli.experiments.build import build_model
    from scissor_cli.experiments.imaging_stage import fast_validation
    from scissor_cli.experiments.profiles import error_model
    from scissor_cli.experiments.sensor_models import imaging_data, imaging_tables_for, sensor_model
    from scissor_cli.layer3d.slab import SlabSpec, build_slab
    from scissor_cli.sensing.sensor import TrueState

    data = yaml.safe_load(open(os.path.join(ROOT, "configs", "example.yaml")))
    data["imaging"] = {"probe": "L11-5v", "position_mm": [0.0, 30.0], "axis": [1.0, 0.0], "depth_mm": 70.0}
    cfg = parse_config(yaml.safe_dump(data))
    scene, mesh, tissue = build_model(cfg)

    t0 = time.perf_counter()
    payload = imaging_data(cfg.imaging)
    print(f"probe and PSF (pymust's import included): {time.perf_counter() - t0:.2f} s")
    res.figure("psf_s", time.perf_counter() - t0, "s")
    t0 = time.perf_counter()
    tables = imaging_tables_for(cfg.imaging, payload)
    print(f"fast model's tables and reference power: {time.perf_counter() - t0:.2f} s")
    res.figure("tables_s", time.perf_counter() - t0, "s")
    v = fast_validation(cfg.imaging, tables)
    res.figure("validation_s", v["time_s"], "s")
    res.figure("validation_envelope_correlation", v["envelope_correlation"], "correlation")
    res.figure("validation_tracking_difference_um", 1e3 * v["tracking_difference_mm"], "µm")
    print(f"validation against SIMUS: {v['time_s']:.1f} s, envelope correlation {v['envelope_correlation']:.3f}, "
          f"tracked displacements {1e3 * v['tracking_difference_mm']:.1f} um apart ({v['scatterer_count']} scatterers)")

    ideal = error_model(TrialsConfig(profile="ideal"))
    model = sensor_model(cfg, scene, ideal, payload)
    whole = replace(model, full_frames=True)
    target = scene.targets[0]
    goal = np.asarray(target.rest) + np.array([0.0, -3.0])
    layer_states = [TrueState(np.asarray(target.rest) + d, mesh.nodes + d, mesh)
                    for d in (np.array([0.02 * k, -0.03 * k]) for k in range(args.repeats))]

    s = model.nominal(cfg.seed, 0, goal)
    first, times = timed_measures(s, layer_states, args.repeats)
    print(f"measure, layer, window {s.grid.shape} ({len(s._scene._carried[-1][1])} scatterers): {median_ms(times)}; "
          f"first call {first:.2f} s")
    rows.append(dict(measurement="measure, layer, window", scatterers=len(s._scene._carried[-1][1]), first_s=first,
                     **stats(times)))
    s = whole.nominal(cfg.seed, 0, goal)
    first, times = timed_measures(s, layer_states, args.repeats)
    print(f"measure, layer, whole frames {s.grid.shape} ({len(s._scene._carried[-1][1])} scatterers): "
          f"{median_ms(times)}; first call {first:.2f} s")
    rows.append(dict(measurement="measure, layer, whole frames", scatterers=len(s._scene._carried[-1][1]),
                     first_s=first, **stats(times)))
    frame_times = []
    for st in layer_states[:args.repeats]:
        t0 = time.perf_counter()
        s.frame(st)
        frame_times.append(time.perf_counter() - t0)
    print(f"one whole frame (carried and formed, no tracking): {median_ms(frame_times)}")
    rows.append(dict(measurement="one whole frame, no tracking", **stats(frame_times)))

    spec = SlabSpec(40.0, 20.0, max_layer_mm=5.0)  # layer_check's defaults
    coarse_scene, coarse_mesh, coarse = build_model(cfg, mesh_scale=args.slab_scale)
    slab = build_slab(coarse_scene, coarse_mesh, spec)
    slab_states = [TrueState(np.asarray(target.rest) + d[:2], slab.rest + d, slab.mesh)
                   for d in (np.array([0.02 * k, -0.03 * k, 0.005 * k]) for k in range(args.repeats))]
    s = model.nominal(cfg.seed, 0, goal)
    first, times = timed_measures(s, slab_states, args.repeats)
    print(f"measure, slab ({slab.mesh.n_nodes} nodes), window {s.grid.shape} ({len(s._scene._carried[-1][1])} "
          f"scatterers in an elevation band): {median_ms(times)}; first call {first:.2f} s")
    rows.append(dict(measurement="measure, slab, window and elevation band", scatterers=len(s._scene._carried[-1][1]),
                     slab_nodes=slab.mesh.n_nodes, first_s=first, **stats(times)))
    res.table("measure", rows, {"first_s": "s", "median_ms": "ms", "p10_ms": "ms", "p90_ms": "ms"})
    located = {"layer": [], "slab": []}
    for seed in range(2 * args.seeds + 2):
        for where, state in (("layer", layer_states[0]), ("slab", slab_states[0])):
            y = model.nominal(seed, 0, goal).measure(state)
            located[where].append(float(np.hypot(*(y - np.asarray(target.rest)))))
    for where, errors in located.items():
        e = np.array(errors)
        print(f"first-frame localisation at rest, {where}, {len(e)} draws: rms "
              f"{1e3 * np.sqrt(np.mean(e ** 2)):.0f} um, "
              f"max {1e3 * e.max():.0f} um")
        res.figure(f"localisation_rest_{where}_rms_um", 1e3 * np.sqrt(np.mean(e ** 2)), "µm", draws=len(e))
        res.figure(f"localisation_rest_{where}_max_um", 1e3 * e.max(), "µm", draws=len(e))

    # the loops: each target moved 2 mm along y (lateral in the image), the miss taken across a needle along x
    jitter, tracking, localisation = [], [], []
    for k, t in enumerate(scene.targets):
        desired = np.asarray(t.rest) + np.array([0.0, -2.0])
        for seed in range(args.seeds):
            s = whole.nominal(seed, k, desired, record=True)
            run = control.TargetRun(target=t.name, sensor=s, direction=np.array([1.0, 0.0]))
            control.run_target(tissue, t.rest, desired, cfg.controller, run)
            tracked, true = np.array(s.recorded.tracked), np.array(s.recorded.true)
            err = tracked - true
            disp = np.linalg.norm((tracked - tracked[0]) - (true - true[0]), axis=1)
            localisation.append(float(np.linalg.norm(err[0])))
            tracking.append((float(np.percentile(disp, 95)), float(disp.max()), len(tracked),
                             float(np.linalg.norm(true[-1] - true[0])), s.lost_frames))
            jitter.append(np.diff(err, axis=0))
    inc = np.concatenate(jitter)
    print(f"nominal loops, {args.seeds} speckle draws per target: localisation error "
          f"{', '.join(f'{1e3 * e:.0f}' for e in localisation)} um")
    for p95, worst, n, travel, lost in tracking:
        print(f"  tracking error of the displacement over {n} frames (travel {travel:.2f} mm): p95 {1e3 * p95:.0f} um, "
              f"max {1e3 * worst:.0f} um, {lost} lost")
    print(f"  frame-to-frame change of the tracked position's error: std {1e3 * float(np.std(inc)):.1f} um per axis, "
          f"rms step {1e3 * float(np.sqrt(np.mean(np.sum(inc ** 2, axis=1)))):.1f} um")
    res.figure("loop_localisation_um", [1e3 * e for e in localisation], "µm (per loop)")
    res.table("loop_tracking", [{"frames": n, "travel_mm": travel, "p95_um": 1e3 * p95, "max_um": 1e3 * worst,
                                 "lost": lost} for p95, worst, n, travel, lost in tracking],
              {"travel_mm": "mm", "p95_um": "µm", "max_um": "µm"})
    res.figure("jitter_std_um", 1e3 * float(np.std(inc)), "µm per axis")
    res.figure("jitter_rms_step_um", 1e3 * float(np.sqrt(np.mean(np.sum(inc ** 2, axis=1)))), "µm")
    res.write()


if __name__ == "__main__":
    main()
