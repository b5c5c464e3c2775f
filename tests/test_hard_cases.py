"""The shipped hard cases (configs/hard/): each converges or fails with a reason; no NaN leaves a solver."""

from pathlib import Path

import numpy as np
import pytest

from scissor_cli.config import load_config
from scissor_cli.config.body_sections import BodyConfig
from scissor_cli.experiments.build import body_model, build_model
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.equilibrium import EquilibriumSolver

from helpers import ROOT

ALL = sorted((ROOT / "configs" / "hard").glob("*.yaml"))
HARD = [p for p in ALL if not p.stem.startswith("dome_")]
HARD_3D = [p for p in ALL if p.stem.startswith("dome_")]


def test_every_hard_case_is_shipped():
    names = {p.stem for p in HARD}
    assert names == {"nearly_incompressible", "compression40", "stiff_fibers", "stiff_obstacle", "thin_polygon",
                     "dynamics_large_dt", "inverted_start", "robot_unreachable"}
    assert {p.stem for p in HARD_3D} == {"dome_nearly_incompressible", "dome_compression40", "dome_stiff_inclusion",
                                         "dome_inverted_start"}


@pytest.mark.parametrize("path", HARD_3D, ids=[p.stem for p in HARD_3D])
def test_hard_case_in_3d(path: Path, tmp_path_factory):
    """Each 3-D hard case converges on its element (`nodal`) at three times the edge length, every tetrahedron
    upright."""
    cfg = load_config(path)
    assert isinstance(cfg, BodyConfig) and cfg.tissue.mesh.element == "nodal"
    _, _, tissue = body_model(cfg, cache=tmp_path_factory.getbasetemp() / "mesh-cache", scale=3.0)
    forward = EquilibriumSolver.from_config(tissue, cfg.solver)
    for case in cfg.forward:
        r = forward.solve_case(tissue.scene.strokes_vector(case.strokes))
        assert r.converged and r.residual <= 1e-8, (case.name, r.message)
        assert np.all(np.isfinite(r.x)) and tissue.jacobians(r.x).min() > 0
        if cfg.solver.initial_guess == "mirrored":
            assert "inverted" in r.message


@pytest.mark.parametrize("solver", ["newton", "admm"])
@pytest.mark.parametrize("path", HARD, ids=[p.stem for p in HARD])
def test_hard_case(path: Path, solver: str):
    cfg = load_config(path)
    cfg = cfg.model_copy(update={"solver": cfg.solver.model_copy(update={"kind": solver, "anderson_memory": 5})})
    _, mesh, tissue = build_model(cfg, mesh_scale=2.0 * cfg.tissue.mesh.scale)
    forward = EquilibriumSolver.from_config(tissue, cfg.solver)
    for case in cfg.forward:
        strokes = tissue.scene.strokes_vector(case.strokes)
        try:
            r = forward.solve_case(strokes)
        except SolverError as exc:
            # allowed only with a reason, and whatever it kept must be finite
            assert str(exc)
            if exc.result is not None:
                assert np.all(np.isfinite(exc.result.x))
            pytest.fail(f"{path.stem} {case.name} {solver}: {exc}")
        assert r.converged, r.message
        assert np.all(np.isfinite(r.x)) and tissue.jacobians(r.x).min() > 0
        assert r.residual <= (1e-8 if solver == "newton" else 1e-2), (r.residual, r.message)
        if cfg.solver.initial_guess == "mirrored":
            assert "inverted" in r.message
