"""scissor: simulate robot-assisted breast intervention from a YAML scene (see docs/).

`import scissor_cli` gives the Python API of docs/api.md (`scissor_cli.api`):
`scissor_cli.load_config(...)`, `scissor_cli.simulate(...)`, … The API is
loaded on first use, so importing the package stays light (the CLI's
`--help`, the trial workers).
"""

import importlib

__version__ = "0.2.0"


#: `scissor_cli.api.__all__` (a test keeps them equal): only these load the API, so `from scissor_cli import
#: runtime` and the other submodules import nothing more
API_NAMES = (
    "ConfigError", "ControllerError", "ControllerLaw", "LoopResult", "PIDLaw", "Scene", "TargetTask",
    "build_tissue", "load_config", "manipulate", "parse_config", "plan", "read_trials", "resolved_yaml", "run",
    "simulate", "solve", "tasks", "trial_run",
)


def __getattr__(name: str):
    if name not in API_NAMES:
        raise AttributeError(f"module 'scissor_cli' has no attribute {name!r} (the API's names: docs/api.md)")
    # by name: the API sits above every layer it hands over to
    return getattr(importlib.import_module("scissor_cli.api"), name)
