"""Needle insertion's results.h5 group, figures, animation and report rows (docs/model.md §12)."""
