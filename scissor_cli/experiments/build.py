"""From a validated config to what the layers below take: each gets the sections it uses, nothing more.

The whole `Config` stops here; the scene, the mesher, the slab and the
planner are given their sections (or the plain data made from them).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scissor_cli.config import Config
from scissor_cli.config.body_section import SectionPlane, section_config
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.mechanics.body_tissue import build_body
from scissor_cli.mechanics.tissue import Tissue, build_tissue
from scissor_cli.mesh.body_inputs import mesh_body
from scissor_cli.mesh.mesh import Mesh, mesh_for_config
from scissor_cli.mesh.probe import TargetProbe, probe_targets
from scissor_cli.scene.body_scene import BodyScene, build_body_scene
from scissor_cli.scene.scene import Scene, build_scene


def scene_of(cfg: Config) -> Scene:
    """The scene of a validated config (`scene.build_scene` on its scene sections)."""
    return build_scene(cfg.name, cfg.tissue, cfg.material, cfg.cups, cfg.targets, cfg.obstacles)


def build_model(cfg: Config, model: str | None = None, mesh_scale: float | None = None) -> tuple[Scene, Mesh, Tissue]:
    """Scene, mesh and tissue of a validated config; `model` and `mesh_scale` override the config's."""
    scene = scene_of(cfg)
    mesh = mesh_for_config(scene, cfg.tissue.mesh, scale=mesh_scale)
    return scene, mesh, build_tissue(scene, mesh, model=model, element=cfg.tissue.mesh.element)


def with_grips(cfg: Config | BodyConfig, contacts: np.ndarray, axes: np.ndarray) -> Config | BodyConfig:
    """The config (a layer's or a body's) with the first len(contacts) cups' contact_mm (k, d) and axis (k, d)
    replaced (radius, stroke, speed stay)."""
    cups = list(cfg.cups)
    for i, (p, a) in enumerate(zip(contacts, axes)):
        cups[i] = cups[i].model_copy(update={"contact_mm": [float(v) for v in p],
                                             "axis": [float(v) + 0.0 for v in a]})
    return cfg.model_copy(update={"cups": cups})


def body_model(cfg: BodyConfig, cache: Path | None = None, scale: float = 1.0,
               model: str | None = None) -> tuple[BodyScene, object, Tissue]:
    """Scene, mesh (`mesh.body_mesh.BodyMesh`) and tissue of a validated 3-D config at a mesh scale."""
    scene = build_body_scene(cfg)
    mesh = mesh_body(scene, cfg.tissue.mesh, scale, cache)
    return scene, mesh, build_body(scene, mesh, model=model, element=cfg.tissue.mesh.element)


def section_model(cfg: BodyConfig, index: int) -> tuple[Tissue, TargetProbe, SectionPlane]:
    """The paper's layer on a 3-D scene's section through target `index` (`config.body_section`): its tissue,
    the probe of its one target and the section's plane."""
    layer, plane = section_config(cfg, index)
    _, mesh, tissue = build_model(layer)
    return tissue, probe_targets(mesh, np.asarray(layer.targets[0].position_mm, float)[None]), plane
