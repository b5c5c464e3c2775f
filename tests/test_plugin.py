"""Controllers from outside (docs/model.md §22): `controller.law: python`, the drives, the API's loop."""

import textwrap

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import scissor_cli
from scissor_cli import control
from scissor_cli.config import ConfigError, parse_config

from helpers import deep_update, example_dict, write_scene
from test_cli import run_cli

CONTROLLERS = textwrap.dedent('''
    import numpy as np

    class Proportional:
        """A fraction of the least-squares stroke that cancels the measured miss, per frame."""

        def __init__(self, gain=0.5):
            self.gain = gain
            self.frames = 0

        def reset(self, observation, info):
            self.frames = 0

        def act(self, observation, info):
            self.frames += 1
            e = observation["desired_mm"] - observation["measured_mm"]
            n = observation["direction"]
            e = e - n * (n @ e)
            return self.gain * np.linalg.lstsq(info["jacobian"], e, rcond=None)[0] / info["dt_s"]

    class Raises:
        def reset(self, observation, info):
            pass

        def act(self, observation, info):
            raise RuntimeError("the controller gave up")

    class NotANumber(Raises):
        def act(self, observation, info):
            return [float("nan")]

    class NoAct:
        def reset(self, observation, info):
            pass
''')


def plugin_scene(tmp_path, class_name="Proportional", **changes):
    (tmp_path / "my_control.py").write_text(CONTROLLERS)
    data = example_dict()
    deep_update(data, "tissue.mesh.max_edge_mm", 8.0)
    deep_update(data, "tissue.mesh.min_edge_mm", 2.0)
    deep_update(data, "solver.kind", "newton")
    data["controller"].update({"law": "python", "class_path": f"my_control:{class_name}"})
    for k, v in changes.items():
        deep_update(data, k, v)
    return write_scene(tmp_path, data)


@pytest.mark.parametrize("class_path, init_args, field, words", [
    ("my_control:Missing", {}, "class_path", "no class 'Missing'"),
    ("no_such_module:Controller", {}, "class_path", "cannot import 'no_such_module'"),
    ("my_control:NoAct", {}, "class_path", "no method act"),
    ("my_control:Proportional", {"gian": 0.5}, "init_args", "gian"),
])
def test_a_class_that_cannot_be_had_is_a_bad_config(tmp_path, class_path, init_args, field, words):
    scene = plugin_scene(tmp_path)
    text = scene.read_text().replace("my_control:Proportional", class_path)
    if init_args:
        text = text.replace("class_path:", f"init_args: {init_args}\n  class_path:")
    scene.write_text(text)
    with pytest.raises(ConfigError) as exc:
        parse_config(text, str(scene), base_dir=tmp_path)
    assert f"controller.{field}" in str(exc.value) and words in str(exc.value)
    if field == "init_args":  # the CLI's exit code and message, once (the same ConfigError path for all)
        proc = run_cli("validate", scene)
        assert proc.returncode == 2 and f"controller.{field}" in proc.stderr and "Traceback" not in proc.stderr


def test_class_fields_belong_to_law_python(tmp_path):
    data = example_dict()
    data["controller"]["class_path"] = "my_control:Proportional"
    with pytest.raises(ConfigError, match="controller.class_path.*only used with law 'python'"):
        parse_config(write_scene(tmp_path, data).read_text(), "scene.yaml", base_dir=tmp_path)
    data["controller"].update({"law": "python", "class_path": "not a path"})
    with pytest.raises(ConfigError, match="package.module:Class"):
        parse_config(write_scene(tmp_path, data).read_text(), "scene.yaml", base_dir=tmp_path)


def test_a_users_controller_runs_through_simulate_trials(tmp_path):
    """Two worker processes import the class from the scene's folder; its trials are stored like the built-in's,
    with the drives' clipping in the history, and are the API's trials of the same config and seed."""
    scene = plugin_scene(tmp_path, **{"controller.init_args": {"gain": 0.6}})
    proc = run_cli("simulate", scene, "--trials", "2", "--jobs", "2", "--out", tmp_path / "out", "--quiet", cwd="/")
    assert proc.returncode == 0, proc.stderr
    cfg = scissor_cli.load_config(scene)
    tasks = {t.name: t for t in scissor_cli.tasks(cfg, scissor_cli.build_tissue(cfg),
                                                   scissor_cli.plan(cfg, scissor_cli.build_tissue(cfg)))}
    with h5py.File(tmp_path / "out" / "results.h5") as f:
        assert f.attrs["status"] == "complete"
        assert f["trials"].attrs["controller_law"] == "python"
        assert f["trials"].attrs["controller_class"] == "my_control:Proportional"
        assert set(tasks) == {name for name in f["trials"] if "failed" in f[f"trials/{name}"]}
        for name, task in tasks.items():
            t = f[f"trials/{name}"]
            assert not t["failed"][:].any() and t["done"][:].all()
            assert set(t["stop_reason"].asstr()[:]) <= {"tolerance", "stalled", "stroke_limit", "max_iterations"}
            history = t["history/1"]
            columns = list(history.attrs["columns"])
            assert columns[-1] == "clipped" and np.all(history[:, -1] >= 0)
            again = scissor_cli.manipulate(cfg, task, trial=1)  # in this process, the class from the config
            np.testing.assert_array_equal(history[:], again.history_table()[1])


def test_a_class_that_raises_fails_only_its_trials(tmp_path):
    scene = plugin_scene(tmp_path, "NotANumber")
    cfg = scissor_cli.load_config(scene)
    tissue = scissor_cli.build_tissue(cfg)
    result = scissor_cli.manipulate(cfg, scissor_cli.tasks(cfg, tissue, scissor_cli.plan(cfg, tissue))[0])
    assert result.stop_reason == "controller_failed" and "non-finite" in result.message
    for name, words in (("Raises", "the controller gave up"),):
        scene = plugin_scene(tmp_path, name)
        proc = run_cli("simulate", scene, "--trials", "2", "--jobs", "1", "--out", tmp_path / name, "--quiet")
        assert proc.returncode == 0, proc.stderr
        with h5py.File(tmp_path / name / "results.h5") as f:
            assert f.attrs["status"] == "complete"
            t = f["trials/T1"]
            assert t["failed"][:].all() and t["done"][:].all()
            assert set(t["stop_reason"].asstr()[:]) == {"controller_failed"}
            assert words in t["message"].asstr()[0]
            assert f["manipulation/T1"].attrs["closed_stop_reason"] == "controller_failed"


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 4).flatmap(lambda c: st.tuples(
    st.lists(st.floats(-1e6, 1e6), min_size=c, max_size=c),
    st.lists(st.floats(-20, 20), min_size=c, max_size=c),
    st.lists(st.floats(0.01, 50), min_size=c, max_size=c),
    st.sampled_from([0.0, 0.01, 0.1]))))
def test_the_drives_hold_speed_and_strokes(case):
    velocity, strokes, speed, resolution = (np.array(v, float) if isinstance(v, list) else v for v in case)
    lo, hi, dt = np.full(len(velocity), -15.0), np.full(len(velocity), 15.0), 0.1
    strokes = np.clip(strokes, lo, hi)
    moved = control.drive(strokes, velocity, dt, lo, hi, speed, resolution)
    assert np.all(moved.command >= lo - 1e-12) and np.all(moved.command <= hi + 1e-12)
    assert np.all(np.abs(moved.command - strokes) <= speed * dt + resolution + 1e-9)
    fast = np.abs(velocity) > speed
    assert moved.clipped >= np.count_nonzero(fast)


def test_the_builtin_law_as_a_plugin_commands_what_the_loop_does():
    """PIDLaw through the plug-in path gives the built-in loop's commands while the PID stays within one
    frame's travel (the built-in loop lets a longer move take longer; the plug-in path holds the speed)."""
    cfg = scissor_cli.load_config(scissor_cli.api.__file__.replace("api.py", "scenes/example.yaml"))
    cups = [c.model_copy(update={"speed_mm_per_s": 50.0}) for c in cfg.cups]
    cfg = cfg.model_copy(update={"cups": cups})
    tissue = scissor_cli.build_tissue(cfg)
    task = scissor_cli.tasks(cfg, tissue, scissor_cli.plan(cfg, tissue))[0]
    builtin = scissor_cli.manipulate(cfg, task)
    plugin = scissor_cli.manipulate(cfg, task, controller=control.PIDLaw(cfg.controller.kp,
                                                                                  cfg.controller.ki))
    assert builtin.stop_reason == plugin.stop_reason == "tolerance"
    np.testing.assert_allclose(plugin.hist_strokes_cmd, builtin.hist_strokes_cmd, atol=1e-9)
    assert not plugin.hist_clipped.any()
