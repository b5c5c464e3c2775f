"""gymnasium environments of scissor (docs/model.md §22): importing this package registers

* ``scissor/LesionAlign2D-v0`` (`env.LesionAlign2D`, the 2-D layer) and
* ``scissor/LesionAlign3D-v0`` (`env.LesionAlign3D`, a 3-D body; ``plant="body"`` or ``"surrogate"``),

so ``gymnasium.make("scissor_cli.gym:scissor/LesionAlign2D-v0", config=PATH)`` works.
`PluginPolicy` drives them with a plug-in controller. Needs the ``gym`` extra (gymnasium).
"""

from gymnasium.envs.registration import register, registry

from scissor_cli.gym.env import FAILURE_REWARD, MISS_BOUND_MM, LesionAlign2D, LesionAlign3D, LesionAlignEnv
from scissor_cli.gym.policy import PluginPolicy

__all__ = ["FAILURE_REWARD", "MISS_BOUND_MM", "LesionAlign2D", "LesionAlign3D", "LesionAlignEnv", "PluginPolicy"]

# no episode limit here: the environments truncate at the config's controller.max_iterations themselves
for _name, _entry in (("scissor/LesionAlign2D-v0", "scissor_cli.gym.env:LesionAlign2D"),
                      ("scissor/LesionAlign3D-v0", "scissor_cli.gym.env:LesionAlign3D")):
    if _name not in registry:
        register(id=_name, entry_point=_entry)
