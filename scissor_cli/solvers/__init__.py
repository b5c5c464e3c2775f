"""Equilibria of the tissue: Newton (the reference), ADMM, the linear algebra and the cup-to-target Jacobian
(docs/model.md §4, §5)."""
