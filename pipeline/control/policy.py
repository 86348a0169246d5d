"""The policy ``stage=control`` deploys, with the environment it was trained in.

The train_ppo artifact is found from the composed config as evaluate finds it (or from
``control.policy_file``); the environment is rebuilt from the artifact's lineage (its manifest and
those of the fit_model and align artifacts it was trained on) with
:func:`pipeline.rl.envs.factory.environment`, exactly as training built it. From it come the
observation's standardization (``EnvParams``), the action mapping and the workspace (the box of
the training goals).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.evaluation.rollouts import policy_controller
from pipeline.infra.artifacts import Artifact, ArtifactStore
from pipeline.keys import SPEC_VERSIONS
from pipeline.rl.envs.factory import (
    ArmSettings,
    LearnedInputs,
    environment,
    read_learned_inputs,
)
from pipeline.rl.envs.learned import EnvParams, SoftArmReachEnv
from pipeline.rl.envs.observation import observe, update_error_integral
from pipeline.rl.networks import initial_hidden
from pipeline.rl.policy_io import best_seed, load_policy
from pipeline.schemas import ConfigError, EnvConfig, EnvName, PressureLimits, SimRobotConfig

log = logging.getLogger(__name__)
MM_PER_M = 1000.0


@dataclass
class Deployment:
    """A policy ready to act: ``step`` is jitted and compiled (see :meth:`act`)."""

    artifact: Artifact
    seed: int
    env: SoftArmReachEnv
    env_params: EnvParams  # the evaluation parameters: the training standardization
    policy_params: Any
    # the initial carry between periods: ([1, H] recurrent state, a placeholder for feed-forward
    # policies; [3] accumulated error, zeros, used with env.include_error_integral)
    hidden: Any
    workspace_m: np.ndarray  # [2, 3] lower and upper corner of the training goals
    control_hz: float
    step: Any  # jitted (policy_params, env_params, carry, first, measured, goal, last_pressure)

    def act(self, hidden: Any, first: bool, measured: np.ndarray, goal: np.ndarray,
            last_pressure: np.ndarray) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
        """One period: ``(carry, observation [obs_dim], action [3] in [-1, 1], pressure [3] kPa
        before the gate)``; ``hidden``: the carry of the previous period (``Deployment.hidden``
        at the first, ``first=True``); ``measured``, ``goal`` in m, ``last_pressure`` in kPa."""
        hidden, obs, action, pressure = self.step(
            self.policy_params, self.env_params, hidden, jnp.asarray(first),
            jnp.asarray(measured, jnp.float32), jnp.asarray(goal, jnp.float32),
            jnp.asarray(last_pressure, jnp.float32))
        obs, action, pressure = jax.device_get((obs, action, pressure))
        return hidden, np.asarray(obs), np.asarray(action), np.asarray(pressure, np.float64)


def policy_artifact(cfg: Any, store: ArtifactStore) -> tuple[Artifact, ArtifactStore]:
    """The train_ppo artifact of ``control.policy_file`` or of ``control.policy`` (by key), and
    the store that holds it and its lineage (that of ``control.policy_file``'s folder)."""
    key = keys.control_policy_key(cfg)
    if cfg.control.policy_file:
        folder = Path(str(cfg.control.policy_file)).resolve().parent
        return Artifact("train_ppo", key, folder), ArtifactStore(folder.parent.parent)
    hint = (f" with agent={cfg.control.policy}, on this robot's data (robot=ros2: `stage=collect` "
            f"first); or point control.policy_file at a train_ppo policy.msgpack")
    return store.require("train_ppo", key, hint=hint), store


def training_config(artifact: Artifact, store: ArtifactStore, n_valves: int
                    ) -> tuple[Any, Artifact | None, Artifact | None]:
    """``(config, fit_model artifact, align artifact)`` that rebuild the artifact's environment
    with :func:`environment`: the env, robot rate and limits, and model rate it was trained with,
    read from its manifest and those of its inputs."""
    manifest = artifact.manifest
    spec = manifest["spec"]
    version = spec.get("spec_version", 1)
    if version != SPEC_VERSIONS["train_ppo"]:
        raise ConfigError(f"{artifact.path}: a policy of train_ppo spec version {version}, this "
                          f"version rebuilds environments of version "
                          f"{SPEC_VERSIONS['train_ppo']}; train it anew (stage=train_ppo)")
    env_name = EnvName(spec["env"]["name"])
    if env_name is EnvName.gymnax:
        raise ValueError(f"{artifact.path}: a policy of a gymnax environment "
                         f"({spec['env'].get('gymnax_name')}) cannot drive the arm")
    if env_name is EnvName.sim:
        robot = spec["robot"]
        dataset = {"model_hz": spec["model_hz"]}
        return OmegaConf.create({"env": spec["env"], "robot": robot, "dataset": dataset}), None, None
    model = store.require("fit_model", manifest["inputs"]["fit_model"])
    aligned = store.require("align", model.manifest["inputs"]["align"])
    dataset = model.manifest["spec"]["dataset"]
    robot = {"control_hz": spec["control_hz"], "limits": spec["limits"], "n_valves": n_valves}
    config = OmegaConf.create({"env": spec["env"], "robot": robot,
                               "dataset": {"model_hz": dataset["model_hz"],
                                           "model_grid": dataset["model_grid"]}})
    return config, model, aligned


def trained_settings(train_cfg: Any, model: Artifact | None, aligned: Artifact | None
                     ) -> tuple[EnvConfig, ArmSettings, LearnedInputs | None]:
    """The arguments of :func:`environment` from :func:`training_config`'s result: the env
    settings (the spec's, merged onto the schema's defaults: a full object), what the env takes
    of the robot and dataset, and the learned env's inputs (None for ``env=sim``)."""
    env = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(EnvConfig), train_cfg.env))
    robot = train_cfg.robot
    sim = None
    if EnvName(env.name) is EnvName.sim:
        sim = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(SimRobotConfig), robot))
    arm = ArmSettings(PressureLimits(**OmegaConf.to_container(robot.limits)),
                      int(robot.n_valves), float(robot.control_hz),
                      float(train_cfg.dataset.model_hz), sim)
    if model is None or aligned is None:
        return env, arm, None
    return env, arm, read_learned_inputs(
        model.file("model.msgpack"), model.file("split.json"), aligned.file("aligned.parquet"),
        float(train_cfg.dataset.model_hz), str(train_cfg.dataset.model_grid))

def make_step(network: Any, env: SoftArmReachEnv) -> Any:
    """The jitted control step: observation (the environment's :func:`observe`), the
    deterministic action (evaluate's policy controller), the pressures (the environment's
    action mapping). Its carry is ``(recurrent state, accumulated error)``; the accumulated
    error is zero at the first period and then updated with each measured pose, as the
    environment does from a reset (:func:`update_error_integral`)."""

    def step(policy_params, env_params, carry, first, measured, goal, last_pressure):
        hidden, integral = carry
        integral = jnp.where(first, jnp.zeros_like(integral),
                             update_error_integral(integral, measured, goal, env_params))
        obs = observe(measured, goal, last_pressure, env_params, include_error=env.include_error,
                      include_last_action=env.include_last_action,
                      error_integral=integral if env.include_error_integral else None)
        act = policy_controller(network, policy_params)
        (hidden, _), action = act(None, obs, None, (hidden, first))
        return (hidden, integral), obs, action, env.command(action, last_pressure, env_params)

    return jax.jit(step)


def load_deployment(cfg: Any, store: ArtifactStore) -> Deployment:
    """The policy of this config, its environment, and its step compiled (one call made)."""
    artifact, lineage = policy_artifact(cfg, store)
    train_cfg, model, aligned = training_config(artifact, lineage, int(cfg.robot.n_valves))
    control_hz = float(train_cfg.robot.control_hz)
    if abs(control_hz - float(cfg.robot.control_hz)) > 1e-9:
        raise ValueError(f"robot.control_hz={cfg.robot.control_hz}: the policy {artifact.path} "
                         f"was trained at {control_hz} Hz; set robot.control_hz={control_hz}")
    trained_limits = OmegaConf.to_container(train_cfg.robot.limits)
    robot_limits = OmegaConf.to_container(cfg.robot.limits)
    if {k: float(v) for k, v in trained_limits.items()} != {
            k: float(v) for k, v in robot_limits.items()}:
        log.warning("control: the policy was trained with limits %s, robot.limits are %s: its "
                    "actions map onto the trained range, the gate then projects onto robot.limits",
                    trained_limits, robot_limits)
    env, train_params, eval_params = environment(*trained_settings(train_cfg, model, aligned))
    network, stacked, meta = load_policy(artifact.file("policy.msgpack"))
    num_seeds = int(meta.get("num_seeds", 1))
    evaluation = artifact.file("evaluation.parquet")
    seed = (best_seed(pd.read_parquet(evaluation), evaluation) if cfg.control.seed is None
            else int(cfg.control.seed))
    if not 0 <= seed < num_seeds:
        raise ValueError(f"control.seed={seed}: {artifact.file('policy.msgpack')} holds seeds "
                         f"0..{num_seeds - 1}")
    policy_params = jax.tree.map(lambda x: x[seed], stacked)
    goals = np.asarray(train_params.goal_set, np.float64)
    workspace = np.stack([goals.min(axis=0), goals.max(axis=0)])
    deployment = Deployment(artifact, seed, env, eval_params, policy_params,
                            (initial_hidden(network, 1), jnp.zeros(3, jnp.float32)),
                            workspace, control_hz,
                            make_step(network, env))
    # compile before the first command: the first period must not wait for XLA
    preload = np.asarray(eval_params.preload, np.float64)
    deployment.act(deployment.hidden, True, workspace.mean(axis=0), workspace.mean(axis=0),
                   preload)
    log.info("control: policy %s seed %d (%s on %s), workspace %s mm", artifact.path, seed,
             meta["agent"]["name"], meta.get("env_name"),
             np.round(workspace * MM_PER_M, 1).tolist())
    return deployment
