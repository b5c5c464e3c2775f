"""results.h5 of a 3-D scene: /mesh with tetrahedra and regions, /material, /cups on the skin (docs/contract.md).

The paths of a 2-D run with 3-vectors: `/mesh/nodes` (N, 3), `/mesh/tetrahedra` (M, 4) instead of
`/mesh/triangles`, `/mesh/region` (M,) and the `/mesh` attributes `regions` and `min_dihedral_deg`,
`/mesh/fiber` (M, 3), `/cups/<cup>` attributes `axis` and `contact` (3,) — the contact on the skin.
Forward cases, targets and the Jacobian use the 2-D writers (`output.results`), which take any dimension.
"""

from __future__ import annotations

import h5py
import numpy as np

from scissor_cli.output.results import ResultsFile, filled


def write_body_model(out: ResultsFile, tissue) -> None:
    """/mesh, /material, /cups of a body tissue (`mechanics.body.build_body`)."""
    mesh, scene = tissue.mesh, tissue.scene
    out.dataset("mesh/nodes", mesh.nodes, "mm")
    out.dataset("mesh/tetrahedra", mesh.tetrahedra.astype(np.int64), description="positive volume")
    out.dataset("mesh/region", mesh.region.astype(np.int64), description="index into the /mesh attribute regions")
    out.dataset("mesh/boundary_triangles", mesh.boundary_triangles.astype(np.int64), description="outward")
    out.dataset("mesh/fiber", tissue.fiber, "1")
    out.dataset("mesh/fixed_nodes", tissue.fixed_nodes.astype(np.int64))
    out.dataset("mesh/element_E_kPa", tissue.element_E_kPa, "kPa")
    out.attrs("mesh", {"n_nodes": mesh.n_nodes, "n_elements": mesh.n_elements, "regions": list(mesh.region_names),
                       "min_dihedral_deg": float(mesh.min_dihedral_deg), "shape": scene.shape,
                       "element": tissue.element.name,
                       "nodes_per_element": tissue.element.nodes_per_element})
    m = scene.material
    out.attrs("material", {
        "model": tissue.params.model, "E_kPa": m.E_kPa, "nu": m.nu, "eta_kPa": m.eta_kPa,
        "density_kg_per_mm3": m.density_kg_per_mm3, "fiber_tension_only": bool(m.tension_only),
        "fiber_angle_rad": m.fiber_angle_rad, "fibers": scene.fibers,
        "skin_thickness_mm": float(scene.skin_thickness_mm or 0.0), "skin_E_kPa": float(scene.skin_E_kPa or m.E_kPa),
    })
    for c, cup in enumerate(scene.cups):
        out.dataset(f"cups/{cup.name}/nodes", tissue.cup_nodes[c].astype(np.int64))
        out.attrs(f"cups/{cup.name}", {
            "axis": cup.axis, "contact": cup.contact, "radius_mm": cup.radius_mm,
            "stroke_range_mm": [cup.stroke_min_mm, cup.stroke_max_mm], "speed_mm_per_s": cup.speed_mm_per_s,
        })


def write_body_resolution(out: ResultsFile, choice) -> None:
    """/mesh_resolution: every candidate (mesh and element) of `tissue.accuracy_mm` (a table) and the pick
    (attributes)."""
    rows = choice.candidates
    out.dataset("mesh_resolution/scale", np.array([c.scale for c in rows]), "1")
    out.dataset("mesh_resolution/n_tetrahedra", np.array([c.n_tetrahedra for c in rows], np.int64))
    out.dataset("mesh_resolution/element", np.array([c.element for c in rows], dtype="S"))
    out.dataset("mesh_resolution/error_mm", np.array([c.error_mm for c in rows]), "mm",
                description="largest lesion distance from the reference's (row 0: the configured mesh); -1: not solved")
    out.dataset("mesh_resolution/time_s", np.array([max(c.mesh_s, 0) + max(c.solve_s, 0) for c in rows]), "s")
    out.dataset("mesh_resolution/skipped", np.array([c.skipped for c in rows], dtype=h5py.string_dtype()),
                description="why a candidate could not be built or solved; empty otherwise")
    out.attrs("mesh_resolution", {"accuracy_mm": choice.accuracy_mm, "pick": int(choice.pick),
                                  "chosen_scale": float(rows[choice.pick].scale), "element": choice.element,
                                  "reference_element": rows[0].element})


def write_body_plan(out: ResultsFile, plan) -> None:
    """/plan/<target> of a 3-D lesion (a `planning.body_plan.BodyNeedlePlan`) and its /targets attributes: entry,
    direction (3,), depth, clearance (0 without obstacles: the +inf of no obstacle, filled), the joints (filled
    where the robot cannot reach), desired (3,), strokes (C,)."""
    joints = np.zeros(5) if plan.joints is None else np.asarray(plan.joints, float)
    out.attrs(f"plan/{plan.target}", {
        "entry": filled(plan.entry), "direction": filled(plan.direction), "depth_mm": float(filled(plan.depth_mm)),
        "clearance_mm": float(filled(plan.clearance_mm)), "joints": filled(joints),
        "joints_units": "d1, d2, d3 mm; theta4 rad; d5 mm", "joints_note": plan.robot_note,
        "robot_reachable": bool(plan.robot_ok), "feasible": bool(plan.feasible), "reason": plan.reason,
        "desired": np.asarray(plan.desired, float), "strokes": np.asarray(plan.strokes, float),
    })
