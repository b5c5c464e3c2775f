"""The ultrasound's figures (docs/contract.md#figures): B-mode before and after a manipulation, and its animation.

`imaging_<target>.png`: the first and the last frame of the nominal
manipulation, log-compressed (dB, one colour bar), on mm axes in the probe's
frame (lateral across, depth down as a scanner shows it), with the tracked
lesion, the true one, the desired point and the needle line.
`imaging_<target>.gif`: the manipulation in B-mode beside the tissue (the
layer's mesh at each frame, the target, the needle line and the probe's
footprint with its field of view).

The image's depth is the scanner's apparent depth (echo time × assumed sound
speed / 2). Layer points are mapped into the probe frame with the probe's pose
(`sensing.ultrasound.ProbePose`: depth = (p − position)·axis, lateral =
(p − position)·(axis turned +90°)): the tracked lesion, which the scanner
placed from the image, lands where the image shows it; the true lesion at its
true depth, so a sound-speed mismatch shows as an offset between the two.

Built on `matplotlib.figure.Figure` directly, like `output.figures`; the
animation uses `FuncAnimation` with the Pillow writer, like the insertion's.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
from matplotlib.animation import FuncAnimation, PillowWriter
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from scissor_cli.experiments.sink import ImagingRecord
from scissor_cli.mesh.outlines import boundary_loop, deformed_outlines, embed_outlines
from scissor_cli.output.figures import OBSTACLE, TISSUE, save
from scissor_cli.output.insertion.figures import mesh_edges, pick_frames
from scissor_cli.sensing.ultrasound import ProbePose, log_compress
from scissor_cli.sensing.ultrasound.body_pose import BodyProbePose

#: the displayed dynamic range (dB) unless the record's attrs give `dynamic_range_db`
DYNAMIC_RANGE_DB = 50.0
#: the GIF keeps at most this many frames (evenly spaced, the last one always in) …
MAX_FRAMES = 24
#: … shown at this many frames per second
FPS = 4
#: the GIF's resolution (dots per inch of its 12 × 5.4 in figure)
GIF_DPI = 72
NEEDLE = "#f2a541"
TRUE = "#d1495b"
TRACKED = "#00d5ff"
DESIRED = "#7ddc1f"
PROBE = "0.1"


class PlaneView:
    """A body's probe pose as the figures read it: body points (..., 3) → (lateral, depth) (..., 2) mm in the
    image plane (their elevation, which the plane does not show, dropped)."""

    def __init__(self, body_pose: BodyProbePose):
        self.body_pose = body_pose

    def to_probe(self, points_mm: np.ndarray) -> np.ndarray:
        return self.body_pose.to_probe(points_mm)[..., :2]


def pose(record: ImagingRecord) -> ProbePose | PlaneView:
    """The probe's pose the scanner assumes (the record's position and axis; a body's also its lateral axis)."""
    if np.size(record.probe_position_mm) == 3:
        return PlaneView(BodyProbePose(record.probe_position_mm, record.probe_axis, record.attrs["lateral_axis"]))
    return ProbePose(record.probe_position_mm, record.probe_axis)


def extent_mm(record: ImagingRecord) -> tuple[float, float, float, float]:
    """imshow's extent (left, right, bottom, top) mm of the grid's pixels, depth growing downward."""
    lat, dep = np.asarray(record.grid_lateral_mm, float), np.asarray(record.grid_depth_mm, float)
    dx = (lat[-1] - lat[0]) / max(len(lat) - 1, 1)
    dz = (dep[-1] - dep[0]) / max(len(dep) - 1, 1)
    return float(lat[0] - dx / 2), float(lat[-1] + dx / 2), float(dep[-1] + dz / 2), float(dep[0] - dz / 2)


def in_db(record: ImagingRecord, ks) -> tuple[np.ndarray, float]:
    """Frames ks log-compressed (len(ks), H, W) dB against one reference, their brightest pixel; the range (dB)."""
    dr = float(record.attrs.get("dynamic_range_db", DYNAMIC_RANGE_DB))
    frames = np.asarray(record.frames)[np.asarray(ks)]
    ref = float(frames.max())
    return np.stack([log_compress(f, dr, reference=ref) for f in frames]), dr


def needle_line(record: ImagingRecord, p: ProbePose, reach_mm: float) -> np.ndarray:
    """The plan's needle line (2, d) mm in the scene, long enough (± reach_mm about the entry) to cross any view."""
    d = np.asarray(record.needle_direction, float)
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    e = np.asarray(record.needle_entry, float)
    return np.array([e - reach_mm * d, e + reach_mm * d])


def _reach_mm(record: ImagingRecord, extra: float = 0.0) -> float:
    lat, dep = np.asarray(record.grid_lateral_mm, float), np.asarray(record.grid_depth_mm, float)
    far = float(np.linalg.norm(np.asarray(record.needle_entry, float) - np.asarray(record.probe_position_mm, float)))
    return 2.0 * (far + float(np.ptp(lat) + np.ptp(dep)) + extra) + 1.0


def _bmode_axes(ax, record: ImagingRecord, db: np.ndarray, dr: float, p: ProbePose):
    """One B-mode frame (H, W) dB on ax with the needle line; returns (image, tracked, true, desired) artists."""
    ext = extent_mm(record)
    im = ax.imshow(db, cmap="gray", vmin=-dr, vmax=0.0, extent=ext, origin="upper", interpolation="bilinear",
                   aspect="equal")
    line = p.to_probe(needle_line(record, p, _reach_mm(record)))
    ax.plot(line[:, 0], line[:, 1], "-", color=NEEDLE, lw=1.2, label="needle line (plan)")
    desired = p.to_probe(np.asarray(record.desired, float))
    d_art, = ax.plot(*desired, "x", color=DESIRED, ms=7, mew=1.5, label="desired")
    t_art, = ax.plot([], [], "o", mfc="none", mec=TRUE, ms=10, mew=1.5, label="true lesion (true depth)")
    k_art, = ax.plot([], [], "+", color=TRACKED, ms=12, mew=1.6, label="tracked lesion")
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.set_xlabel("lateral (mm)")
    return im, k_art, t_art, d_art


def _depth_label(record: ImagingRecord) -> str:
    c0 = record.attrs.get("assumed_sound_speed_m_per_s")
    return "apparent depth (mm)" + (f", c₀ = {float(c0):.0f} m/s" if c0 is not None else "")


def _caption(record: ImagingRecord, dr: float) -> str:
    a = record.attrs
    speeds = ""
    if "assumed_sound_speed_m_per_s" in a and "sound_speed_m_per_s" in a:
        speeds = (f" (the scanner assumes {float(a['assumed_sound_speed_m_per_s']):.0f} m/s, the tissue's is "
                  f"{float(a['sound_speed_m_per_s']):.0f} m/s)")
    plane = (" A body's needle line and lesions are projected into the image plane; the tracked lesion lies at the "
             "plan's elevation." if np.size(record.probe_position_mm) == 3 else "")
    return (f"Depth is the scanner's apparent depth, echo time × assumed sound speed / 2{speeds}; the true lesion is "
            f"drawn at its true depth. Points mapped into the probe frame with the probe's pose.{plane} "
            f"0\u00a0dB: the brightest pixel shown; {dr:.0f}\u00a0dB displayed.")


def _miss(record: ImagingRecord, k: int, p) -> str:
    """|tracked − true| at frame k; a body's split into the image plane's part and the elevation it does not see."""
    tracked, true = np.asarray(record.tracked[k], float), np.asarray(record.true[k], float)
    if isinstance(p, PlaneView):
        apart = p.body_pose.to_probe(true) - p.body_pose.to_probe(tracked)
        return (f"tracked − true: {float(np.hypot(apart[0], apart[1])):.2f} mm in plane,\n"
                f"{abs(float(apart[2])):.2f} mm in elevation (unseen)")
    return f"|tracked − true| {float(np.linalg.norm(tracked - true)):.2f} mm"


def bmode_figure(record: ImagingRecord, title: str) -> Figure:
    """B-mode of the first and the last frame side by side (see the module docstring), one dB scale."""
    K = len(record.frames)
    p = pose(record)
    db, dr = in_db(record, [0, K - 1])
    tracked = p.to_probe(np.asarray(record.tracked, float))
    true = p.to_probe(np.asarray(record.true, float))
    fig = Figure(figsize=(10.5, 5.4), layout="constrained")
    axes = fig.subplots(1, 2, sharex=True, sharey=True)
    for ax, k, img, name in ((axes[0], 0, db[0], "before"), (axes[1], K - 1, db[1], "after")):
        im, k_art, t_art, _ = _bmode_axes(ax, record, img, dr, p)
        k_art.set_data([tracked[k, 0]], [tracked[k, 1]])
        t_art.set_data([true[k, 0]], [true[k, 1]])
        ax.set_title(f"{name}: frame {k + 1}/{K}\n{_miss(record, k, p)}", fontsize=9)
    axes[1].plot(tracked[:, 0], tracked[:, 1], "-", color=TRACKED, lw=0.8, alpha=0.8, label="tracked path")
    axes[1].plot(true[:, 0], true[:, 1], "--", color=TRUE, lw=0.8, alpha=0.8, label="true path")
    axes[0].set_ylabel(_depth_label(record))
    fig.colorbar(im, ax=list(axes), shrink=0.85, pad=0.02, label="echo amplitude (dB)")
    handles = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.legend(list(handles.values()), list(handles.keys()), loc="outside right lower", ncol=1,
               fontsize=8, frameon=False)
    fig.supxlabel(textwrap.fill(_caption(record, dr), 120), fontsize=7)
    fig.suptitle(title, fontsize=10)
    return fig


def footprint_mm(record: ImagingRecord) -> tuple[np.ndarray, np.ndarray]:
    """The probe's face (2, 2) mm and its field of view (5, 2) mm, a closed outline, in the layer's frame.

    The face spans the grid's lateral extent; the field of view spans the grid
    in apparent depth, drawn as if it were true depth.
    """
    p = pose(record)
    lat, dep = np.asarray(record.grid_lateral_mm, float), np.asarray(record.grid_depth_mm, float)
    face = p.to_layer(np.array([[lat[0], 0.0], [lat[-1], 0.0]]))
    corners = np.array([[lat[0], dep[0]], [lat[-1], dep[0]], [lat[-1], dep[-1]], [lat[0], dep[-1]], [lat[0], dep[0]]])
    return face, p.to_layer(corners)


def imaging_animation(path: Path | str, record: ImagingRecord, tissue, layer_frames: list, title: str,
                      fps: int = FPS, most: int = MAX_FRAMES) -> Path:
    """A GIF: B-mode frame k beside the tissue at layer_frames[k] (N, 2) mm, for ≤ most evenly spaced frames.

    tissue: the layer (its mesh's triangles, boundary and obstacles).
    """
    K = len(record.frames)
    ks = pick_frames(K, most)
    p = pose(record)
    db, dr = in_db(record, ks)
    mesh = tissue.mesh
    edges = mesh_edges(mesh.triangles)
    loop = boundary_loop(mesh)
    emb = embed_outlines(mesh, [o.outline for o in tissue.scene.obstacles])
    xs = [np.asarray(layer_frames[k], float)[:, :2] for k in ks]
    tracked = p.to_probe(np.asarray(record.tracked, float))
    true = p.to_probe(np.asarray(record.true, float))
    face, view = footprint_mm(record)

    fig = Figure(figsize=(12, 5.4), layout="constrained")
    FigureCanvasAgg(fig)
    ax_b, ax_t = fig.subplots(1, 2, width_ratios=[1.0, 1.6])
    im, k_art, t_art, _ = _bmode_axes(ax_b, record, db[0], dr, p)
    ax_b.set_ylabel(_depth_label(record))
    fig.colorbar(im, ax=ax_b, shrink=0.8, pad=0.02, label="dB")

    allx = np.vstack(xs + [face, view])
    pad = 3.0
    lo, hi = allx.min(0) - pad, allx.max(0) + pad
    ax_t.set_xlim(lo[0], hi[0])
    ax_t.set_ylim(lo[1], hi[1])
    ax_t.set_aspect("equal")
    skin, = ax_t.fill(*xs[0][loop].T, fc=TISSUE, ec="0.3", lw=0.8, zorder=0)
    lines = LineCollection(xs[0][edges], colors="0.5", linewidths=0.3, zorder=1)
    ax_t.add_collection(lines)
    obstacles = [ax_t.fill([], [], fc=OBSTACLE, alpha=0.45, ec=OBSTACLE, lw=0.8, zorder=2)[0] for _ in emb.splits]
    needle = needle_line(record, p, _reach_mm(record, float(np.ptp(allx))))
    ax_t.plot(needle[:, 0], needle[:, 1], "-", color=NEEDLE, lw=1.2, zorder=3, label="needle line (plan)")
    ax_t.plot(*view.T, "--", color="0.25", lw=0.8, zorder=3, label="image (apparent depth)")
    ax_t.plot(*face.T, "-", color=PROBE, lw=4, solid_capstyle="butt", zorder=4, label="probe")
    ax_t.plot(*np.asarray(record.desired, float), "o", mfc="none", mec="k", ms=9, mew=1.2, zorder=5, label="desired")
    true_t, = ax_t.plot([], [], "o", color=TRUE, ms=5, mec="k", mew=0.5, zorder=6, label="true target")
    tracked_t, = ax_t.plot([], [], "+", color="#006d8f", ms=10, mew=1.6, zorder=6, label="tracked")
    ax_t.set_xlabel("x (mm)")
    ax_t.set_ylabel("y (mm)")
    fig.legend(*ax_t.get_legend_handles_labels(), loc="outside lower center", ncol=6, fontsize=8, frameon=False)
    caption = fig.suptitle(f"{title}\n", fontsize=9)
    frame_time = record.attrs.get("frame_time_s")
    strokes = np.atleast_2d(np.asarray(record.strokes, float))

    def draw(i):
        k = int(ks[i])
        x = xs[i]
        im.set_data(db[i])
        k_art.set_data([tracked[k, 0]], [tracked[k, 1]])
        t_art.set_data([true[k, 0]], [true[k, 1]])
        skin.set_xy(x[loop])
        lines.set_segments(x[edges])
        for patch, poly in zip(obstacles, deformed_outlines(emb, x)):
            patch.set_xy(poly)
        true_t.set_data([record.true[k][0]], [record.true[k][1]])
        tracked_t.set_data([record.tracked[k][0]], [record.tracked[k][1]])
        when = f", t = {k * float(frame_time):.2f} s" if frame_time is not None else ""
        stroke = ", ".join(f"{s:+.2f}" for s in strokes[k])
        caption.set_text(f"{title}\nframe {k + 1}/{K}{when}; strokes ({stroke}) mm; {_miss(record, k, p)}")
        return [im, k_art, t_art, skin, lines, true_t, tracked_t, caption, *obstacles]

    draw(0)
    fig.canvas.draw()
    fig.set_layout_engine("none")  # the layout of the first frame for all: no frame jumps
    anim = FuncAnimation(fig, draw, frames=len(ks), blit=False)
    anim.save(str(path), writer=PillowWriter(fps=fps), dpi=GIF_DPI)
    return Path(path)


def imaging_outputs(record: ImagingRecord, tissue, layer_frames: list, out_dir: Path) -> list[Path]:
    """imaging_<target>.png (before | after) and imaging_<target>.gif (the manipulation beside the tissue).

    layer_frames: the tissue's nodes (N, 2) mm at each of the record's K frames. A body's record (3-D): the
    PNG alone, its needle line and lesions projected into the image plane (no animation beside a 3-D body).
    """
    K = len(record.frames)
    body = np.size(record.probe_position_mm) == 3
    if not body and len(layer_frames) != K:
        raise ValueError(f"imaging {record.target}: {len(layer_frames)} tissue frames for {K} B-mode frames")
    a = record.attrs
    probe = f"{a['probe']}, " if "probe" in a else ""
    model = f"{a['model']} model, " if "model" in a else ""
    name = tissue.scene.name
    png = save(bmode_figure(record, f"{name} — {record.target}: B-mode before and after the manipulation "
                                    f"({probe}{model}{K} frames)"), Path(out_dir) / f"imaging_{record.target}.png")
    if body:
        return [png]
    title = f"{name} — {record.target}: the manipulation in B-mode ({probe.rstrip(', ') or 'ultrasound'})"
    gif = imaging_animation(Path(out_dir) / f"imaging_{record.target}.gif", record, tissue, layer_frames, title)
    return [png, gif]
