"""results.h5 `/imaging` (docs/contract.md#resultsh5, docs/ultrasound.md): the ultrasound frames of each target's
nominal manipulation, the tracked and true lesion, and the run's imaging settings.

Layout:

* `/imaging/grid_lateral_mm` (W,), `/imaging/grid_depth_mm` (H,) float64 mm:
  the image grid in the probe's frame, one per run. Every target shares it:
  a target whose grid differs is refused (`ImagingMismatch`).
* `/imaging` attrs: the record's `attrs` (probe, sound speeds, model,
  frame_time_s, the fast model's validation against SIMUS, …) with
  `position_mm` and `axis`, the probe's pose. Also one per run: a later
  target's must be the same.
* `/imaging/<target>/frames` (K, H, W) float32: the envelope, linear; one
  gzip chunk per frame. `tracked`, `true` (K, 2) mm in the layer's frame
  ((K, 3) in a body's, whose /imaging attrs add `lateral_axis`),
  `strokes` (K, C) mm; attrs `needle_entry`, `needle_direction`, `desired`.

Every array goes through `ResultsFile`'s finite check first.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import h5py
import numpy as np

from scissor_cli.experiments.sink import ImagingRecord
from scissor_cli.output.results import ResultsFile, check_finite

GROUP = "imaging"
GRID = ("grid_lateral_mm", "grid_depth_mm")
#: the frames' HDF5 filter: gzip (any HDF5 reader has it) after the byte shuffle, one chunk per frame
FRAME_COMPRESSION = {"compression": "gzip", "compression_opts": 4, "shuffle": True}


class ImagingMismatch(ValueError):
    """A target's imaging does not fit the run's /imaging: another grid, probe pose or setting."""


def sensor_of(h5: h5py.File) -> str:
    """The sensor a stored run's loop saw the target with: "ultrasound" with /imaging, else "camera"."""
    return "ultrasound" if GROUP in h5 else "camera"


def imaging_targets(h5: h5py.File) -> list[str]:
    """The targets /imaging holds, in the file's order."""
    g = h5.get(GROUP)
    return [] if g is None else [name for name, obj in g.items() if isinstance(obj, h5py.Group)]


def check_record(record: ImagingRecord) -> tuple[int, int, int]:
    """(K, H, W) of a record whose arrays fit together; ValueError naming the first array that does not."""
    W, H = np.size(record.grid_lateral_mm), np.size(record.grid_depth_mm)
    frames = np.asarray(record.frames)
    if np.ndim(record.grid_lateral_mm) != 1 or np.ndim(record.grid_depth_mm) != 1 or W < 2 or H < 2:
        raise ValueError(f"imaging {record.target}: the grid must be two 1-D arrays of at least 2 points, got "
                         f"{np.shape(record.grid_lateral_mm)} lateral, {np.shape(record.grid_depth_mm)} depth")
    if frames.ndim != 3 or frames.shape[1:] != (H, W) or frames.shape[0] < 1:
        raise ValueError(f"imaging {record.target}: frames must be (K, H, W) = (K, {H}, {W}), got {frames.shape}")
    K = frames.shape[0]
    d = 3 if np.size(record.probe_position_mm) == 3 else 2  # a body's record is in 3-D (its pose has a lateral)
    expected = {"tracked": (K, d), "true": (K, d), "needle_entry": (d,), "needle_direction": (d,),
                "desired": (d,), "probe_position_mm": (d,), "probe_axis": (d,)}
    if d == 3 and np.shape(record.attrs.get("lateral_axis")) != (3,):
        raise ValueError(f"imaging {record.target}: a body's record needs attrs['lateral_axis'] (3,)")
    for name, shape in expected.items():
        if np.shape(getattr(record, name)) != shape:
            raise ValueError(f"imaging {record.target}: {name} must be {shape}, got {np.shape(getattr(record, name))}")
    strokes = np.shape(record.strokes)
    if len(strokes) != 2 or strokes[0] != K:
        raise ValueError(f"imaging {record.target}: strokes must be (K, C) with K = {K}, got {strokes}")
    return K, H, W


def flat_attrs(attrs: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """`attrs` as HDF5 attributes: a nested mapping or dataclass becomes `key_field` entries; None is refused."""
    out: dict[str, Any] = {}
    for key, value in attrs.items():
        name = f"{prefix}{key}"
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
        if isinstance(value, Mapping):
            out.update(flat_attrs(value, f"{name}_"))
        elif value is None:
            raise ValueError(f"/imaging attribute {name!r} is None: leave it out or give its value")
        else:
            out[name] = value
    return out


def _same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype.kind in "OSU" or b.dtype.kind in "OSU":
        return a.shape == b.shape and all(str(x) == str(y) for x, y in zip(a.ravel().tolist(), b.ravel().tolist()))
    return a.shape == b.shape and bool(np.array_equal(a, b))


def run_attrs(record: ImagingRecord) -> dict[str, Any]:
    """The /imaging attributes a record asks for: its `attrs`, flat, with the probe's `position_mm` and `axis`."""
    attrs = flat_attrs(record.attrs)
    pose = {"position_mm": np.asarray(record.probe_position_mm, float), "axis": np.asarray(record.probe_axis, float)}
    for key, value in pose.items():
        if key in attrs and not _same(attrs[key], value):
            raise ImagingMismatch(f"imaging {record.target}: attrs[{key!r}] = {attrs[key]!r} is not the record's "
                                  f"probe pose {value.tolist()}")
    return attrs | pose


def _write_shared(out: ResultsFile, record: ImagingRecord) -> None:
    """The grid and the /imaging attrs: written by the first target, the same for every later one."""
    grid = {GRID[0]: np.asarray(record.grid_lateral_mm, float), GRID[1]: np.asarray(record.grid_depth_mm, float)}
    attrs = run_attrs(record)
    for name in attrs:
        check_finite(f"/{GROUP}@{name}", attrs[name])
    stored = [t for t in imaging_targets(out.h5) if t != record.target]
    if stored:  # (the same target alone, written again by a resumed run, replaces what it wrote)
        for name, values in grid.items():
            have = out.h5[f"{GROUP}/{name}"][()]
            if not _same(have, values):
                raise ImagingMismatch(
                    f"imaging {record.target}: its grid /{GROUP}/{name} ({values.size} points, {values[0]:.4g} … "
                    f"{values[-1]:.4g} mm) differs from the one stored with {', '.join(stored)} "
                    f"({have.size} points, {have[0]:.4g} … {have[-1]:.4g} mm); /imaging holds one grid per run")
        have_attrs = out.h5[GROUP].attrs
        for name, value in attrs.items():
            if name not in have_attrs or not _same(have_attrs[name], value):
                was = have_attrs.get(name, "(absent)")
                raise ImagingMismatch(f"imaging {record.target}: /{GROUP} attribute {name!r} = {value!r} differs "
                                      f"from {was!r} stored with {', '.join(stored)}; the attributes are the run's")
    out.dataset(f"{GROUP}/{GRID[0]}", grid[GRID[0]], "mm",
                description="pixel centres across the beam: along the probe's axis turned +90 degrees")
    out.dataset(f"{GROUP}/{GRID[1]}", grid[GRID[1]], "mm",
                description="pixel centres along the beam: the scanner's apparent depth "
                            "(echo time x assumed speed / 2)")
    out.attrs(GROUP, attrs)


def write_imaging(out: ResultsFile, record: ImagingRecord, cup_names: list[str] | None = None) -> None:
    """One target's `ImagingRecord` at /imaging/<target> (and the shared grid and attrs; see the module docstring).

    cup_names: the strokes' columns (C,), stored as their `columns` attr when given.
    Raises ValueError on arrays that do not fit, `ImagingMismatch` on a grid or
    attrs unlike the stored ones, NonFiniteError on NaN or infinity (nothing of
    the target is written then).
    """
    K, H, W = check_record(record)
    frames = np.ascontiguousarray(record.frames, dtype=np.float32)
    check_finite(f"/{GROUP}/{record.target}/frames", frames)
    base = f"{GROUP}/{record.target}"
    paths = {"tracked": np.asarray(record.tracked, float), "true": np.asarray(record.true, float),
             "strokes": np.asarray(record.strokes, float)}
    for name, values in paths.items():
        check_finite(f"/{base}/{name}", values)
    line = {"needle_entry": np.asarray(record.needle_entry, float),
            "needle_direction": np.asarray(record.needle_direction, float),
            "desired": np.asarray(record.desired, float)}
    for name, values in line.items():
        check_finite(f"/{base}@{name}", values)
    _write_shared(out, record)
    if base in out.h5:  # a resumed run redoing this target's manipulation
        del out.h5[base]
    out.h5.create_dataset(f"{base}/frames", data=frames, chunks=(1, H, W), **FRAME_COMPRESSION)
    out.attrs(f"{base}/frames", {"units": "1", "description": "envelope per frame (K, H, W), linear, before log "
                                 "compression; rows: grid_depth_mm, columns: grid_lateral_mm; arbitrary scale"})
    columns = ["x", "y", "z"][:paths["tracked"].shape[1]]
    out.dataset(f"{base}/tracked", paths["tracked"], "mm", columns=columns,
                description="the lesion's position the tracking reports per frame, in the scene's frame (a body: "
                            "at the plan's elevation, which one image plane does not see)")
    out.dataset(f"{base}/true", paths["true"], "mm", columns=columns,
                description="the true target per frame, in the scene's frame (the layer: in-plane)")
    named = cup_names is not None and len(cup_names) == paths["strokes"].shape[1]
    strokes_attrs = {"columns": list(cup_names)} if named else {}
    out.dataset(f"{base}/strokes", paths["strokes"], "mm", description="cup strokes per frame", **strokes_attrs)
    out.attrs(base, line | {"frames": K, "units": "mm"})


def read_imaging(h5: h5py.File) -> dict[str, ImagingRecord]:
    """Every target's record as `write_imaging` stored it ({} without /imaging); attrs are the /imaging attrs."""
    if GROUP not in h5:
        return {}
    g = h5[GROUP]
    attrs = dict(g.attrs)
    lateral, depth = g[GRID[0]][()], g[GRID[1]][()]
    records = {}
    for name in imaging_targets(h5):
        t = g[name]
        records[name] = ImagingRecord(
            target=name, grid_lateral_mm=lateral, grid_depth_mm=depth, frames=t["frames"][()],
            tracked=t["tracked"][()], true=t["true"][()], strokes=t["strokes"][()],
            needle_entry=np.asarray(t.attrs["needle_entry"], float),
            needle_direction=np.asarray(t.attrs["needle_direction"], float),
            desired=np.asarray(t.attrs["desired"], float),
            probe_position_mm=np.asarray(attrs["position_mm"], float), probe_axis=np.asarray(attrs["axis"], float),
            attrs=attrs,
        )
    return records
