"""Where to grip the body (docs/model.md §20): one, two and three cups chosen over the skin, timed; not a test.

On configs/example_dome.yaml with a second camera beside the dome (so the loop sees all three coordinates),
the ideal profile, and `manipulation_points` over the skin of the cup's side of the dome (ball of 30 mm about
(0, 50, 15) mm, 4 mm spacing), for N = 1, 2, 3 cups (the paper's single cup; two, the fewest that control the
miss across the needle; three, the follow-on's fingers that control the 3-D position): the grip search's time
(median of --repeats searches on the body, goal ≤ 2 s), then `scissor simulate` (the chosen grips verified, every
lesion planned and moved by the closed loop): per lesion the true miss across the needle after the nominal loop,
its iterations and the strokes it used.

    PYTHONPATH=. python3 benchmarks/bench_body_grips.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import results_io
import yaml

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "example_dome.yaml"
REGION = {"center_mm": [0.0, 50.0, 15.0], "radius_mm": 30.0}
SIDE_CAMERA = {"position_mm": [400.0, 0.0, 15.0], "look_at_mm": [0.0, 0.0, 15.0]}


def scene(n_cups: int) -> dict:
    """example_dome with n_cups cups (copies of its one, to be placed), two cameras, one ideal trial."""
    data = yaml.safe_load(CONFIG.read_text())
    cup = data["cups"][0]
    data["cups"] = [dict(cup, name=f"cup{k + 1}") for k in range(n_cups)]
    for k, c in enumerate(data["cups"]):  # anywhere on the skin, apart: the grips replace them
        angle = 2.0 * np.pi * k / n_cups
        c["contact_mm"] = [float(57.0 * np.cos(angle)), float(57.0 * np.sin(angle)), 10.0]
        c.pop("axis", None)
    data["forward"] = []
    data["cameras"] = [{"position_mm": data.pop("camera")["position_mm"]}, SIDE_CAMERA]
    data["manipulation_points"] = {"skin": REGION, "spacing_mm": 4.0, "cups": n_cups}
    data["trials"] = {"count": 1, "profile": "ideal"}
    return data


def search_seconds(data: dict, repeats: int) -> tuple[float, int]:
    """Median seconds of the grip search on the scene's body, and its candidates."""
    from scissor_cli.config.loading import parse_config
    from scissor_cli.experiments.build import body_model
    from scissor_cli.planning.body_grips import plan_body_grips

    cfg = parse_config(yaml.safe_dump(data), "<bench>")
    _, _, tissue = body_model(cfg)
    mp = cfg.manipulation_points
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        plan = plan_body_grips(tissue, mp.skin.center_mm, mp.skin.radius_mm, mp.spacing_mm, mp.cups,
                               cfg.needle.direction, cfg.cups[0].radius_mm, 15.0)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), len(plan.candidates)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    res = results_io.Results("bench_body_grips")
    rows = []
    for n_cups in (1, 2, 3):
        data = scene(n_cups)
        search_s, candidates = search_seconds(data, args.repeats)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "scene.yaml"
            path.write_text(yaml.safe_dump(data, sort_keys=False))
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, "-m", "scissor_cli", "simulate", str(path), "--out",
                                str(Path(tmp) / "run"), "--quiet"], capture_output=True, text=True,
                               env=results_io.subprocess_env())
            wall = time.perf_counter() - t0
            if r.returncode != 0:
                raise SystemExit(f"simulate failed ({r.returncode}):\n{r.stderr[-2000:]}")
            with h5py.File(Path(tmp) / "run" / "results.h5", "r") as f:
                mp = f["manipulation_points"].attrs
                for t in f["trials"]:
                    n = f[f"plan/{t}"].attrs["direction"]
                    error = f[f"trials/{t}/final_error"][0]
                    miss = float(np.linalg.norm(error - (error @ n) * n))
                    history = f[f"trials/{t}/history/0"]
                    columns = list(history.attrs["columns"])
                    strokes = history[()][-1, [columns.index(c) for c in columns if c.startswith("stroke_cmd_")]]
                    rows.append({"cups": n_cups, "target": t, "candidates": candidates, "search_s": search_s,
                                 "verify_s": float(mp["verify_s"]), "score": float(mp["score"]),
                                 "controls": str(mp["controls"]), "miss_mm": miss,
                                 "iterations": int(f[f"trials/{t}/iterations"][0]),
                                 "stop": f[f"trials/{t}/stop_reason"][0].decode(),
                                 "max_stroke_mm": float(np.max(np.abs(strokes))), "run_s": wall})
                    print(f"{n_cups} cup(s) {t}: search {search_s:.2f} s ({candidates} candidates), miss {miss:.3f} mm "
                          f"in {rows[-1]['iterations']} iterations ({rows[-1]['stop']}), strokes up to "
                          f"{rows[-1]['max_stroke_mm']:.2f} mm; run {wall:.0f} s", flush=True)
    res.table("grips", rows, {"search_s": "s", "verify_s": "s", "miss_mm": "mm", "max_stroke_mm": "mm", "run_s": "s"})
    res.data("config", str(CONFIG.relative_to(ROOT)))
    res.write()


if __name__ == "__main__":
    main()
