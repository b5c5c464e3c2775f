"""The needle under a 3-D-aware controller (docs/model.md §18): the tabulated model of the target under the needle,
the needle aimed at its height, and `loop` steering with it against the slab.

The small slab of tests/test_insertion3d.py (the example's coarse layer, five levels over 8 mm) with the cup
pushed so that the target leaves the layer's plane: the tabulated insertion is the nominal slab's own, so with
an exact sensor `loop` lands on the line; a sensor with a known offset shows what it steers on.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from scissor_cli.config import parse_config
from scissor_cli.experiments.build import build_model
from scissor_cli.insertion import (
    InsertionOptions,
    NeedleModel,
    NeedleParams,
    needle_path,
    run_insertion,
    run_strategies,
)
from scissor_cli.insertion.model_table import tabulate
from scissor_cli.insertion.steering import TableSteering
from scissor_cli.layer3d.slab import SlabSpec, build_slab, slab_probe
from scissor_cli.sensing.sensor import TrueState
from scissor_cli.solvers.newton import solve_newton

from helpers import example_dict

INSERTION = {"step_mm": 2.0, "friction_static_mN_per_mm": 15.0, "friction_kinetic_mN_per_mm": 10.0,
             "tip_force_mN": 100.0, "tip_zone_mm": 2.0, "capture_radius_mm": 2.5,
             "strategies": ["none", "depth", "loop"]}
LAYER_Z = 4.0
TARGET = np.array([48.0, 45.0])  # below the cup
ENTRY, AXIS, DEPTH = np.array([0.0, 45.0]), np.array([1.0, 0.0]), 48.0
STROKES = np.array([6.0])


@pytest.fixture(scope="module")
def pushed():
    """(cfg, slab, its equilibrium pushed 6 mm, needle params, the tabulated model at the target's height)."""
    data = example_dict()
    data["tissue"]["mesh"]["scale"] = 2.0
    data["insertion"] = dict(INSERTION)
    cfg = parse_config(yaml.safe_dump(data), "scene.yaml")
    scene, mesh, tissue = build_model(cfg)
    slab = build_slab(scene, mesh, SlabSpec(8.0, LAYER_Z, levels_mm=(0.0, 3.0, 4.0, 5.0, 8.0)))
    x0 = solve_newton(slab, STROKES, tol=1e-10).x
    params = NeedleParams.from_config(cfg.insertion, cfg.needle, cfg.tissue.mesh)
    height = float(slab_probe(slab, TARGET[None]).positions(x0)[0, 2])
    model = tabulate(slab, x0, STROKES, needle_path(slab, ENTRY, AXIS, DEPTH, TARGET, "T", height), params,
                     cfg.controller)
    return cfg, slab, x0, params, model


def _insert(pushed, strategy, model=None, sensor=None, height=None):
    cfg, slab, x0, params, table = pushed
    kw = {} if sensor is None else {"sensor": sensor}
    return run_insertion(slab, x0, STROKES, needle_path(slab, ENTRY, AXIS, DEPTH, TARGET, "T", height), params,
                         InsertionOptions(strategy, cfg.controller, needle_model=model, keep_displacement=False, **kw))


def test_the_table_follows_the_nominal_insertion(pushed):
    """One row per step, depths increasing to where the tip met the target; the held Jacobian finite, the
    target's in-plane response to the cup falling as the needle holds the tissue around it; the target left the
    layer's plane under the push, and the loop's cup moves change the height it ends at."""
    cfg, slab, x0, params, model = pushed
    K = len(model.depth_mm)
    assert model.target_mm.shape == (K, 3) and model.jacobian.shape == (K, 3, 1) and K >= 10
    assert np.all(np.diff(model.depth_mm) > 0) and np.all(np.isfinite(model.jacobian))
    assert abs(model.entry_height_mm - LAYER_Z) > 0.01  # the push moved the target out of the plane
    across = np.abs(model.jacobian[:, 1, 0])  # AXIS is x: across is y
    assert across[-1] < 0.8 * across[0]
    assert np.isfinite(model.steered_height_mm) and model.height_for("loop") == model.steered_height_mm
    assert model.height_for("none") == model.height_for("depth") == model.end_height_mm
    np.testing.assert_allclose(model.target_at(model.depth_mm[3]), model.target_mm[3])
    with pytest.raises(ValueError, match="increasing"):
        NeedleModel(model.depth_mm[::-1], model.target_mm, model.jacobian, 4.0, 4.0)


def test_loop_with_the_table_lands_on_the_line_where_the_slab_can_reach(pushed):
    """Truth = the nominal slab, exact sensor: `loop` steered by the table and aimed at its height misses by
    at most the controller's tolerance, far less than the same needle in the layer's plane or `none`."""
    cfg, slab, x0, params, model = pushed
    loop = _insert(pushed, "loop", model, height=model.height_for("loop"))
    none = _insert(pushed, "none", height=model.height_for("none"))
    in_plane = _insert(pushed, "loop", model)  # the needle at the layer's height: the out-of-plane miss stays
    assert loop.completed and none.completed
    assert loop.miss_mm <= cfg.controller.tolerance_mm
    assert loop.miss_mm < none.miss_mm and loop.miss_mm < in_plane.miss_mm
    assert np.any(np.abs(loop.strokes - STROKES) > 1e-3)  # the cup did move


class _Offset:
    """A sensor that reads the true target shifted by a fixed offset (mm), and counts its readings."""

    def __init__(self, offset):
        self.offset, self.calls, self.noise_mm = np.asarray(offset, float), 0, 0.0

    def measure(self, state: TrueState) -> np.ndarray:
        self.calls += 1
        return np.asarray(state.target_mm, float)[:2] + self.offset

    def reseeded(self, rng):
        return self


def test_loop_steers_on_what_its_sensor_sees_not_on_the_truth(pushed, monkeypatch):
    """A sensor 0.3 mm off across the axis: the loop puts what it sees on the line, so the true target ends
    0.3 mm off it; every J and offset it steers with came from the table and the sensor's readings."""
    cfg, slab, x0, params, model = pushed
    seen_args = []
    original = TableSteering.jacobian

    def spy(self, depth_mm, strokes, measured):
        seen_args.append(np.asarray(measured, float).copy())
        return original(self, depth_mm, strokes, measured)

    monkeypatch.setattr(TableSteering, "jacobian", spy)
    sensor = _Offset([0.0, 0.3])
    r = _insert(pushed, "loop", model, sensor, model.height_for("loop"))
    assert r.completed and sensor.calls >= len(seen_args) > 5
    across = (r.target[-1] - np.append(ENTRY, 0.0))[1]
    assert across == pytest.approx(-0.3, abs=cfg.controller.tolerance_mm)


def test_none_and_depth_share_their_steps(pushed):
    """Inserted together, `none` and `depth` give what each gives alone, to the step's tolerance."""
    cfg, slab, x0, params, model = pushed
    height = model.height_for("none")
    path = needle_path(slab, ENTRY, AXIS, DEPTH, TARGET, "T", height)
    options = {s: InsertionOptions(s, cfg.controller, keep_displacement=False) for s in ("none", "depth")}
    together = run_strategies(slab, x0, STROKES, {"none": path, "depth": path}, params, options)
    for r in together:
        alone = _insert(pushed, r.strategy, height=height)
        assert r.steps == alone.steps and r.stop_reason == alone.stop_reason
        np.testing.assert_allclose(r.target[-1], alone.target[-1], atol=1e-3)
        assert r.miss_mm == pytest.approx(alone.miss_mm, abs=1e-3)
