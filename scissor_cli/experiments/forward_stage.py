"""The forward cases of a run (docs/model.md §4), for a layer and a body alike: each case's strokes solved from
rest, stored with its figure and marked finished, one progress line each."""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from scissor_cli import progress
from scissor_cli.experiments.run_summary import RunSummary
from scissor_cli.experiments.sink import ForwardCase, RunSink, product_key
from scissor_cli.mechanics.tissue import Tissue
from scissor_cli.mesh.probe import target_positions
from scissor_cli.solvers.common import SolverError
from scissor_cli.solvers.equilibrium import EquilibriumSolver

#: (case name, strokes (C,) mm, its solve, the targets' deformed positions by name) → the figure's kwargs
FigureInputs = Callable[[str, np.ndarray, object, dict], dict]


def forward_stage(cases: Sequence, solver_config, tissue: Tissue, probe, sink: RunSink, summary: RunSummary,
                  figure_inputs: FigureInputs, kind: str = "layer", done: frozenset[str] = frozenset()) -> None:
    """Solve every forward case (the config's `forward` entries: name, strokes by cup) not in `done`; `probe`
    carries the targets' rest positions (`mesh.probe`). A case whose solve fails fails the run with its name."""
    scene = tissue.scene
    solver = EquilibriumSolver.from_config(tissue, solver_config)
    todo = [case for case in cases if product_key("forward", case.name) not in done]
    advance = progress.bar("forward cases", len(todo))
    for case in todo:
        strokes = scene.strokes_vector(case.strokes)
        try:
            result = solver.solve_case(strokes)
        except SolverError as exc:
            summary.status, summary.failure = "failed", f"forward case {case.name!r}: {exc}"
            raise SolverError(summary.failure, exc.result) from None
        summary.forward[case.name] = result
        targets = {t.name: p for t, p in zip(scene.targets, target_positions(probe, result.x))}
        paths = sink.forward_case(ForwardCase(case.name, {c.name: float(s) for c, s in zip(scene.cups, strokes)},
                                              result, tissue.mesh.nodes, targets,
                                              figure_inputs(case.name, strokes, result, targets), kind=kind))
        sink.mark_finished(product_key("forward", case.name))
        summary.figures += [p for p in np.atleast_1d(paths) if p is not None]
        moved = "; ".join(f"{n} moved {np.linalg.norm(p - t.rest):.3f} mm"
                          for (n, p), t in zip(targets.items(), scene.targets))
        note = "" if result.message.startswith("converged") else f" ({result.message})"
        progress.info(f"forward {case.name}: {result.solver} {result.iterations} iterations, residual "
                      f"{result.residual:.2e}, {result.time_s * 1e3:.1f} ms{note}" + (f"; {moved}" if moved else ""))
        advance(1)
