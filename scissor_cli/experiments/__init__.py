"""Experiments: the simulate pipeline, trials, solver studies and accuracy-driven model selection
(docs/model.md §9, §10)."""
