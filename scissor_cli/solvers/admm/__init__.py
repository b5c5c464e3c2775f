"""ADMM-PD (docs/model.md §4): the solver, its per-element weights, local step, Anderson acceleration and
implicit Euler."""
