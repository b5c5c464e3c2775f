"""scissor: simulate robot-assisted breast intervention from a YAML scene."""

__version__ = "0.1.0"
