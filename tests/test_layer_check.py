"""The layer check (docs/model.md §13, docs/contract.md): config, exit 2 on bad input, the run's
/layer_check group, figure and report column."""

import subprocess
import sys

import h5py
import numpy as np
import pytest
import yaml

from scissor_cli.config import ConfigError, parse_config
from scissor_cli.experiments.build import build_model
from tests.helpers import cli_here, example_dict, simulate_here, write_scene

from figure_checks import assert_png_drawn

#: the slab as set (accuracy_mm null pins it: the tests here are not about its choice)
SPEC = {"height_mm": 40.0, "layer_z_mm": 20.0, "chest_wall_fixed": True, "cup_holds_z": True, "max_layer_mm": 5.0,
        "accuracy_mm": None}


def _cli(*args, cwd=None):
    import os
    env = dict(os.environ)
    return subprocess.run([sys.executable, "-m", "scissor_cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=600)


def test_full_example_section_validates():
    data = example_dict() | {"layer_check": dict(SPEC)}
    cfg = parse_config(yaml.safe_dump(data), "scene.yaml")
    assert cfg.layer_check.height_mm == 40.0 and cfg.trials.truth == "layer"


@pytest.mark.parametrize("change, words", [
    ({"layer_z_mm": 45.0}, ["layer_check.layer_z_mm", "inside the slab"]),
    ({"height_mm": 0.5, "layer_z_mm": 0.2}, ["layer_check.height_mm", "too thin for one prism layer"]),
    ({"height_mm": 400.0, "max_layer_mm": 0.1}, ["layer_check", "tetrahedra", "budget"]),
    ({"layer_z_mm": -1.0}, ["layer_check.layer_z_mm"]),
    ({"in_plane_scale": 0.5}, ["layer_check.in_plane_scale"]),
    ({"in_plane_scale": float("nan")}, ["layer_check.in_plane_scale"]),
])
def test_bad_slab_exits_2(tmp_path, change, words):
    data = example_dict() | {"layer_check": dict(SPEC) | change}
    path = write_scene(tmp_path, data)
    r = _cli("validate", path)
    assert r.returncode == 2, r.stderr
    lines = [line for line in r.stderr.strip().splitlines() if line.strip()]
    assert "scene.yaml" in r.stderr and "line" in r.stderr
    for w in words:
        assert w in r.stderr, r.stderr
    assert len(lines) <= 3


def test_truth_slab_needs_layer_check():
    data = example_dict()
    data.setdefault("trials", {})["truth"] = "slab"
    with pytest.raises(ConfigError, match="layer_check"):
        parse_config(yaml.safe_dump(data), "scene.yaml")


def small_scene(tmp_path):
    data = example_dict()
    data["tissue"]["mesh"]["scale"] = 4.0
    data["solver"]["kind"] = "newton"
    data["layer_check"] = {"height_mm": 8.0, "layer_z_mm": 4.0, "chest_wall_fixed": True, "cup_holds_z": True,
                           "max_layer_mm": 4.0, "accuracy_mm": None}
    data["forward"] = [{"name": "push4", "strokes": {"cup": 4.0}}]
    return write_scene(tmp_path, data)


def test_run_writes_layer_check(tmp_path):
    data = yaml.safe_load(small_scene(tmp_path).read_text())
    data["trials"] = dict(data.get("trials") or {}, count=0)  # (`--trials 0`, through the API in this process)
    out = simulate_here(tmp_path, data)
    with h5py.File(out / "results.h5") as f:
        nodes, tets = f["layer_check/mesh/nodes"][()], f["layer_check/mesh/tetrahedra"][()]
        assert nodes.shape[1] == 3 and tets.shape[1] == 4 and tets.dtype == np.int64
        X = nodes[tets]
        vol = np.einsum("ij,ij->i", np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), X[:, 3] - X[:, 0])
        assert np.all(vol > 0)
        case = f["layer_check/push4"]
        assert case["displacement"].shape == nodes.shape
        for name in ("T1", "T2"):
            t = case[f"targets/{name}"][()]
            assert t.shape == (3,) and np.all(np.isfinite(t))
        a = dict(case.attrs)
        assert a["closer_to"] in ("plane_strain", "plane_stress")
        assert a["in_plane_diff_mm"] >= 0 and a["out_of_plane_mm"] >= 0 and a["iterations"] > 0 and a["time_s"] > 0
        # the 2-D forward case is untouched by the check
        assert f["forward/push4/displacement"].shape[1] == 2
    assert_png_drawn(out / "layer_check_push4.png")
    rep = cli_here("report", out, "--out", tmp_path / "report")  # not the checkout's runs/
    assert rep.exit_code == 0, rep.output
    assert "layer check" in rep.stdout.lower()


@pytest.mark.slow  # (test_slab_truth_inserts_in_the_slab_nominally_and_in_trials runs slab-truth trials too)
def test_slab_truth_trials(tmp_path):
    """trials.truth: slab runs the closed loop on the 2-D model against the 3-D slab (docs/model.md §13)."""
    path = small_scene(tmp_path)
    finals = {}
    for truth in ("layer", "slab"):
        out = tmp_path / f"run_{truth}"
        r = _cli("simulate", path, "--out", out, "--trials", "1", "--jobs", "1", "--truth", truth)
        assert r.returncode == 0, r.stderr
        assert ("solved once for every trial" in r.stdout + r.stderr) == (truth == "slab")
        with h5py.File(out / "results.h5") as f:
            g = f["trials/T2"]
            assert bool(g["done"][0]) and not bool(g["failed"][0])
            finals[truth] = (g["final_error"][0], int(g["iterations"][0]))
    # the slab is another tissue: the loop sees other errors and iterates differently
    assert not np.allclose(finals["layer"][0], finals["slab"][0])
    # the nominal slab at the plan was solved once and cached beside the run; two workers read it, same numbers
    assert len(list((tmp_path / ".scissor-cache").glob("slab-start-*.npy"))) >= 1
    out = tmp_path / "run_slab_again"
    r = _cli("simulate", path, "--out", out, "--trials", "1", "--jobs", "2", "--truth", "slab")
    assert r.returncode == 0, r.stderr
    assert "solved once for every trial" not in r.stdout + r.stderr
    with h5py.File(out / "results.h5") as f:
        g = f["trials/T2"]
        assert np.array_equal(g["final_error"][0], finals["slab"][0]) and int(g["iterations"][0]) == finals["slab"][1]


def test_truth_option_needs_layer_check(tmp_path):
    data = example_dict()
    r = _cli("simulate", write_scene(tmp_path, data), "--out", tmp_path / "x", "--trials", "0", "--truth", "slab")
    assert r.returncode == 2 and "layer_check" in r.stderr


def test_slab_truth_inserts_in_the_slab_nominally_and_in_trials(tmp_path):
    """With the slab truth the nominal insertion and the trials' run in the slab, every strategy (docs/model.md
    §14): 3-D shapes in results.h5 (docs/contract.md), and export and report read them. The slab meshes its
    own, coarser plane (`in_plane_scale`): the layer's nodes in the frames are points of the slab."""
    data = yaml.safe_load(small_scene(tmp_path).read_text())
    # (2 mm steps on a slab plane twice as coarse as the layer's: the 3-D insertion's layout and readers are on
    # test here, not its fidelity; `simulate_here`: the run through the API, as `--trials 1 --truth slab` would)
    data["insertion"] = {"strategies": ["none", "depth", "loop"], "step_mm": 2.0}
    data["layer_check"]["in_plane_scale"] = 2.0
    data["trials"] = dict(data.get("trials") or {}, count=1, truth="slab")
    out = simulate_here(tmp_path, data)
    with h5py.File(out / "results.h5") as f:
        n3 = f["layer_check/mesh/nodes"].shape[0]
        levels = np.unique(f["layer_check/mesh/nodes"][:, 2]).size
        assert n3 // levels < f["mesh/nodes"].shape[0]  # the slab's plane is coarser than the layer's mesh
        for target in f["trials"]:
            g = f["trials"][target]
            assert not bool(g["failed"][0])
            miss = g["miss_mm"][()]
            assert miss.shape == (1, 3) and np.all(np.isfinite(miss)) and np.all(miss >= 0) and np.any(miss > 0)
        for strategy in ("none", "depth", "loop"):
            ins = f[f"insertion/T1/{strategy}"]
            k = ins["depth_mm"].shape[0]
            assert k > 0 and ins["tip"].shape == (k, 3) and ins["target"].shape == (k, 3)
            assert ins["displacement"].shape == (k, n3, 3) and len(ins.attrs["entry"]) == 3
            assert ins.attrs["completed"]
    assert (out / "insertion_T1.gif").exists()
    assert_png_drawn(out / "insertion_path_T1.png")
    exported = cli_here("export", out, "--out", tmp_path / "export")
    assert exported.exit_code == 0, exported.output
    assert any("insertion_T1_none" in p.name for p in (tmp_path / "export").iterdir())
    rep = cli_here("report", out, "--out", tmp_path / "report")
    assert rep.exit_code == 0, rep.output


@pytest.mark.parametrize("change, words", [
    ({"first_layer_mm": 6.0, "max_layer_mm": 4.0}, ["layer_check.first_layer_mm", "thicker than the thickest"]),
    ({"accuracy_mm": 0.0}, ["layer_check.accuracy_mm"]),
])
def test_bad_resolution_exits_2(tmp_path, change, words):
    data = example_dict() | {"layer_check": dict(SPEC) | change}
    if "accuracy_mm" in change and change["accuracy_mm"] > 0:
        data["forward"] = []
    r = _cli("validate", write_scene(tmp_path, data))
    assert r.returncode == 2, r.stderr
    for w in words:
        assert w in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_resolution_by_accuracy_goes_coarse_to_fine_and_stops_within_it():
    """choose_slab: the finest slab first, then the coarsest candidate against it; a loose accuracy takes the
    coarsest having solved only those two, a tight one goes on to the configured grading (error 0); every rung is
    coarser than the one before; the errors are those of every candidate solved against the finest, and an
    accuracy between two of them picks as the full ladder does."""
    from scissor_cli.experiments.build import build_model
    from scissor_cli.layer3d.check import slab_spec
    from scissor_cli.layer3d.resolution import choose_slab, exhaustive_errors

    data = example_dict()
    data["layer_check"] = {"height_mm": 12.0, "layer_z_mm": 6.0, "max_layer_mm": 3.0}
    cfg = parse_config(yaml.safe_dump(data), "scene.yaml")
    _, _, model = build_model(cfg, mesh_scale=4.0)
    cases = [np.array([4.0])]
    spec = slab_spec(cfg.layer_check, cfg.tissue.mesh)
    loose = choose_slab(model, spec, cases, 10.0)
    rungs = loose.candidates
    assert len(rungs) >= 3
    assert all(b.levels < a.levels and b.n_tetrahedra < a.n_tetrahedra for a, b in zip(rungs, rungs[1:]))
    assert loose.pick == len(rungs) - 1 and loose.solved == 2 and 0 < loose.chosen.error_mm <= 10.0
    assert loose.chosen.reference == 0 and loose.chosen.factor_s > 0
    tight = choose_slab(model, spec, cases, 1e-6)
    assert tight.pick == 0 and tight.chosen.error_mm == 0.0 and tight.solved == len(rungs)
    assert all(r.error_mm > 1e-6 for r in tight.candidates[1:])
    candidates, true = exhaustive_errors(model, spec, cases)
    assert true[0] == 0.0
    np.testing.assert_allclose(true[1:], [r.error_mm for r in tight.candidates[1:]], rtol=1e-9)
    for accuracy in np.sort(true[1:]):
        within = [k for k in range(len(true)) if true[k] <= accuracy]
        assert choose_slab(model, spec, cases, float(accuracy)).pick == min(
            within, key=lambda k: candidates[k].n_tetrahedra)


def test_the_ladder_on_two_workers_picks_as_one_process_does_with_the_same_numbers():
    """choose_slab with the finest slab's cases split over worker processes and the candidates solved beside them
    (`--jobs 2`): the same pick and, number for number, the same errors; the workers end with the choice."""
    import multiprocessing

    from scissor_cli.experiments.build import build_model
    from scissor_cli.experiments.layer_check_stage import ladder_runner
    from scissor_cli.layer3d.check import slab_spec
    from scissor_cli.layer3d.resolution import choose_slab, exhaustive_errors, in_process

    data = example_dict()
    data["layer_check"] = {"height_mm": 12.0, "layer_z_mm": 6.0, "max_layer_mm": 3.0}
    cfg = parse_config(yaml.safe_dump(data), "scene.yaml")
    _, _, model = build_model(cfg, mesh_scale=4.0)
    cases = [np.array([4.0]), np.array([-4.0])]
    spec = slab_spec(cfg.layer_check, cfg.tissue.mesh)
    _, true = exhaustive_errors(model, spec, cases)
    accuracy = float(np.min(true[1:]))  # the closest candidate: coarser ones are tried (and refused) first
    serial = choose_slab(model, spec, cases, accuracy, run_tasks=in_process)
    parallel = choose_slab(model, spec, cases, accuracy, run_tasks=ladder_runner(2), workers=2)
    assert serial.pick == parallel.pick != 0 and serial.solved == parallel.solved >= 3
    assert [c.error_mm for c in parallel.candidates] == [c.error_mm for c in serial.candidates]
    assert [c.n_tetrahedra for c in parallel.candidates] == [c.n_tetrahedra for c in serial.candidates]
    assert not multiprocessing.active_children()


def test_a_layer_check_without_accuracy_picks_its_slab_by_default(tmp_path):
    """Without accuracy_mm the slab is picked to 0.1 mm (validate shows the default; null pins the slab); a scene
    without forward cases is compared at each cup's strokes at two thirds of its limits."""
    from scissor_cli.experiments.layer_check_stage import ladder_cases, slab_resolution_stage

    path = small_scene(tmp_path)
    data = yaml.safe_load(path.read_text())
    del data["layer_check"]["accuracy_mm"]
    path.write_text(yaml.safe_dump(data))
    shown = _cli("validate", path)
    assert shown.returncode == 0 and "accuracy_mm: 0.1" in shown.stdout
    data["forward"] = []
    cfg = parse_config(yaml.safe_dump(data), "scene.yaml")
    assert cfg.layer_check.accuracy_mm == 0.1
    scene = build_model(cfg)[0]
    cases = ladder_cases(cfg, scene)
    limits = scene.cups[0].stroke_max_mm, scene.cups[0].stroke_min_mm
    np.testing.assert_allclose([c[0] for c in cases], [2 / 3 * v for v in limits])
    ran, choice = slab_resolution_stage(cfg)
    assert ran.layer_check.accuracy_mm is None and choice.accuracy_mm == 0.1
    assert choice.chosen.error_mm <= 0.1 and ran.layer_check.in_plane_scale == choice.chosen.in_plane_scale


def test_run_records_the_chosen_resolution(tmp_path):
    path = small_scene(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["layer_check"]["accuracy_mm"] = 10.0  # anything goes: the coarsest rung
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "run"
    r = _cli("simulate", path, "--out", out, "--trials", "0")
    assert r.returncode == 0, r.stderr
    assert "slab resolution" in r.stderr + r.stdout
    with h5py.File(out / "results.h5") as f:
        a = dict(f["layer_check_resolution"].attrs)
        ran = parse_config(str(f.attrs["config_yaml"]), "results.h5")
        levels = f["layer_check_resolution/levels"][()]
        assert a["pick"] == len(levels) - 1 and a["size_ratio"] > 1 and a["solved"] == 2
        # the recorded config is the slab that ran: the chosen grading, no accuracy left to choose again
        assert ran.layer_check.accuracy_mm is None
        assert ran.layer_check.first_layer_mm == pytest.approx(a["first_layer_mm"])
        assert ran.layer_check.max_layer_mm == pytest.approx(a["max_layer_mm"])
        assert f["layer_check/mesh/nodes"].shape[0] > 0
        first = f["layer_check_resolution/levels"][()], str(f.attrs["config_yaml"])
    # a second run of the scene reads the choice from the cache beside the runs: the same slab and record
    r = _cli("simulate", path, "--out", tmp_path / "again", "--trials", "0")
    assert r.returncode == 0, r.stderr
    assert "(from the cache)" in r.stderr + r.stdout
    with h5py.File(tmp_path / "again" / "results.h5") as f:
        assert np.array_equal(f["layer_check_resolution/levels"][()], first[0])
        assert str(f.attrs["config_yaml"]) == first[1]
