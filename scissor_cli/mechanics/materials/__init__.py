"""Hyperelastic material models (package; see :mod:`.plane_strain`)."""

from scissor_cli.mechanics.materials.plane_strain import *  # noqa: F401,F403
from scissor_cli.mechanics.materials.plane_strain import (  # noqa: F401
    __all__,
    _eigensystem,
    _evaluate_projected,
)
