"""Composition of the pipeline's config: the schemas (``pipeline/schemas/``) registered with Hydra,
the project's paths, and composing the config outside a Hydra run.

Every YAML file under ``conf/`` extends one of the schemas (through its defaults list), so Hydra
type-checks every value and rejects unknown keys at composition: a typo such as
``exploration.alpah=0.5`` or ``stage=fitmodel`` fails before any work starts, with a message that
names the key and, for enums, the valid values. The router then runs
:func:`pipeline.validation.validate_config` before any work.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from pipeline import PROJECT_ROOT
from pipeline.schemas import (
    AdaptConfig,
    AgentConfig,
    CalibrationConfig,
    Config,
    ControlConfig,
    DatasetConfig,
    EnvConfig,
    EvaluationConfig,
    ExplorationConfig,
    ImportRobotConfig,
    ImproveConfig,
    LoggerConfig,
    ModelConfig,
    PathsConfig,
    Ros2RobotConfig,
    RosbagRobotConfig,
    SimRobotConfig,
)


def sorolex_dir() -> Path:
    """The paper's recorded runs: ``SOROLEX_DIR``, else ``../shared/data/sorolex`` beside the
    checkout (as ``paths.data_dir``)."""
    return Path(os.environ.get("SOROLEX_DIR", PROJECT_ROOT.parent / "shared" / "data" / "sorolex"))


def compose(*overrides: str) -> Any:
    """The pipeline's composed config (``conf/config.yaml``) with Hydra ``overrides``, outside
    a Hydra run (scripts, benchmarks, experiments); the schemas are registered first."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    register_configs()
    with initialize_config_dir(config_dir=str(PROJECT_ROOT / "conf"), version_base="1.3"):
        return hydra_compose("config", overrides=list(overrides))


def register_configs() -> None:
    """Register the schemas (each YAML names its schema first in its defaults list) and the
    ``${project_root:}`` resolver."""
    OmegaConf.register_new_resolver("project_root", lambda: str(PROJECT_ROOT), replace=True)
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(group="robot", name="base_sim", node=SimRobotConfig)
    cs.store(group="robot", name="base_import", node=ImportRobotConfig)
    cs.store(group="robot", name="base_ros2", node=Ros2RobotConfig)
    cs.store(group="robot", name="base_rosbag", node=RosbagRobotConfig)
    cs.store(group="exploration", name="base_exploration", node=ExplorationConfig)
    cs.store(group="dataset", name="base_dataset", node=DatasetConfig)
    cs.store(group="calibration", name="base_calibration", node=CalibrationConfig)
    cs.store(group="model", name="base_model", node=ModelConfig)
    cs.store(group="env", name="base_env", node=EnvConfig)
    cs.store(group="agent", name="base_agent", node=AgentConfig)
    cs.store(group="evaluation", name="base_evaluation", node=EvaluationConfig)
    cs.store(group="control", name="base_control", node=ControlConfig)
    cs.store(group="adapt", name="base_adapt", node=AdaptConfig)
    cs.store(group="improve", name="base_improve", node=ImproveConfig)
    cs.store(group="logger", name="base_logger", node=LoggerConfig)
    cs.store(group="paths", name="base_paths", node=PathsConfig)
    adopt_launcher_schemas()


# Hydra's sweep launchers (hydra/launcher=joblib|submitit_local|submitit_slurm): the plugins
# register their schemas under the options' own names, and a YAML of the same name is then
# matched to its schema automatically, which Hydra deprecated (a warning on every composition).
# Each schema moves to base_<name>, which conf/hydra/launcher/<name>.yaml names first, as the
# other groups name theirs.
LAUNCHER_OPTIONS = ("joblib", "submitit_local", "submitit_slurm")


def adopt_launcher_schemas() -> list[str]:
    """Store each installed launcher plugin's schema as ``hydra/launcher/base_<name>`` in place of
    the entry of the option's own name; returns the options whose schema is there."""
    from hydra.core.plugins import Plugins

    Plugins.instance()  # Hydra's one scan of the plugins, which registers their schemas
    entries = ConfigStore.instance().repo.setdefault("hydra", {}).setdefault("launcher", {})
    for name in LAUNCHER_OPTIONS:
        entry = entries.pop(f"{name}.yaml", None)
        if entry is not None:
            ConfigStore.instance().store(group="hydra/launcher", name=f"base_{name}",
                                         node=entry.node, provider=entry.provider)
    return [name for name in LAUNCHER_OPTIONS if f"base_{name}.yaml" in entries]
