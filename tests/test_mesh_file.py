"""A pinned mesh (`tissue.mesh.file`): read from .npz or a run's results.h5, checked as config, used as it is."""

from __future__ import annotations

import subprocess
import sys

import h5py
import numpy as np
import pytest
import yaml

from scissor_cli import geometry
from scissor_cli.config import ConfigError, load_config, parse_config
from scissor_cli.experiments.build import build_model

from helpers import deep_update, example_dict, write_scene


@pytest.fixture(scope="module")
def example_mesh():
    return build_model(parse_config(yaml.safe_dump(example_dict())))[1]


def _scene_with_mesh(tmp_path, file, **updates) -> dict:
    data = deep_update(example_dict(), "tissue.mesh.file", str(file))
    for key, value in updates.items():
        deep_update(data, key.replace("__", "."), value)
    return data


def test_npz_and_results_h5_give_the_same_mesh(tmp_path, example_mesh):
    np.savez(tmp_path / "m.npz", nodes=example_mesh.nodes, triangles=example_mesh.triangles)
    with h5py.File(tmp_path / "results.h5", "w") as h5:
        h5["mesh/nodes"], h5["mesh/triangles"] = example_mesh.nodes, example_mesh.triangles
    for name in ("m.npz", "results.h5"):
        # relative to the config file's folder, whatever the working directory
        path = write_scene(tmp_path, _scene_with_mesh(tmp_path, name), name=f"scene_{name}.yaml")
        cfg = load_config(path)
        assert cfg.tissue.mesh.file == str(tmp_path / name)
        mesh = build_model(cfg)[1]
        assert np.array_equal(mesh.nodes, example_mesh.nodes)
        assert np.array_equal(mesh.triangles, example_mesh.triangles)
        assert np.array_equal(mesh.element_obstacle, example_mesh.element_obstacle)
        assert np.array_equal(mesh.boundary_edges, example_mesh.boundary_edges)


def test_clockwise_triangles_are_turned(tmp_path, example_mesh):
    np.savez(tmp_path / "cw.npz", nodes=example_mesh.nodes, triangles=example_mesh.triangles[:, [0, 2, 1]])
    mesh = build_model(load_config(write_scene(tmp_path, _scene_with_mesh(tmp_path, "cw.npz"))))[1]
    p = mesh.nodes[mesh.triangles]
    assert np.all(geometry.cross2(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]) > 0)


def _bad_files(tmp_path, mesh):
    n, t = mesh.nodes, mesh.triangles
    (tmp_path / "garbage.npz").write_bytes(b"\x00\x01 not a zip file")
    (tmp_path / "text.h5").write_text("hello")
    np.savez(tmp_path / "nokeys.npz", points=n)
    np.savez(tmp_path / "nan.npz", nodes=np.where(np.arange(len(n))[:, None] == 3, np.nan, n), triangles=t)
    np.savez(tmp_path / "index.npz", nodes=n, triangles=np.where(t == t.max(), len(n) + 5, t))
    np.savez(tmp_path / "float.npz", nodes=n, triangles=t.astype(float))
    np.savez(tmp_path / "flat.npz", nodes=n, triangles=np.vstack([t, [[0, 0, 1]]]))
    np.savez(tmp_path / "shape.npz", nodes=n[:, :1], triangles=t)
    np.savez(tmp_path / "half.npz", nodes=n, triangles=t[: len(t) // 2])
    np.savez(tmp_path / "objects.npz", nodes=np.array([None, 1], dtype=object), triangles=t)
    return {
        "missing.npz": "cannot read", "scene.txt": "a mesh file is .npz", "garbage.npz": "cannot read",
        "text.h5": "cannot read", "nokeys.npz": "'nodes' and 'triangles'", "nan.npz": "finite",
        "index.npz": "must index nodes", "float.npz": "node indices", "flat.npz": "no area",
        "shape.npz": "(N, 2)", "half.npz": "not a mesh of this layer", "objects.npz": "cannot read",
    }


def test_bad_mesh_files_are_config_errors(tmp_path, example_mesh):
    for name, words in _bad_files(tmp_path, example_mesh).items():
        with pytest.raises(ConfigError) as info:
            load_config(write_scene(tmp_path, _scene_with_mesh(tmp_path, name)))
        message = str(info.value)
        assert "tissue.mesh.file" in message and name in message and words in message, (name, message)


def test_a_mesh_file_excludes_accuracy_selection_and_scale(tmp_path, example_mesh):
    np.savez(tmp_path / "m.npz", nodes=example_mesh.nodes, triangles=example_mesh.triangles)
    for key, value, words in (("solver__accuracy_mm", 0.1, "give one of the two"),
                              ("tissue__mesh__scale", 2.0, "scale must be 1")):
        with pytest.raises(ConfigError, match=words):
            load_config(write_scene(tmp_path, _scene_with_mesh(tmp_path, "m.npz", **{key: value})))


def test_cli_exit_2_names_file_and_field(tmp_path):
    path = write_scene(tmp_path, _scene_with_mesh(tmp_path, "nowhere.npz"))
    proc = subprocess.run([sys.executable, "-m", "scissor_cli", "validate", str(path)], capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert str(path) in proc.stderr and "tissue.mesh.file" in proc.stderr and "nowhere.npz" in proc.stderr
