"""The environment of a config, as the stages that train in it or evaluate in it build it: the
env settings and what the environment takes of the robot and dataset as typed settings, and the
fit_model and align artifacts read into :class:`~pipeline.rl.envs.factory.LearnedInputs`."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from omegaconf import OmegaConf

from pipeline.infra.artifacts import Artifact
from pipeline.rl.envs.factory import (
    ArmSettings,
    LearnedInputs,
    environment,
    measured_paths,
    read_learned_inputs,
)
from pipeline.schemas import EnvConfig, EnvName


def env_settings(cfg: Any) -> EnvConfig:
    """``cfg.env`` as the schema's object."""
    return OmegaConf.to_object(cfg.env)


def arm_settings(cfg: Any) -> ArmSettings:
    """What the environment of ``cfg`` takes of ``robot`` and ``dataset`` (the whole simulated
    robot for ``env=sim``, whose plant it is)."""
    robot = cfg.robot
    sim = OmegaConf.to_object(robot) if EnvName(cfg.env.name) is EnvName.sim else None
    return ArmSettings(limits=OmegaConf.to_object(robot.limits), n_valves=int(robot.n_valves),
                       control_hz=float(robot.control_hz), model_hz=float(cfg.dataset.model_hz),
                       sim=sim)


def learned_inputs(cfg: Any, model: Artifact, aligned: Artifact,
                   members: Sequence[Artifact] = ()) -> LearnedInputs:
    """The fit_model artifact ``model`` (model and split), the align artifact ``aligned`` it was
    fitted to (at ``dataset.model_hz``) and further fit_model artifacts ``members``."""
    return read_learned_inputs(
        model.file("model.msgpack"), model.file("split.json"), aligned.file("aligned.parquet"),
        float(cfg.dataset.model_hz), str(cfg.dataset.model_grid),
        [member.file("model.msgpack") for member in members])


def config_inputs(cfg: Any, model: Artifact | None = None, aligned: Artifact | None = None,
                  members: Sequence[Artifact] = ()) -> LearnedInputs | None:
    """What ``cfg``'s ``env=learned`` is built from, read of ``model``, ``aligned`` and
    ``members`` (:func:`learned_inputs`); None for the other environments, which need none."""
    if EnvName(cfg.env.name) is EnvName.learned and model is not None and aligned is not None:
        return learned_inputs(cfg, model, aligned, members)
    return None


def config_environment(cfg: Any, model: Artifact | None = None, aligned: Artifact | None = None,
                       members: Sequence[Artifact] = ()) -> tuple[Any, Any, Any]:
    """``(env, train_params, eval_params)`` of ``cfg``'s environment; ``env=learned`` reads
    ``model``, ``aligned`` and ``members`` (the others need none)."""
    return environment_of(cfg, config_inputs(cfg, model, aligned, members))


def environment_of(cfg: Any, inputs: LearnedInputs | None) -> tuple[Any, Any, Any]:
    """``(env, train_params, eval_params)`` of ``cfg``'s environment from ``inputs``
    (:func:`config_inputs`, read once where the caller needs them too)."""
    return environment(env_settings(cfg), arm_settings(cfg), inputs)


def recorded_paths(inputs: LearnedInputs | None) -> dict[str, tuple[Any, Any]]:
    """The measured paths of the runs whose positions are the evaluation goals, by run (``(times
    [T] s, positions [T, 3] m)`` at ``dataset.model_hz``; what a replayed reference replays), of
    ``inputs`` (:func:`config_inputs`); empty without them (not ``env=learned`` on fitted
    runs)."""
    return {} if inputs is None else measured_paths(inputs)
