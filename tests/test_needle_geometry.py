"""The needle's geometry generic by dimension (docs/model.md §12, §14): transverse basis, capture by the
distance to the axis (3-D: both transverse components), shares along the axis
(the tip zone: tests/test_tip_zone.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from scissor_cli.insertion import shaft_lengths
from scissor_cli.insertion.capture import capture, capture_radii, free_nodes, node_edges
from scissor_cli.insertion.needle import STEP_TOL_BODY, NeedleParams, NeedleState, transverse_basis
from scissor_cli.insertion.run import miss_and_depth_error

from figure_checks import assert_figure_readable


@pytest.mark.parametrize("n", [
    [1.0, 0.0], [0.6, 0.8], [1.0, 0.0, 0.0], [0.6, -0.8, 0.0], [0.0, 0.0, 1.0], [2 / 3, 1 / 3, 2 / 3],
])
def test_transverse_basis_is_orthonormal_and_across_the_axis(n):
    n = np.asarray(n)
    T = transverse_basis(n)
    assert T.shape == (n.size - 1, n.size)
    np.testing.assert_allclose(T @ T.T, np.eye(n.size - 1), atol=1e-12)
    np.testing.assert_allclose(T @ n, 0.0, atol=1e-12)


def test_in_layer_axis_splits_into_the_layers_normal_and_the_height():
    """A slab's offset is the layer's across-axis offset plus the height: what makes the blade test possible."""
    n2 = np.array([0.6, 0.8])
    T3 = transverse_basis(np.append(n2, 0.0))
    np.testing.assert_allclose(T3[0], np.append(NeedleState(np.zeros(2), n2).across, 0.0), atol=1e-15)
    np.testing.assert_allclose(np.abs(T3[1]), [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(transverse_basis(n2)[0], NeedleState(np.zeros(2), n2).across)


def test_capture_uses_the_3d_distance_to_the_axis():
    state = NeedleState(np.array([0.0, 0.0, 5.0]), np.array([1.0, 0.0, 0.0]), depth_mm=10.0)
    x = np.array([
        [4.0, 1.5, 5.0],   # 1.5 mm across in the layer: captured
        [4.0, 0.0, 6.5],   # 1.5 mm above the layer: captured
        [4.0, 1.5, 6.5],   # each component within 2 mm, the distance 2.12 mm is not
        [12.0, 0.0, 5.0],  # on the axis ahead of the tip: not yet
        [-1.0, 0.0, 5.0],  # behind the entry
        [9.9, -1.9, 5.0],  # just inside, near the tip
    ])
    radii = np.full(len(x), 2.0)
    got = capture(x, np.arange(len(x)), state.entry, state.direction, state.depth_mm, state.captured, radii)
    assert sorted(got.tolist()) == [0, 1, 5]
    assert sorted(capture(x, np.arange(len(x)), state.entry, state.direction, state.depth_mm, np.array([1]),
                          radii).tolist()) == [0, 5]
    # each node against its own radius: node 1 (1.5 mm off) is not captured with a 1.4 mm one
    radii[1] = 1.4
    assert sorted(capture(x, np.arange(len(x)), state.entry, state.direction, state.depth_mm, state.captured,
                          radii).tolist()) == [0, 5]


def test_2d_capture_unchanged():
    state = NeedleState(np.zeros(2), np.array([0.0, 1.0]), depth_mm=5.0)
    x = np.array([[1.9, 3.0], [-2.1, 3.0], [0.0, 5.5], [0.5, 0.0]])
    assert sorted(capture(x, np.arange(4), state.entry, state.direction, state.depth_mm, state.captured,
                          np.full(4, 2.0)).tolist()) == [0, 3]


def test_node_edges_of_a_right_tetrahedron():
    """Node 0 meets three unit edges; node 1 one unit edge and two √2 ones."""
    X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    mean, longest = node_edges(X, np.arange(4)[:, None])
    np.testing.assert_allclose(mean, [1.0] + [(1.0 + 2.0 * np.sqrt(2.0)) / 3.0] * 3, rtol=1e-12)
    np.testing.assert_allclose(longest, [1.0] + [np.sqrt(2.0)] * 3, rtol=1e-12)


def test_a_body_captures_by_its_local_edge_and_a_layer_by_its_coarsest():
    """The defaults (docs/model.md §20): a body's radius half the mean edge at each node, a layer's half the max edge;
    a body's steps solved to STEP_TOL_BODY, a layer's by dimension."""
    from scissor_cli.config import InsertionConfig, NeedleConfig
    from scissor_cli.config.body_sections import BodyMeshConfig
    from scissor_cli.config.sections import MeshConfig

    body = NeedleParams.from_config(InsertionConfig(), NeedleConfig(), BodyMeshConfig(max_edge_mm=6.0, min_edge_mm=1.5))
    assert body.capture_radius_mm is None and body.step_tol == STEP_TOL_BODY
    assert body.tolerances(3) == (STEP_TOL_BODY, STEP_TOL_BODY)
    layer = NeedleParams.from_config(InsertionConfig(), NeedleConfig(), MeshConfig(max_edge_mm=4.0, min_edge_mm=1.0))
    assert layer.capture_radius_mm == pytest.approx(2.0) and layer.step_tol is None
    given = NeedleParams.from_config(InsertionConfig(capture_radius_mm=1.0), NeedleConfig(),
                                     BodyMeshConfig(max_edge_mm=6.0, min_edge_mm=1.5))
    assert given.capture_radius_mm == 1.0
    # two tetrahedra sharing a face, the second three times the size: its apex takes half its own edges
    X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [3.0, 3.0, 3.0]])
    corners = np.array([[0, 1, 2, 3], [1, 2, 3, 4]]).T
    tissue = SimpleNamespace(mesh=SimpleNamespace(nodes=X, n_nodes=5), ops=SimpleNamespace(corners=corners))
    np.testing.assert_array_equal(capture_radii(tissue, 2.5), 2.5)
    local = capture_radii(tissue, None)
    apex = np.linalg.norm(X[4] - X[1:4], axis=1).mean()
    assert local[4] == pytest.approx(0.5 * apex)
    assert local[0] == pytest.approx(0.5)


def test_shares_along_the_axis_sum_to_the_depth_in_3d():
    """Shares depend on positions along the axis only: nodes at several heights share like one sorted line."""
    state = NeedleState(np.array([0.0, 0.0, 5.0]), np.array([0.0, 1.0, 0.0]), depth_mm=8.0)
    x = np.array([[0.3, 1.0, 4.0], [-0.2, 1.0, 6.0], [0.0, 5.0, 5.0], [1.0, 7.5, 3.5]])
    lengths = shaft_lengths((x - state.entry) @ state.direction, state.depth_mm)
    assert lengths.sum() == pytest.approx(8.0, abs=1e-12)
    # the axial positions 1, 1, 5, 7.5: half gaps, the entry's and the tip's gaps to the ends
    np.testing.assert_allclose(lengths, [1.0, 2.0, 3.25, 1.75], atol=1e-12)


def test_free_nodes_needs_every_dof_free():
    fi = np.array([0, 1, 2, -1, 3, 4, 5, 6, 7, 8, -1, 9]).astype(np.int64)
    assert free_nodes(SimpleNamespace(free_index=fi, dim=3)).tolist() == [0, 2]
    assert free_nodes(SimpleNamespace(free_index=fi, dim=2)).tolist() == [0, 2, 3, 4]


def test_miss_in_3d_is_the_distance_to_the_needle_line():
    entry, n = np.array([0.0, 0.0, 5.0]), np.array([0.6, 0.8, 0.0])
    target = entry + 10.0 * n + np.array([0.8, -0.6, 0.0]) * 0.3 + np.array([0.0, 0.0, 0.4])
    miss, depth_error = miss_and_depth_error(target, entry, n, 9.0)
    assert miss == pytest.approx(0.5) and depth_error == pytest.approx(-1.0)
    # in the layer's plane the 3-D miss is the 2-D one
    m2, d2 = miss_and_depth_error(target[:2], entry[:2], n[:2], 9.0)
    assert m2 == pytest.approx(0.3) and d2 == pytest.approx(-1.0)


@pytest.mark.parametrize("d", [2, 3])
def test_target_path_figure_takes_a_slab_insertion(d):
    """The path figure draws the layer's plane; a slab insertion's targets (K, 3) show their in-plane part."""
    from scissor_cli.output.insertion.figures import target_path_figure

    k = 5
    target = np.zeros((k, d))
    target[:, 0] = np.linspace(10.0, 10.4, k)
    target[:, 1] = 20.0
    r = SimpleNamespace(steps=k, target=target, strategy="none", miss_mm=0.1, depth_error_mm=0.0,
                        direction=np.eye(d)[0])
    fig = target_path_figure("t", [r], target[0])
    line = fig.axes[0].lines[1]
    np.testing.assert_allclose(line.get_xydata(), target[:, :2])
    assert_figure_readable(fig)


def test_needle_force_figure_is_readable():
    from scissor_cli.output.insertion.figures import needle_force_figure

    depth = np.linspace(0.0, 10.0, 21)
    runs = [SimpleNamespace(depth_mm=depth, needle_force_mN=f * depth, strategy=s, steps=21)
            for s, f in (("none", 10.0), ("loop", 12.0))]
    fig = needle_force_figure("T1: needle force", runs)
    assert [line.get_label() for line in fig.axes[0].lines] == ["none (21 steps)", "loop (21 steps)"]
    assert_figure_readable(fig)
