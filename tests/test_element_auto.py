"""`tissue.mesh.element: auto` (docs/model.md §21): a body's `tissue.accuracy_mm` picks the element and the mesh
together, against the element that converges."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from scissor_cli import api
from scissor_cli.config import ConfigError, parse_config
from scissor_cli.experiments.body_resolution import choose_body_scale

SCENE = {
    "name": "auto-dome",
    "tissue": {"shape": "dome", "radius_mm": 40.0, "height_mm": 25.0, "fixed": ["base"],
               "mesh": {"max_edge_mm": 8.0, "min_edge_mm": 2.5, "element": "auto"}, "accuracy_mm": 0.05},
    "material": {"model": "neo_hookean", "E_kPa": 10.0, "nu": 0.49},
    "cups": [{"name": "side", "contact_mm": [0.0, 38.5, 8.0], "radius_mm": 5.0, "stroke_mm": [-10.0, 10.0]}],
    "targets": [{"name": "T1", "position_mm": [5.0, 10.0, 10.0], "radius_mm": 3.0}],
    "needle": {"direction": [-1.0, 0.0, 0.0]},
    "solver": {"kind": "newton"},
    "forward": [{"name": "push", "strokes": {"side": 4.0}}],
    "trials": {"count": 0},
}


def _config(accuracy_mm: float, nu: float, element: str = "auto"):
    data = dict(SCENE, material=dict(SCENE["material"], nu=nu),
                tissue=dict(SCENE["tissue"], accuracy_mm=accuracy_mm, mesh=dict(SCENE["tissue"]["mesh"],
                                                                                 element=element)))
    return parse_config(yaml.safe_dump(data), "auto.yaml", Path.cwd())


def _ladder_is_sound(choice) -> None:
    """The reference is the configured mesh on nodal; the pick meets the accuracy (or is an element's configured
    mesh); every solved candidate of the picked element coarser than the pick missed it, and none finer than a
    coarser pick was solved."""
    reference, chosen = choice.candidates[0], choice.chosen
    assert (reference.element, reference.scale, reference.error_mm) == ("nodal", 1.0, 0.0)
    assert chosen.error_mm <= choice.accuracy_mm or chosen.scale == 1.0
    if choice.pick == 0:  # the configured mesh itself: every coarser nodal candidate was solved and missed
        coarser = [c for c in choice.candidates[1:] if c.element == chosen.element]
        assert coarser and all(c.solved and c.error_mm > choice.accuracy_mm for c in coarser)
        return
    ladder = [c for c in choice.candidates[choice.pick + 1:] if c.element == chosen.element]
    assert not any(c.solved for c in ladder)  # the ladder stops at the pick
    tried = [c for c in choice.candidates[1:choice.pick] if c.element == chosen.element and c.scale != 1.0]
    assert all(c.error_mm > choice.accuracy_mm for c in tried)


def test_near_incompressible_tissue_at_a_tight_accuracy_gets_the_element_that_does_not_lock():
    choice = choose_body_scale(_config(0.05, 0.49))
    _ladder_is_sound(choice)
    p1 = choice.candidates[1]
    assert (p1.element, p1.scale) == ("p1", 1.0) and p1.error_mm > 0.05  # p1 locks: tenths of a mm off
    assert choice.element == "nodal"


def test_a_loose_accuracy_gets_the_cheaper_element_on_a_coarser_mesh_and_the_api_builds_it():
    cfg = _config(1.0, 0.45)
    choice = choose_body_scale(cfg)
    _ladder_is_sound(choice)
    assert choice.element == "p1" and choice.candidates[1].error_mm <= 1.0
    assert choice.chosen.scale > 1.0
    tissue = api.build_tissue(cfg)  # as `simulate` builds it: the pick's element and mesh
    assert tissue.element.name == "p1" and tissue.mesh.n_elements == choice.chosen.n_tetrahedra


def test_a_named_element_keeps_its_own_reference():
    choice = choose_body_scale(_config(1.0, 0.45, element="p1"))
    assert {c.element for c in choice.candidates} == {"p1"} and choice.candidates[0].error_mm == 0.0


def test_auto_without_an_accuracy_is_refused_naming_the_field():
    data = dict(SCENE, tissue=dict(SCENE["tissue"], accuracy_mm=None))
    with pytest.raises(ConfigError, match=r"tissue\.mesh\.element"):
        parse_config(yaml.safe_dump(data), "auto.yaml", Path.cwd())


def test_a_layers_auto_needs_solver_accuracy():
    """A layer picks its element with §9's selection (tests/test_selection.py): without solver.accuracy_mm, exit 2
    naming both fields."""
    text = (Path(__file__).resolve().parents[1] / "configs" / "example.yaml").read_text()
    data = yaml.safe_load(text)
    data["tissue"].setdefault("mesh", {})["element"] = "auto"
    with pytest.raises(ConfigError, match=r"tissue\.mesh\.element(.|\n)*solver\.accuracy_mm"):
        parse_config(yaml.safe_dump(data), "example.yaml", Path.cwd())
