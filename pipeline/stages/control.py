"""Stage ``control``: a trained policy drives the arm toward goals (see
:mod:`pipeline.control.session`). Not part of ``stage=all``: started on its own.

The train_ppo artifact is found from the composed config as evaluate finds it (or from
``control.policy_file``); its environment is rebuilt from the artifact's lineage (its manifest and
those of the fit_model and align artifacts it was trained on) with
:func:`pipeline.rl.envs.factory.environment`, exactly as training built it
(:func:`load_deployment`). The session's rows, per-goal metrics, figures and report go into the
``control`` artifact.
"""

from __future__ import annotations

import datetime as _dt
import logging
import shutil
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.arm.limits import validate_limits
from pipeline.control.goals import GoalError, goal_schedule
from pipeline.control.loop import Outcome
from pipeline.control.policy import Deployment, deploy
from pipeline.control.results import goal_metrics
from pipeline.control.session import (
    STAGE,
    ControlInterrupted,
    report_session,
    run_session,
    set_aside_interrupted,
)
from pipeline.infra.artifacts import Artifact, ArtifactStore, ArtifactWriter, artifact_key, produce
from pipeline.keys import SPEC_VERSIONS
from pipeline.rl.policy_io import best_seed, load_policy
from pipeline.schemas import (
    ConfigError,
    EnvConfig,
    EnvName,
    PressureLimits,
    RobotKind,
    SimRobotConfig,
)
from pipeline.stages._environment import config_environment
from pipeline.validation import validate_config

log = logging.getLogger(__name__)


def control(cfg: Any) -> Artifact:
    """Run ``control.policy`` (or ``control.policy_file``) on ``cfg.robot``; see the module doc."""
    validate_config(cfg)  # also when called without the entry point (scripts, benchmarks)
    robot = OmegaConf.to_object(cfg.robot)
    settings = OmegaConf.to_object(cfg.control)
    kind = RobotKind(robot.kind)
    if kind not in (RobotKind.sim, RobotKind.ros2):
        raise ValueError(f"stage=control drives an arm: robot=ros2 (or the twin) or robot=sim; "
                         f"got robot={robot.name} (recorded data)")
    if kind is RobotKind.sim and settings.goal_topic:
        raise GoalError("control.goal_topic needs robot=ros2 (live goals arrive over ROS 2)")
    if kind is RobotKind.ros2:
        if not float(robot.time_scale) > 0:
            raise ValueError(f"robot.time_scale={robot.time_scale} must be positive")
        from pipeline.ros2.node import require_rclpy

        require_rclpy()
    validate_limits(robot.limits, robot.n_valves)
    store = ArtifactStore(cfg.paths.artifact_dir)
    deployment = load_deployment(cfg, store)
    schedule = goal_schedule(settings, deployment.control_hz, deployment.workspace_m)
    spec, inputs = keys.control_spec(cfg)
    set_aside_interrupted(store, artifact_key(spec, inputs))
    outcomes: list[Outcome] = []

    def build(writer: ArtifactWriter) -> None:
        started = _dt.datetime.now().strftime("%Y%m%dT%H%M%S")
        recovery = Path(cfg.paths.output_dir) / "recovery" / f"{STAGE}-{writer.key}-{started}"
        record = run_session(robot, settings, deployment, schedule, recovery, spec)
        record.recorder.write(writer.file("periods.parquet"), record.periods)
        metrics = goal_metrics(record.periods, 1.0 / deployment.control_hz)
        metrics.to_parquet(writer.file("goals.parquet"), index=False)
        writer.summary = report_session(writer.path, record, metrics, deployment, schedule, robot)
        shutil.rmtree(record.recovery)  # the artifact's temporary folder now holds every row
        outcomes.append(record.outcome)

    artifact = produce(store, STAGE, spec, inputs, build, force=cfg.force)
    log.info("control: report at %s", artifact.file("report.html"))
    outcome = outcomes[0] if outcomes else None
    if outcome is not None and outcome.reason is not None:
        live_end = (schedule.end is None and outcome.error is None
                    and outcome.reason.endswith("received"))
        if not live_end:
            raise ControlInterrupted(
                f"control interrupted: {outcome.reason}. The preload was commanded"
                f"{'' if outcome.preload_acknowledged is not False else ' (not acknowledged)'}. "
                f"The periods recorded so far are in {artifact.path}") from outcome.error
    return artifact


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
    with :func:`~pipeline.stages._environment.config_environment`: the env, robot rate and limits,
    and model rate it was trained with, read from its manifest and those of its inputs, laid over
    the schemas' defaults (the spec keeps what differs from them)."""
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
    if int(spec["env"].get("preview", 0)):
        raise ConfigError(f"{artifact.path}: a policy trained to track with a preview of "
                          f"env.preview={spec['env']['preview']} reference points; stage=control "
                          f"sends goals, not references: drive a policy trained without a preview")
    env = OmegaConf.merge(OmegaConf.structured(EnvConfig), spec["env"])
    if env_name is EnvName.sim:
        robot = OmegaConf.merge(OmegaConf.structured(SimRobotConfig), spec["robot"])
        dataset = {"model_hz": spec["model_hz"]}
        return OmegaConf.create({"env": env, "robot": robot, "dataset": dataset}), None, None
    model = store.require("fit_model", manifest["inputs"]["fit_model"])
    aligned = store.require("align", model.manifest["inputs"]["align"])
    dataset = model.manifest["spec"]["dataset"]
    robot = {"control_hz": spec["control_hz"], "n_valves": n_valves,
             "limits": OmegaConf.merge(OmegaConf.structured(PressureLimits), spec["limits"])}
    config = OmegaConf.create({"env": env, "robot": robot,
                               "dataset": {"model_hz": dataset["model_hz"],
                                           "model_grid": dataset["model_grid"]}})
    return config, model, aligned


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
    env, train_params, eval_params = config_environment(train_cfg, model, aligned)
    network, stacked, meta = load_policy(artifact.file("policy.msgpack"))
    num_seeds = int(meta.get("num_seeds", 1))
    evaluation = artifact.file("evaluation.parquet")
    seed = (best_seed(pd.read_parquet(evaluation), evaluation) if cfg.control.seed is None
            else int(cfg.control.seed))
    if not 0 <= seed < num_seeds:
        raise ValueError(f"control.seed={seed}: {artifact.file('policy.msgpack')} holds seeds "
                         f"0..{num_seeds - 1}")
    return deploy(artifact, seed, network, stacked, meta, env, train_params, eval_params,
                  control_hz)
