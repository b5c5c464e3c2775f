"""Finite elements and energies: P1 operators, material models, the discrete tissue (docs/model.md §2, §3)."""
