"""The ultrasound's outputs: /imaging in results.h5 (writer, reader, refusals), its figures, and report's sensor."""

from __future__ import annotations

import csv
from dataclasses import dataclass

import h5py
import numpy as np
import pytest
from PIL import Image
from scipy.ndimage import gaussian_filter

from scissor_cli.config import load_config
from scissor_cli.experiments.build import build_model
from scissor_cli.experiments.sink import ImagingRecord, NonFiniteError
from scissor_cli.output.imaging.figures import footprint_mm, imaging_animation
from scissor_cli.output.imaging.results import (
    ImagingMismatch,
    flat_attrs,
    read_imaging,
    sensor_of,
    write_imaging,
)
from scissor_cli.output.report import report_trials
from scissor_cli.output.results import ResultsFile, reopen
from scissor_cli.output.results_sink import RunDirectory

from figure_checks import assert_png_drawn
from helpers import example_dict, write_scene

POSITION = np.array([45.0, 60.0])  # on the top skin, looking down: lateral = +x, depth = 60 − y
AXIS = np.array([0.0, -1.0])
H, W, K = 60, 40, 4
ATTRS = {"probe": "L11-5v", "assumed_sound_speed_m_per_s": 1540.0, "sound_speed_m_per_s": 1480.0, "model": "fast",
         "frame_time_s": 0.1, "validation_envelope_correlation": 0.96, "validation_tracking_difference_mm": 0.012}


def push(points: np.ndarray, stroke_mm: float) -> np.ndarray:
    """A smooth push under the cup (x = 50 mm) fading with depth: displacement (..., 2) mm."""
    x, y = points[..., 0], points[..., 1]
    w = (y / 60.0) * np.exp(-((x - 50.0) / 25.0) ** 2)
    return np.stack([0.1 * stroke_mm * w, -stroke_mm * w], -1)


def make_record(target="T1", rest=(50.0, 27.5), k=K, seed=0, depth_mm=(0.5, 40.0), **changes) -> ImagingRecord:
    """K Rayleigh-like envelopes (H, W) with a dark (−10 dB) disc of 2 mm at the true lesion's place."""
    rng = np.random.default_rng(seed)
    lateral, depth = np.linspace(-19.0, 19.0, W), np.linspace(*depth_mm, H)
    strokes = np.linspace(0.0, 6.0, k)
    rest = np.asarray(rest, float)
    true = np.array([rest + push(rest, s) for s in strokes])
    L, D = np.meshgrid(lateral, depth)
    frames = []
    for p in true:
        lat, dep = p[0] - POSITION[0], POSITION[1] - p[1]
        e = gaussian_filter(np.abs(rng.standard_normal((H, W)) + 1j * rng.standard_normal((H, W))), (0.7, 1.0))
        e[(L - lat) ** 2 + (D - dep) ** 2 < 4.0] *= 10 ** (-10 / 20)
        frames.append(e)
    fields = {"target": target, "grid_lateral_mm": lateral, "grid_depth_mm": depth,
              "frames": np.asarray(frames, np.float32), "tracked": true + rng.normal(scale=0.1, size=true.shape),
              "true": true, "strokes": strokes[:, None], "needle_entry": np.array([100.0, 25.0]),
              "needle_direction": np.array([-1.0, 0.0]), "desired": np.array([50.0, 25.0]),
              "probe_position_mm": POSITION, "probe_axis": AXIS, "attrs": dict(ATTRS)}
    return ImagingRecord(**(fields | changes))


def layer_frames(nodes: np.ndarray, record: ImagingRecord) -> list[np.ndarray]:
    return [nodes + push(nodes, s) for s in record.strokes[:, 0]]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    directory = tmp_path_factory.mktemp("scene")
    path = write_scene(directory, example_dict())
    tissue = build_model(load_config(path), mesh_scale=2.0)[2]
    return path.read_text(), tissue


@pytest.fixture(scope="module")
def run(scene, tmp_path_factory):
    """Two targets' imaging through a real ResultsSink: (run dir, {target: record}, {target: figure paths})."""
    text, tissue = scene
    directory = tmp_path_factory.mktemp("run")
    records = {"T1": make_record(), "T2": make_record("T2", (58.0, 22.0), seed=1)}
    paths = {}
    with RunDirectory(directory).open(text, 7) as sink:
        for name, rec in records.items():
            paths[name] = sink.imaging(rec, tissue, layer_frames(tissue.mesh.nodes, rec))
    return directory, records, paths


def test_imaging_layout_units_and_attrs(run):
    directory, records, _ = run
    with h5py.File(directory / "results.h5") as f:
        assert f.attrs["status"] == "complete" and sensor_of(f) == "ultrasound"
        g = f["imaging"]
        assert g["grid_lateral_mm"].shape == (W,) and g["grid_depth_mm"].shape == (H,)
        assert g["grid_lateral_mm"].dtype == np.float64 and g["grid_lateral_mm"].attrs["units"] == "mm"
        assert g["grid_depth_mm"].attrs["units"] == "mm"
        for key, value in ATTRS.items():
            assert g.attrs[key] == value
        np.testing.assert_array_equal(g.attrs["position_mm"], POSITION)
        np.testing.assert_array_equal(g.attrs["axis"], AXIS)
        for name, rec in records.items():
            t = g[name]
            frames = t["frames"]
            assert frames.shape == (K, H, W) and frames.dtype == np.float32
            assert frames.chunks == (1, H, W) and frames.compression == "gzip" and "units" in frames.attrs
            for key, shape in (("tracked", (K, 2)), ("true", (K, 2)), ("strokes", (K, 1))):
                assert t[key].shape == shape and t[key].dtype == np.float64 and t[key].attrs["units"] == "mm"
            assert list(t["strokes"].attrs["columns"]) == ["cup"]
            np.testing.assert_array_equal(t.attrs["needle_entry"], rec.needle_entry)
            np.testing.assert_array_equal(t.attrs["needle_direction"], rec.needle_direction)
            np.testing.assert_array_equal(t.attrs["desired"], rec.desired)

        def finite(name, obj):
            if isinstance(obj, h5py.Dataset) and obj.dtype.kind == "f":
                assert np.all(np.isfinite(obj[()])), name
            for key, value in obj.attrs.items():
                a = np.asarray(value)
                assert a.dtype.kind != "f" or np.all(np.isfinite(a)), f"{name}@{key}"

        f.visititems(finite)


def test_reader_round_trips(run):
    directory, records, _ = run
    with h5py.File(directory / "results.h5") as f:
        back = read_imaging(f)
    assert list(back) == ["T1", "T2"]
    for name, rec in records.items():
        got = back[name]
        for field in ("grid_lateral_mm", "grid_depth_mm", "frames", "tracked", "true", "strokes", "needle_entry",
                      "needle_direction", "desired", "probe_position_mm", "probe_axis"):
            np.testing.assert_array_equal(getattr(got, field), getattr(rec, field), err_msg=field)
        assert got.frames.dtype == np.float32 and got.target == name
        assert {k: got.attrs[k] for k in ATTRS} == ATTRS


def test_figures_are_written(run):
    directory, _, paths = run
    for name, files in paths.items():
        assert [p.name for p in files] == [f"imaging_{name}.png", f"imaging_{name}.gif"]
        assert all(p.parent == directory for p in files)
        png, gif = (Image.open(p) for p in files)
        assert png.format == "PNG" and png.size[0] > 800
        assert_png_drawn(files[0])
        assert gif.format == "GIF" and gif.n_frames == K and files[1].stat().st_size > 30_000
        gif.seek(K - 1)  # the frames differ: the B-mode and the tissue move
        last = np.asarray(gif.convert("RGB"), float)
        gif.seek(0)
        assert np.abs(np.asarray(gif.convert("RGB"), float) - last).mean() > 1.0


def test_the_animation_keeps_a_bounded_number_of_frames(scene, tmp_path):
    _, tissue = scene
    rec = make_record(k=7)
    path = imaging_animation(tmp_path / "a.gif", rec, tissue, layer_frames(tissue.mesh.nodes, rec), "t", most=3)
    assert Image.open(path).n_frames == 3
    face, view = footprint_mm(rec)  # the probe's face on the skin, its view down to the grid's last depth
    np.testing.assert_allclose(face, [[26.0, 60.0], [64.0, 60.0]])
    np.testing.assert_allclose(view[2], [64.0, 20.0])


def new_file(tmp_path, text="name: t\n") -> ResultsFile:
    return ResultsFile.create(tmp_path / "results.h5", text, 1)


def test_a_second_target_must_share_the_grid_and_the_attrs(tmp_path):
    out = new_file(tmp_path)
    write_imaging(out, make_record())
    with pytest.raises(ImagingMismatch, match="grid"):
        write_imaging(out, make_record("T2", depth_mm=(0.5, 45.0)))
    with pytest.raises(ImagingMismatch, match="sound_speed_m_per_s"):
        write_imaging(out, make_record("T2", attrs=ATTRS | {"sound_speed_m_per_s": 1560.0}))
    with pytest.raises(ImagingMismatch, match="position_mm"):
        write_imaging(out, make_record("T2", probe_position_mm=np.array([40.0, 60.0])))
    assert "T2" not in out.h5["imaging"]
    write_imaging(out, make_record("T1", depth_mm=(0.5, 45.0)))  # the same target alone again (a resume): replaced
    assert out.h5["imaging/grid_depth_mm"][-1] == 45.0
    out.close("complete")


def test_bad_records_are_refused_before_anything_is_written(tmp_path):
    out = new_file(tmp_path)
    tracked = make_record().tracked.copy()
    tracked[2, 1] = np.nan
    with pytest.raises(NonFiniteError, match="/imaging/T1/tracked"):
        write_imaging(out, make_record(tracked=tracked))
    frames = make_record().frames.copy()
    frames[0, 3, 3] = np.inf
    with pytest.raises(NonFiniteError, match="frames"):
        write_imaging(out, make_record(frames=frames))
    with pytest.raises(ValueError, match=r"frames must be \(K, H, W\)"):
        write_imaging(out, make_record(frames=make_record().frames[:, :, :-1]))
    with pytest.raises(ValueError, match="strokes"):
        write_imaging(out, make_record(strokes=np.zeros((K + 1, 1))))
    with pytest.raises(ValueError, match="is None"):
        write_imaging(out, make_record(attrs=ATTRS | {"validation": None}))
    assert "imaging" not in out.h5
    out.close("complete")


def test_nested_attrs_are_flattened():
    @dataclass(frozen=True)
    class Validation:
        envelope_correlation: float
        tracked_fast_mm: np.ndarray

    flat = flat_attrs({"probe": "L11-5v", "validation": Validation(0.95, np.array([0.1, 0.2])),
                       "psf": {"axial_mm": 0.2, "lateral": {"mm": 0.6}}})
    assert flat["validation_envelope_correlation"] == 0.95 and flat["psf_lateral_mm"] == 0.6
    np.testing.assert_array_equal(flat["validation_tracked_fast_mm"], [0.1, 0.2])
    assert set(flat) == {"probe", "validation_envelope_correlation", "validation_tracked_fast_mm", "psf_axial_mm",
                         "psf_lateral_mm"}


# ---------------------------------------------------------------- report

COLUMNS = np.array(["time_s", "stroke_cmd_cup", "stroke_cup", "measured_x", "measured_y", "true_x", "true_y"],
                   dtype=object)


def hand_run(directory, text, seed, sensor_noise_mm):
    """A complete results.h5 with 5 trials of T1 (one crashed), their histories and insertion misses, by hand."""
    directory.mkdir()
    rng = np.random.default_rng(seed)
    T = 5
    with h5py.File(directory / "results.h5", "w") as f:
        f.attrs.update({"status": "complete", "config_yaml": text, "seed": seed})
        f.create_group("cups/cup")
        g = f.create_group("trials/T1")
        f["trials"].attrs["profile"] = "lab"
        g["final_error"] = rng.normal(scale=0.3, size=(T, 2))
        g["iterations"] = np.array([4, 5, 6, 3, -1])
        g["time_s"] = rng.uniform(1, 2, T)
        g["corridor_clear"] = np.ones(T, bool)
        g["done"] = np.ones(T, bool)
        g["failed"] = np.array([False] * 4 + [True])
        g["stop_reason"] = np.array(["tolerance"] * 4 + ["crashed"], dtype=object)
        g["manipulation_miss_mm"] = np.array([0.1, 0.2, 0.3, 0.4, 0.0])
        g["along_mm"] = rng.normal(size=T)
        g["miss_mm"] = np.array([[0.5, 0.2], [0.6, 0.3], [0.7, 0.1], [0.8, 0.4], [0.0, 0.0]])
        g["miss_mm"].attrs["strategies"] = ["none", "loop"]
        g["depth_error_mm"] = rng.normal(size=(T, 2))
        for k in range(4):
            true = rng.normal(size=(3, 2))
            measured = true + np.array([sensor_noise_mm, 0.0])
            h = g.create_dataset(f"history/{k}", data=np.column_stack([np.arange(3) * 0.1, np.ones(3), np.ones(3),
                                                                      measured, true]))
            h.attrs["columns"] = COLUMNS
    return directory


def read_csv(path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_report_names_the_sensor_and_compares_them(scene, tmp_path):
    text, _ = scene
    camera = hand_run(tmp_path / "camera", text, 1, 0.05)
    ultrasound = hand_run(tmp_path / "ultrasound", text, 2, 0.2)
    with reopen(ultrasound / "results.h5") as out:
        write_imaging(out, make_record())

    alone = report_trials([camera], tmp_path / "rep1")  # one sensor: the column, no comparison
    rows = read_csv(tmp_path / "rep1" / "summary.csv")
    assert [r["sensor"] for r in rows] == ["camera"] and not (tmp_path / "rep1" / "sensors.md").exists()
    assert "Camera against ultrasound" not in alone.table_markdown
    header = list(rows[0])
    assert header.index("sensor") == header.index("controller") + 1 and header[:3] == ["run", "target", "trials"]

    both = report_trials([camera, ultrasound], tmp_path / "rep2")
    rows = read_csv(tmp_path / "rep2" / "summary.csv")
    assert [r["sensor"] for r in rows] == ["camera", "ultrasound"]
    md = (tmp_path / "rep2" / "sensors.md").read_text()
    assert "Camera against ultrasound" in both.table_markdown and md in both.table_markdown
    lines = [[c.strip() for c in line.strip("|").split("|")] for line in md.strip().splitlines()]
    head, body = lines[0], lines[2:]
    assert head == ["run", "sensor", "target", "what", "count", "median_mm", "p95_mm", "max_mm"]
    table = {(r[1], r[3]): dict(zip(head, r)) for r in body}
    assert set(table) == {(s, w) for s in ("camera", "ultrasound")
                          for w in ("manipulation miss", "needle miss (none)", "needle miss (loop)", "sensor error")}
    miss = table[("camera", "manipulation miss")]  # the crashed trial left out
    assert miss["count"] == "4" and float(miss["median_mm"]) == pytest.approx(0.25) and miss["max_mm"] == "0.400"
    assert float(table[("camera", "needle miss (loop)")]["max_mm"]) == pytest.approx(0.4)
    assert table[("ultrasound", "sensor error")]["count"] == "12"
    assert float(table[("ultrasound", "sensor error")]["median_mm"]) == pytest.approx(0.2)
    assert float(table[("camera", "sensor error")]["max_mm"]) == pytest.approx(0.05)


def test_a_run_without_imaging_reads_camera(tmp_path):
    out = new_file(tmp_path)
    out.close("complete")
    with h5py.File(tmp_path / "results.h5") as f:
        assert sensor_of(f) == "camera" and read_imaging(f) == {}
