"""The filter `loop` steers on during an insertion (docs/model.md §18 on the table, §20 in a body).

Against closed forms: the scalar Kalman filter the table's steering used before the filter was shared, and the
reading itself where the sensor is exact; and against the noise it is there to remove.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scissor_cli.insertion.steering import DRIFT_SD_MM, MissFilter, NeedleModel, TableSteering, seen_directions


def _scalar(prior_sd, noise, moves, readings):
    """The scalar filter written out: predict by the move, add DRIFT_SD_MM² of variance, correct by the reading."""
    offset, var, out = 0.0, prior_sd ** 2, []
    for k, (m, z) in enumerate(zip(moves, readings)):
        if k:
            offset, var = offset + m, var + DRIFT_SD_MM ** 2
        gain = var / (var + noise ** 2)
        offset += gain * (z - offset)
        var *= 1.0 - gain
        out.append(offset)
    return np.array(out)


@settings(max_examples=30, deadline=None)
@given(st.floats(0.01, 1.0), st.floats(0.0, 0.5), st.integers(0, 2 ** 32 - 1))
def test_one_component_is_the_scalar_kalman_filter(prior_sd, noise, seed):
    rng = np.random.default_rng(seed)
    moves, readings = rng.normal(0, 0.05, 20), rng.normal(0, 0.3, 20)
    f = MissFilter(1, prior_sd, noise)
    got = [f.update(np.array([m]), np.array([z]), np.ones((1, 1)))[0] for m, z in zip(moves, readings)]
    np.testing.assert_allclose(got, _scalar(prior_sd, noise, moves, readings), rtol=1e-9, atol=1e-12)


def test_an_exact_sensor_gives_its_reading_and_an_unseen_component_the_prediction():
    f = MissFilter(2, 0.1, 0.0)
    seen = np.array([[1.0, 0.0]])  # the first component seen, the second not
    assert f.update(np.zeros(2), np.array([0.3, 5.0]), seen) == pytest.approx([0.3, 0.0])
    est = f.update(np.array([0.1, 0.2]), np.array([-0.2, 7.0]), seen)
    assert est == pytest.approx([-0.2, 0.2])  # the reading where seen; the prior plus the move where not
    est = f.update(np.array([0.0, 0.05]), np.array([0.0, 7.0]), np.zeros((0, 2)))  # nothing seen this frame
    assert est == pytest.approx([-0.2, 0.25])


def test_the_filter_follows_a_drift_with_less_error_than_the_readings():
    """A target dragged off the line at a steady rate, seen with σ = 0.1 mm, the model predicting the drag to 20 %:
    the filtered offset's error is a fraction of the readings' (seeded: the same numbers on every machine)."""
    rng = np.random.default_rng(4)
    truth, noise = np.cumsum(np.full(100, 0.006)), 0.1
    f = MissFilter(1, 0.1, noise)
    readings = truth + rng.normal(0, noise, truth.size)
    moves = np.diff(truth, prepend=0.0) * 0.8
    est = np.array([f.update(np.array([m]), np.array([z]), np.ones((1, 1)))[0] for m, z in zip(moves, readings)])
    raw, filtered = np.sqrt(np.mean((readings - truth) ** 2)), np.sqrt(np.mean((est - truth)[20:] ** 2))
    assert filtered < 0.5 * raw


@pytest.mark.parametrize("axis", [[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [1.0, 0.0, 0.0]])
def test_seen_directions_span_what_one_camera_sees_across_the_needle(axis):
    """The needle along x, across it (y, z); one camera along `axis` sees I − a aᵀ: from above y only, from the
    needle's side both, obliquely the direction it sees more than half of."""
    across = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    a = np.asarray(axis)
    rows = seen_directions(across @ (np.eye(3) - np.outer(a, a)) @ across.T)
    assert np.allclose(rows @ rows.T, np.eye(len(rows)))
    if axis == [0.0, 0.0, 1.0]:
        assert rows.shape == (1, 2) and abs(rows[0, 0]) == pytest.approx(1.0)
    elif axis == [1.0, 0.0, 0.0]:
        assert rows.shape == (2, 2)
    else:  # sees (0.8, −0.6) across fully and (0.6, 0.8) not at all
        assert rows.shape == (1, 2) and abs(rows[0] @ [0.8, -0.6]) == pytest.approx(1.0)


def test_a_body_s_table_steers_both_components_across_the_needle_on_the_filter():
    """A body's `loop` on its table (r = 2 across the needle along x, the table 3-D): J is the table's across the
    needle; the move predicted is the table's drag plus J times the strokes' change; an exact sensor that sees y
    only corrects y, z keeps the prediction (as `MissFilter` alone does)."""
    depth = np.array([1.0, 2.0, 3.0])
    target = np.array([[10.0, 0.0, 0.0], [10.0, 0.1, 0.2], [10.0, 0.3, 0.4]])  # dragged in y and z
    J = np.stack([np.array([[9.0, 9.0], [1.0, 0.0], [0.0, 2.0]])] * 3)  # (K, 3, C): x, y, z per cup
    across = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    steer = TableSteering(NeedleModel(depth, target, J, 0.0, 0.0), across, noise_mm=0.0, tolerance_mm=0.1)
    assert steer.jacobian(2.0, np.zeros(2), np.full(3, np.nan)) == pytest.approx(np.array([[1.0, 0.0], [0.0, 2.0]]))
    y_only = np.array([[1.0, 0.0]])
    assert steer.offset(1.0, np.zeros(2), np.array([0.05, 9.0]), J[0][1:], y_only) == pytest.approx([0.05, 0.0])
    # from depth 1 to 2 at strokes (0.1, 0.1): drag (0.1, 0.2) plus J (0.1, 0.1) = (0.1, 0.2); y read 0.0
    est = steer.offset(2.0, np.array([0.1, 0.1]), np.array([0.0, 9.0]), J[1][1:], y_only)
    assert est == pytest.approx([0.0, 0.4])
