"""The scene file: pydantic models of every section, loading with errors that name file, field and line.

Everything outside this package imports from here, so the package's inner
split may change.
"""

from scissor_cli.config.checks import obstacle_outline, scene_problems, tissue_outline
from scissor_cli.config.controller_class import ControllerClassError, controller_instance
from scissor_cli.config.element_budget import ELEMENT_BUDGET, estimate_elements
from scissor_cli.config.loading import (
    MAX_CONFIG_BYTES,
    ConfigError,
    load_config,
    parse_config,
    read_config_text,
    resolved_yaml,
)
from scissor_cli.config.sections import (
    BoxConfig,
    CameraConfig,
    CircleConfig,
    Config,
    ControllerConfig,
    CupConfig,
    DHLinkConfig,
    ForwardCase,
    ImagingConfig,
    InsertionConfig,
    LayerCheckConfig,
    ManipulationPointsConfig,
    MaterialConfig,
    MeshConfig,
    NeedleConfig,
    ObstacleConfig,
    RobotConfig,
    SolverConfig,
    StudyConfig,
    TargetConfig,
    TissueConfig,
    TrialsConfig,
)

__all__ = [
    "ELEMENT_BUDGET", "MAX_CONFIG_BYTES",
    "BoxConfig", "CameraConfig", "CircleConfig", "Config", "ConfigError", "ControllerClassError", "ControllerConfig",
    "CupConfig",
    "DHLinkConfig", "ForwardCase", "ImagingConfig", "InsertionConfig", "LayerCheckConfig", "ManipulationPointsConfig",
    "MaterialConfig", "MeshConfig",
    "NeedleConfig", "ObstacleConfig",
    "RobotConfig", "SolverConfig", "StudyConfig", "TargetConfig", "TissueConfig", "TrialsConfig",
    "controller_instance", "estimate_elements", "load_config", "obstacle_outline", "parse_config", "read_config_text",
    "resolved_yaml",
    "scene_problems", "tissue_outline",
]
