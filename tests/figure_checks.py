"""What a reader of a written figure would notice: a blank or empty image, an axes without labels.

`assert_png_drawn` opens a PNG the code wrote and measures its pixels:
  * ink: the fraction of pixels away from the background (the image's most
    common colour) by more than INK_STEP in some channel;
  * colour: the fraction of pixels whose channels differ from each other by
    more than COLOUR_SPREAD. Axes, ticks and text are black or grey; every
    scissor figure draws its data in colour (tissue, boxes, curves, density),
    so a frame with labels but no data has ink and no colour;
  * spread: the standard deviation of the grey levels.
A blank image fails all three.

`assert_figure_readable` checks a `matplotlib.figure.Figure` the output
functions return, before or after it is saved: at least one axes draws
data, and every axes that draws data has a title (its own or the figure's
suptitle) and says what each axis shows: a label, the label of an axes
sharing that axis, or named ticks (box plots name their targets there).
Colour-bar axes are left out; they carry their own label.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.image import imread

INK_STEP = 0.1
COLOUR_SPREAD = 0.15


def png_measures(path: Path | str) -> dict[str, float]:
    """Ink, colour (fractions of pixels), grey-level spread and size of the PNG at path (see the module doc)."""
    image = imread(str(path))
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    rgb = image[..., :3].astype(float)
    if image.shape[2] == 4:  # transparent parts show the page: composite on white
        alpha = image[..., 3:4].astype(float)
        rgb = rgb * alpha + (1.0 - alpha)
    pixels = rgb.reshape(-1, 3)
    levels, counts = np.unique(np.round(pixels * 255).astype(np.int16), axis=0, return_counts=True)
    background = levels[np.argmax(counts)] / 255.0
    ink = float(np.mean(np.abs(pixels - background).max(axis=1) > INK_STEP))
    colour = float(np.mean(np.ptp(pixels, axis=1) > COLOUR_SPREAD))
    return {"ink": ink, "colour": colour, "spread": float(pixels.mean(axis=1).std()),
            "height": image.shape[0], "width": image.shape[1]}


def assert_png_drawn(path: Path | str, min_ink: float = 0.02, min_colour: float = 0.001,
                     min_spread: float = 0.05) -> dict[str, float]:
    """The PNG at path shows a drawing: ink, colour and grey-level spread at least the given minima."""
    m = png_measures(path)
    assert m["height"] >= 200 and m["width"] >= 200, f"{path}: a {m['width']} x {m['height']} image"
    assert m["ink"] >= min_ink, f"{path}: {m['ink']:.4f} of the pixels drawn (< {min_ink}): blank"
    assert m["colour"] >= min_colour, f"{path}: {m['colour']:.4f} of the pixels in colour (< {min_colour}): no data"
    assert m["spread"] >= min_spread, f"{path}: grey-level spread {m['spread']:.4f} (< {min_spread})"
    return m


def draws_data(ax) -> bool:
    """Whether the axes draws any data: a line with a finite point, a non-empty collection, a patch, an image."""
    for line in ax.lines:
        xy = np.asarray(line.get_xydata(), float)
        if xy.size and np.isfinite(xy).all(axis=1).any():
            return True
    for c in ax.collections:
        if len(c.get_paths()) or len(c.get_offsets()):
            return True
    return bool(ax.patches or ax.images)


def _named_ticks(axis) -> bool:
    """Whether a tick label is a name (has a letter and is not a number in mathtext, like a log axis's)."""
    labels = axis.get_major_formatter().format_ticks(axis.get_majorticklocs())
    return any(re.search(r"[A-Za-z]", s) and not s.startswith("$") for s in map(str, labels))


def _says_what_it_shows(ax, which: str) -> bool:
    axis = ax.xaxis if which == "x" else ax.yaxis
    shared = ax.get_shared_x_axes() if which == "x" else ax.get_shared_y_axes()
    return any(a.xaxis.get_label_text() if which == "x" else a.yaxis.get_label_text()
               for a in shared.get_siblings(ax)) or _named_ticks(axis)


def assert_figure_readable(fig: Figure) -> None:
    """At least one axes draws data; each that does has a title and names what its x and y axes show."""
    axes = [ax for ax in fig.axes if ax.get_visible() and not hasattr(ax, "_colorbar")]
    drawn = [ax for ax in axes if draws_data(ax)]
    assert drawn, "no axes draws any data"
    suptitle = fig.get_suptitle()
    for ax in drawn:
        name = ax.get_title() or ax.get_title("left") or ax.get_title("right") or "untitled axes"
        assert ax.get_title() or ax.get_title("left") or ax.get_title("right") or suptitle, "an axes without a title"
        assert _says_what_it_shows(ax, "x"), f"{name!r}: nothing says what x is (no label, no named ticks)"
        assert _says_what_it_shows(ax, "y"), f"{name!r}: nothing says what y is (no label, no named ticks)"
