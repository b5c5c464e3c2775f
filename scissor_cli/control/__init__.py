"""Closed-loop target manipulation: actuator, measurement, PID and the loop (docs/model.md §6)."""
