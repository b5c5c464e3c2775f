"""Needle insertion and needle–tissue interaction (docs/model.md §12)."""

from scissor_cli.insertion.capture import shaft_lengths
from scissor_cli.insertion.needle import NeedleParams, NeedleState
from scissor_cli.insertion.run import (
    STRATEGIES,
    InsertionOptions,
    InsertionResult,
    NeedlePath,
    miss_and_depth_error,
    needle_path,
    run_insertion,
    run_strategies,
)
from scissor_cli.insertion.steering import NeedleModel

__all__ = ["NeedleParams", "NeedleState", "shaft_lengths", "STRATEGIES", "InsertionOptions", "InsertionResult",
           "NeedleModel", "NeedlePath", "miss_and_depth_error", "needle_path", "run_insertion", "run_strategies"]
