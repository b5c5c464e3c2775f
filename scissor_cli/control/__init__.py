"""Closed-loop target manipulation: actuator, the two tissues, the control law and the loop (docs/model.md §6).

Callers outside the package import from here.
"""

from scissor_cli.control.actuator import Actuator, quantise
from scissor_cli.control.corridor_check import Corridor, corridor_at
from scissor_cli.control.law import PID, STOP_REASONS, split_error
from scissor_cli.control.loop import TargetRun, open_loop, outside_law, run_loop, run_target
from scissor_cli.control.plant import Controller, ModelPaths, Plant, TruthPerturbation, TruthView, true_tissue
from scissor_cli.control.plugin import ControllerError, ControllerLaw, PIDLaw, drive, frame_info, observation
from scissor_cli.control.result import LoopResult

__all__ = [
    "Actuator", "Controller", "ControllerError", "ControllerLaw", "Corridor", "LoopResult", "ModelPaths", "PID",
    "PIDLaw", "Plant", "STOP_REASONS", "TargetRun", "TruthPerturbation", "TruthView", "corridor_at", "drive",
    "frame_info", "observation", "open_loop", "outside_law", "quantise", "run_loop", "run_target", "split_error",
    "true_tissue",
]
