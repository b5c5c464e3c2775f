"""The ultrasound's outputs (docs/contract.md `/imaging`): the results.h5 group, the B-mode figures and
animation, report rows."""
