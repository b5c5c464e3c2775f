"""scissor: simulate robot-assisted breast intervention from a YAML scene (see docs/)."""

__version__ = "0.2.0"
