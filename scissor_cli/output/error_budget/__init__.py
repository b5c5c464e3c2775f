"""The error budget's results.h5 group, figures and report rows (docs/model.md §16)."""
