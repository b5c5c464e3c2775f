"""Needle insertion and needle–tissue interaction (docs/model.md §12)."""

from scissor_cli.insertion.needle import NeedleParams, NeedleState, shaft_lengths
from scissor_cli.insertion.run import (STRATEGIES, InsertionOptions, InsertionResult, NeedlePath, miss_and_depth_error,
                                      run_insertion)

__all__ = ["NeedleParams", "NeedleState", "shaft_lengths", "STRATEGIES", "InsertionOptions", "InsertionResult",
           "NeedlePath", "miss_and_depth_error", "run_insertion"]
