"""Needle insertion and needle–tissue interaction (docs/model.md §12)."""

from scissor_cli.insertion.needle import NeedleParams, NeedleState, shaft_lengths
from scissor_cli.insertion.run import STRATEGIES, InsertionResult, miss_and_depth_error, run_insertion

__all__ = ["NeedleParams", "NeedleState", "shaft_lengths", "STRATEGIES", "InsertionResult", "miss_and_depth_error",
           "run_insertion"]
