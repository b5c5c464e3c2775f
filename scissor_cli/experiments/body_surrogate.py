"""The controller's surrogate of a body (`controller.model: surrogate`, docs/model.md §19 "Control", §15).

§15's surrogate learned from the model's body instead of the slab: the
body (at `controller.mesh_scale`, undrawn) solved along a chain of stroke
vectors — the space-filling design of `layer3d.surrogate` within the cups'
stroke limits, `controller.surrogate.samples` of them and a quarter as
many held out — and every lesion's 3-D position at each learned by a
thin-plate-spline interpolant; J (3 × cups) its derivative. Its error is
the largest 3-D distance from the body at the held-out strokes. The
samples are cached beside the run (`<run's parent>/.scissor-cache/`, keyed
by everything they depend on), so a resume or a second run reuses them;
the trials get them in their tasks as plain data (`ModelData`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from scissor_cli import progress
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.experiments import run_cache
from scissor_cli.experiments.controller_model_stage import load_model_data, save_model_data
from scissor_cli.layer3d.surrogate import Surrogate, train
from scissor_cli.layer3d.tissue_models import ModelData
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import TargetProbe, target_positions

#: the design's solves: well below any accuracy a run asks for (as the mesh choice's, `body_resolution`)
SOLVE_TOL = 1e-8


class _Lesions:
    """The lesions as `surrogate.train` reads them: `nodes` (T rows) and positions(x (N, 3)) → (T, 3) mm."""

    def __init__(self, probe: TargetProbe):
        self.probe, self.nodes = probe, probe.nodes

    def positions(self, x: np.ndarray) -> np.ndarray:
        return target_positions(self.probe, x)


def _key(cfg: BodyConfig) -> str:
    return run_cache.key({
        "kind": "body-surrogate", "tol": SOLVE_TOL, "mesh_scale": cfg.controller.mesh_scale,
        "surrogate": cfg.controller.surrogate.model_dump(mode="json"),
        "scene": cfg.model_dump(mode="json", include={"tissue", "material", "cups", "targets", "obstacles"}),
    })


def body_surrogate_data(cfg: BodyConfig, tissue: Tissue, cache: Optional[Path]) -> ModelData:
    """The surrogate's samples on the model's body `tissue`, from the cache when it holds them."""
    path = None if cache is None else cache / f"controller-surrogate-{_key(cfg)}.npz"
    if path is not None and path.exists():
        data = load_model_data(path)
        if data is not None and data.kind == "surrogate":
            progress.info(f"controller model (surrogate): from the cache, held-out error "
                          f"{data.validation_error_mm:.3g} mm")
            return data
    scene = tissue.scene
    lo = np.array([c.stroke_min_mm for c in scene.cups])
    hi = np.array([c.stroke_max_mm for c in scene.cups])
    n = cfg.controller.surrogate.samples
    probe = tissue.probe(np.array([t.rest for t in scene.targets]).reshape(-1, 3))
    advance = progress.bar("controller model (surrogate): body solves", n + max(4, n // 4))
    samples = train(tissue, _Lesions(probe), None, lo, hi, n, SOLVE_TOL, advance)
    error = Surrogate(samples, components=3).validation_error_mm()
    data = ModelData("surrogate", samples.build_time_s, error, samples=samples)
    progress.info(f"controller model (surrogate): {n} body solves and {len(samples.held_strokes)} held out in "
                  f"{samples.build_time_s:.1f} s; held-out error {error:.3g} mm")
    if path is not None:
        save_model_data(path, data)
    return data
