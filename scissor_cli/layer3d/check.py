"""The layer check: the 3-D slab against the 2-D layer, per forward case (docs/model.md §13).

For each forward case the slab is solved with the case's strokes (the one
Newton solver, `solvers.equilibrium`) and compared with the 2-D layer's
equilibrium (plane strain, the model the paper uses):

* the 3-D deformed targets (K, 3) mm; their in-plane displacement against
  the layer's (largest difference over the targets, in mm and as a
  fraction of the layer's largest target displacement), and the largest
  out-of-plane displacement;
* which 2-D assumption the slab is closer to. Plane strain is the layer.
  Plane stress is solved as the slab of one prism layer, as thick as the
  layer (`tissue.thickness_mm`), with free faces (no chest wall, the cup
  gripping its whole height but not holding z): the same energy and mesh,
  no separate plane-stress energy to keep in step with §3. For the linear
  model this one-element slab is within 5 % of the closed-form plane
  stress (E* = E(1+2ν)/(1+ν)², ν* = ν/(1+ν); tests/test_slab.py).

Without targets the comparison runs over every node of the layer's level.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from scissor_cli.config import LayerCheckConfig, MeshConfig
from scissor_cli.layer3d.resolution import IN_PLANE_SCALES
from scissor_cli.layer3d.slab import SlabProbe, SlabSpec, build_slab, layer_probe, slab_probe
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import TargetProbe, probe_targets, target_positions
from scissor_cli.solvers.common import SolveResult
from scissor_cli.solvers.equilibrium import EquilibriumSolver

CLOSER = ("plane_strain", "plane_stress")


@dataclass(frozen=True)
class LayerCheckCase:
    """The check of one forward case; positions in mm."""

    name: str
    displacement: np.ndarray  # (N3, 3) mm, the slab's equilibrium minus rest
    targets: dict  # name -> (3,) mm, deformed 3-D target
    targets_2d: dict  # name -> (2,) mm, the layer's deformed target (plane strain)
    targets_stress: dict  # name -> (2,) mm, the plane-stress slab's
    in_plane_diff_mm: float
    in_plane_diff_fraction: float
    plane_stress_diff_mm: float
    out_of_plane_mm: float
    closer_to: str
    time_s: float
    iterations: int
    layer_nodes: np.ndarray  # (N2, 3) mm, the slab at the layer's nodes (figure): `slab.layer_probe`


@dataclass
class LayerCheck:
    """The slab of a scene and its plane-stress companion, built once for every forward case."""

    tissue: Tissue  # the 2-D layer
    slab: Tissue
    stress: Tissue
    probe: SlabProbe
    probe_stress: SlabProbe
    probe_2d: TargetProbe
    names: list
    layer: SlabProbe  # the layer's nodes in the slab

    @property
    def mesh(self):
        return self.slab.mesh

    def run_case(self, name: str, strokes: np.ndarray, layer_result: SolveResult) -> LayerCheckCase:
        """Solve the slab and the plane-stress slab for strokes (C,) mm; compare with the layer's result."""
        t0 = time.perf_counter()
        strokes = np.asarray(strokes, float)
        r3 = EquilibriumSolver(self.slab, "newton").solve(strokes)
        elapsed = time.perf_counter() - t0
        rs = EquilibriumSolver(self.stress, "newton").solve(strokes)
        p3 = self.probe.positions(r3.x)
        rest3 = self.probe.positions(self.slab.rest)
        p2 = target_positions(self.probe_2d, layer_result.x)
        rest2 = target_positions(self.probe_2d, self.tissue.rest)
        ps = self.probe_stress.positions(rs.x)[:, :2]
        u3 = p3 - rest3
        u2 = p2 - rest2
        diff = np.linalg.norm(u3[:, :2] - u2, axis=1)
        diff_stress = np.linalg.norm(p3[:, :2] - ps, axis=1)
        scale = float(np.linalg.norm(u2, axis=1).max(initial=0.0))
        in_plane = float(diff.max(initial=0.0))
        stress_diff = float(diff_stress.max(initial=0.0))
        layer_nodes = self.layer.positions(r3.x)
        names = self.names
        return LayerCheckCase(
            name=name,
            displacement=r3.x - self.slab.rest,
            targets={n: p3[k] for k, n in enumerate(names)},
            targets_2d={n: p2[k] for k, n in enumerate(names)},
            targets_stress={n: ps[k] for k, n in enumerate(names)},
            in_plane_diff_mm=in_plane,
            in_plane_diff_fraction=in_plane / scale if scale > 0 else 0.0,
            plane_stress_diff_mm=stress_diff,
            out_of_plane_mm=float(np.abs(u3[:, 2]).max(initial=0.0)),
            closer_to=CLOSER[0] if in_plane <= stress_diff else CLOSER[1],
            time_s=elapsed,
            iterations=int(r3.iterations),
            layer_nodes=layer_nodes,
        )


def plane_spec(mesh: MeshConfig, in_plane_scale: float) -> tuple | None:
    """`SlabSpec.plane` at an in-plane scale: the `tissue.mesh` section's edge lengths times it (None at 1: the
    layer's own mesh)."""
    if in_plane_scale == 1.0:
        return None
    m = mesh
    s = float(m.scale) * float(in_plane_scale)
    return (float(m.min_edge_mm) * s, float(m.max_edge_mm) * s, float(m.min_angle_deg), float(m.grading),
            bool(m.graded))


def plane_ladder(section: LayerCheckConfig, mesh: MeshConfig) -> list[tuple[float, tuple | None]]:
    """The in-plane candidates of `layer_check.accuracy_mm`: (in_plane_scale, `SlabSpec.plane`), the configured
    scale first (`resolution.IN_PLANE_SCALES` times it, at most the config's bound of 10)."""
    base = float(section.in_plane_scale)
    scales = dict.fromkeys(min(base * f, 10.0) for f in IN_PLANE_SCALES)
    return [(s, plane_spec(mesh, s)) for s in scales]


def slab_spec(section: LayerCheckConfig, mesh: MeshConfig) -> SlabSpec:
    """The slab spec of the `layer_check` section (its plane from the `tissue.mesh` section)."""
    first = None if section.first_layer_mm is None else float(section.first_layer_mm)
    return SlabSpec(float(section.height_mm), float(section.layer_z_mm), bool(section.chest_wall_fixed),
                    bool(section.cup_holds_z), float(section.max_layer_mm), first,
                    plane=plane_spec(mesh, float(section.in_plane_scale)))


def stress_spec(tissue: Tissue) -> SlabSpec:
    """The plane-stress companion: one prism layer as thick as the layer, free faces."""
    h = float(tissue.scene.thickness_mm)
    return SlabSpec(h, 0.5 * h, chest_wall_fixed=False, cup_holds_z=False, max_layer_mm=h,
                    grip_full_height=True, levels_mm=(0.0, h))


def build_layer_check(tissue: Tissue, spec: SlabSpec) -> LayerCheck:
    """The slab of a 2-D tissue (its scene, mesh and material model) and its plane-stress companion."""
    scene, mesh = tissue.scene, tissue.mesh
    model = tissue.params.model
    slab = build_slab(scene, mesh, spec, model=model, element=tissue.element.name)
    stress = build_slab(scene, mesh, stress_spec(tissue), model=model, element=tissue.element.name)
    if len(scene.targets):
        names = [t.name for t in scene.targets]
        points = np.array([t.rest for t in scene.targets])
        probe_2d = probe_targets(mesh, points)
        probe, probe_stress = slab_probe(slab, points), slab_probe(stress, points)
    else:  # every node of the layer: vertex v as the point, weight 1
        names = []
        n = mesh.n_nodes
        tri = np.zeros(n, np.int64)
        probe_2d = TargetProbe(tri, np.column_stack([np.arange(n)] * 3),
                               np.column_stack([np.ones(n), np.zeros(n), np.zeros(n)]))
        probe, probe_stress = layer_probe(slab, mesh), layer_probe(stress, mesh)
    return LayerCheck(tissue, slab, stress, probe, probe_stress, probe_2d, names, layer_probe(slab, mesh))
