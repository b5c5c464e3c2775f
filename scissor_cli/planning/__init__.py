"""Needle plans: corridors that miss the obstacles and the target positions that open them (docs/model.md §7)."""
