"""The figure checks themselves (tests/figure_checks.py) fail on what they are meant to catch."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure

from scissor_cli.output.figures import save

from figure_checks import assert_figure_readable, assert_png_drawn, png_measures


def _plotted(labels: bool = True, title: bool = True) -> Figure:
    fig = Figure(figsize=(5, 4))
    ax = fig.add_subplot(1, 1, 1)
    t = np.linspace(0.0, 6.0, 50)
    ax.plot(t, np.sin(t), color="tab:blue", lw=3)
    ax.fill_between(t, 0.0, np.sin(t), color="tab:orange", alpha=0.6)
    if labels:
        ax.set_xlabel("t (s)")
        ax.set_ylabel("x (mm)")
    if title:
        ax.set_title("a drawing")
    return fig


def test_a_plotted_figure_passes(tmp_path):
    fig = _plotted()
    assert_figure_readable(fig)
    m = assert_png_drawn(save(fig, tmp_path / "ok.png"))
    assert 0 < m["ink"] < 1 and m["colour"] > 0


def test_a_blank_image_fails(tmp_path):
    path = save(Figure(figsize=(5, 4)), tmp_path / "blank.png")
    assert png_measures(path)["ink"] == 0.0
    with pytest.raises(AssertionError, match="blank"):
        assert_png_drawn(path)


def test_labelled_axes_without_data_fail(tmp_path):
    fig = Figure(figsize=(5, 4))
    ax = fig.add_subplot(1, 1, 1)
    ax.set(xlabel="x (mm)", ylabel="y (mm)", title="empty", xlim=(0, 1), ylim=(0, 1))
    with pytest.raises(AssertionError, match="no data"):
        assert_png_drawn(save(fig, tmp_path / "frame.png"))
    with pytest.raises(AssertionError, match="no axes draws"):
        assert_figure_readable(fig)


def test_missing_labels_and_titles_fail():
    with pytest.raises(AssertionError, match="what x is"):
        assert_figure_readable(_plotted(labels=False))
    with pytest.raises(AssertionError, match="without a title"):
        assert_figure_readable(_plotted(title=False))


def test_named_ticks_and_a_shared_label_say_what_an_axis_shows():
    fig = Figure(figsize=(6, 3))
    left, right = fig.subplots(1, 2, sharey=True)
    left.boxplot([np.arange(5.0), np.arange(3.0, 9.0)], tick_labels=["T1", "T2"])
    right.boxplot([np.arange(5.0), np.arange(3.0, 9.0)])
    right.set_xticks([1, 2], ["T1", "T2"])  # (a FuncFormatter, not boxplot's FixedFormatter)
    left.set_ylabel("miss (mm)")
    fig.suptitle("box plots")
    assert_figure_readable(fig)
