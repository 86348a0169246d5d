"""The config schemas, one module per concern: every YAML file under ``conf/`` extends one of
these dataclasses. Plain dataclasses and enums (no OmegaConf, no Hydra), so libraries can take
them as typed settings; ``pipeline.config`` registers them with Hydra.

Units: pressures in kPa, positions in metres, times in seconds, rates in Hz.
"""

from __future__ import annotations

from pipeline.schemas.adapt import AdaptConfig
from pipeline.schemas.agent import (
    AgentConfig,
    budget_overrides,
)
from pipeline.schemas.choices import (
    ActionMode,
    Activation,
    Cell,
    Choice,
    EnvName,
    GapPolicy,
    GoalMode,
    GoalSource,
    LrSchedule,
    ModelGrid,
    ModelLoss,
    ModelProtocol,
    ReferencePose,
    RobotKind,
    Stage,
    WindowOrder,
)
from pipeline.schemas.data import (
    AlignConfig,
    CalibrationConfig,
    DatasetConfig,
    ExplorationConfig,
)
from pipeline.schemas.env import (
    EnvConfig,
    RandomizationConfig,
    incremental_actions,
    no_randomization_overrides,
)
from pipeline.schemas.model import (
    ModelArchitecture,
    ModelConfig,
)
from pipeline.schemas.robot import (
    GuardConfig,
    ImportRobotConfig,
    MocapConfig,
    PressureLimits,
    PressureRating,
    QosConfig,
    QosDurability,
    QosReliability,
    ReplayConfig,
    RobotConfig,
    Ros2RobotConfig,
    RosbagRobotConfig,
    RosTopicsConfig,
    SafetyBounds,
    SimPhysics,
    SimRobotConfig,
    TwinConfig,
    WorkspaceConfig,
)
from pipeline.schemas.run import (
    Config,
    ControlConfig,
    EvaluationConfig,
    LoggerConfig,
    PathsConfig,
)
from pipeline.schemas.values import (
    MISSING,
    ConfigError,
    dataclass_values,
    frozen_twin,
)

__all__ = [
    "MISSING",
    "ActionMode",
    "Activation",
    "AdaptConfig",
    "AgentConfig",
    "AlignConfig",
    "CalibrationConfig",
    "Cell",
    "Choice",
    "Config",
    "ConfigError",
    "ControlConfig",
    "DatasetConfig",
    "EnvConfig",
    "EnvName",
    "EvaluationConfig",
    "ExplorationConfig",
    "GapPolicy",
    "GoalMode",
    "GoalSource",
    "GuardConfig",
    "ImportRobotConfig",
    "LoggerConfig",
    "LrSchedule",
    "MocapConfig",
    "ModelArchitecture",
    "ModelConfig",
    "ModelGrid",
    "ModelLoss",
    "ModelProtocol",
    "PathsConfig",
    "PressureLimits",
    "PressureRating",
    "QosConfig",
    "QosDurability",
    "QosReliability",
    "RandomizationConfig",
    "ReferencePose",
    "ReplayConfig",
    "RobotConfig",
    "RobotKind",
    "Ros2RobotConfig",
    "RosTopicsConfig",
    "RosbagRobotConfig",
    "SafetyBounds",
    "SimPhysics",
    "SimRobotConfig",
    "Stage",
    "TwinConfig",
    "WindowOrder",
    "WorkspaceConfig",
    "budget_overrides",
    "dataclass_values",
    "frozen_twin",
    "incremental_actions",
    "no_randomization_overrides",
]
