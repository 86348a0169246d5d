"""Stage ``control``: a trained policy drives the arm toward goals, or along a reference
(``control.trajectory``, :mod:`pipeline.control.trajectory`; see :mod:`pipeline.control.session`).
Not part of ``stage=all``: started on its own.

The train_ppo artifact is found from the composed config as evaluate finds it (or from
``control.policy_file``: a train_ppo artifact's policy, or an adapt artifact's, the policy
fine-tuned to the session in the calibrated model, ``stage=adapt``); its environment is rebuilt
from the artifact's lineage (its manifest and those of the fit_model and align artifacts it was
trained on; for an adapted policy the calibrated model in place of the fit_model's) with
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

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.arm.limits import validate_limits
from pipeline.arm.safety import SafeSet
from pipeline.chain import control_hold
from pipeline.control.goals import GoalError, GoalSchedule, goal_schedule
from pipeline.control.loop import Outcome
from pipeline.control.policy import MM_PER_M, Deployment, deploy
from pipeline.control.results import goal_metrics
from pipeline.control.session import (
    STAGE,
    ControlInterrupted,
    report_session,
    run_session,
    set_aside_interrupted,
)
from pipeline.control.trajectory import (
    ReferenceSchedule,
    live_trajectory,
    trajectory_metrics,
    trajectory_of,
    trajectory_schedule,
)
from pipeline.data.sessions import arm_identity, session_run_id, session_tables, write_session
from pipeline.infra.artifacts import Artifact, ArtifactStore, ArtifactWriter, artifact_key, produce
from pipeline.rl.policy_io import best_seed, load_policy
from pipeline.schemas import ControlConfig, RobotKind
from pipeline.stages._deployed import policy_artifact, training_config
from pipeline.stages._environment import config_inputs, environment_of, recorded_paths
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
    if kind is RobotKind.sim and (settings.goal_topic or settings.trajectory_topic):
        raise GoalError("control.goal_topic and control.trajectory_topic need robot=ros2 (live "
                        "goals and references arrive over ROS 2)")
    if kind is RobotKind.ros2:
        if not float(robot.time_scale) > 0:
            raise ValueError(f"robot.time_scale={robot.time_scale} must be positive")
        from pipeline.ros2.node import require_rclpy

        require_rclpy()
    validate_limits(robot.limits, robot.n_valves)
    store = ArtifactStore(cfg.paths.artifact_dir)
    deployment = load_deployment(cfg, store)
    schedule = session_schedule(cfg, settings, deployment)
    spec, inputs = keys.control_spec(cfg)
    set_aside_interrupted(store, artifact_key(spec, inputs))
    outcomes: list[Outcome] = []

    def build(writer: ArtifactWriter) -> None:
        started = _dt.datetime.now().strftime("%Y%m%dT%H%M%S")
        recovery = Path(cfg.paths.output_dir) / "recovery" / f"{STAGE}-{writer.key}-{started}"
        record = run_session(robot, settings, deployment, schedule, recovery, spec)
        record.recorder.write(writer.file("periods.parquet"), record.periods)
        if isinstance(schedule, ReferenceSchedule):
            metrics = trajectory_metrics(record.periods, deployment.control_hz, schedule.settle_s,
                                         SafeSet.from_limits(robot.limits, robot.n_valves))
            metrics.to_parquet(writer.file("tracking.parquet"), index=False)
        else:
            metrics = goal_metrics(record.periods, 1.0 / deployment.control_hz)
            metrics.to_parquet(writer.file("goals.parquet"), index=False)
        writer.summary = report_session(writer.path, record, metrics, deployment, schedule, robot)
        keep_session_run(writer, record, deployment, robot, schedule)
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


def keep_session_run(writer: ArtifactWriter, record: Any, deployment: Deployment, robot: Any,
                     schedule: GoalSchedule) -> None:
    """The session as a run in collect's format (``run/``, :mod:`pipeline.data.sessions`): every
    command and pose frame, the goal or reference in force and, in the tables' metadata, the
    controller, the arm and the rates, so that ``dataset.sessions`` can join it to a model's
    data."""
    task = "track" if isinstance(schedule, ReferenceSchedule) else "reach"
    controller = {"policy": str(deployment.artifact.path), "stage": deployment.artifact.stage,
                  "seed": int(deployment.seed), "task": task, "goals": schedule.source}
    run = session_tables(record.periods, record.recorder.read_frames(),
                         session_run_id(STAGE, writer.key),
                         f"{STAGE}:{deployment.artifact.stage}/{deployment.artifact.key}"
                         f"#seed={deployment.seed}",
                         record.outcome.reason is None, int(robot.n_valves))
    provenance = {"stage": STAGE, "artifact": writer.key, "robot": robot.name,
                  "arm": arm_identity(robot.rating), "control_hz": float(robot.control_hz),
                  "controller": controller}
    write_session(writer.path, run, writer.spec, provenance)
    writer.summary["session_run"] = {"run_id": run.run_id, "commands": len(run.commands),
                                     "frames": len(run.mocap)}


def session_schedule(cfg: Any, settings: ControlConfig, deployment: Deployment
                     ) -> GoalSchedule:
    """The goals of ``control.goals`` / ``goals_csv`` / ``goal_topic``, or the reference of
    ``control.trajectory`` (a name of ``evaluation.references``, an inline shape, a CSV) with the
    preview the policy was trained with, each checked before anything moves; or the live
    reference of ``control.trajectory_topic`` (its points checked as they arrive)."""
    if settings.trajectory is None and not settings.trajectory_topic:
        return goal_schedule(settings, deployment.control_hz, deployment.workspace_m)
    own = "trajectory" if settings.trajectory is not None else "trajectory_topic"
    given = [name for name in ("goals", "goals_csv", "goal_topic", "trajectory")
             if name != own and getattr(settings, name)]
    if given:
        raise GoalError(f"control.{own}={getattr(settings, own)} is followed on its own; "
                        f"leave out {', '.join(f'control.{name}' for name in given)}")
    evaluation = cfg.evaluation
    settle = (evaluation.tracking_settle_seconds if settings.settle_s is None
              else settings.settle_s)
    if settings.trajectory_topic:
        return live_trajectory(str(settings.trajectory_topic), settings.duration_s,
                               float(settle), deployment.control_hz)
    named = OmegaConf.to_container(evaluation.references, resolve=True) or {}
    held_out = np.asarray(deployment.env_params.goal_set, np.float64)
    trained = deployment.train_goals_m
    trajectory = trajectory_of(settings.trajectory, named,
                               np.median(held_out, axis=0) * MM_PER_M, deployment.recorded)
    duration = (settings.duration_s if settings.duration_s is not None
                else trajectory.duration_s if trajectory.duration_s is not None
                else evaluation.tracking_seconds)
    return trajectory_schedule(trajectory, float(duration), float(settle), deployment.control_hz,
                               deployment.preview, np.concatenate([trained, held_out]),
                               float(settings.workspace_margin_mm))


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
    inputs = config_inputs(train_cfg, model, aligned)
    env, train_params, eval_params = environment_of(train_cfg, inputs)
    network, stacked, meta = load_policy(artifact.file("policy.msgpack"))
    num_seeds = int(meta.get("num_seeds", 1))
    evaluation = artifact.file("evaluation.parquet")
    seed = (best_seed(pd.read_parquet(evaluation), evaluation) if cfg.control.seed is None
            else int(cfg.control.seed))
    if not 0 <= seed < num_seeds:
        raise ValueError(f"control.seed={seed}: {artifact.file('policy.msgpack')} holds seeds "
                         f"0..{num_seeds - 1}")
    # the deadband and the hold are how this session deploys the policy, not how it was trained
    deadband, hold_gain, hold_backoff = control_hold(cfg)
    eval_params = eval_params.replace(deadband_m=np.float32(deadband),
                                      hold_gain=np.float32(hold_gain),
                                      hold_backoff=np.float32(hold_backoff))
    return deploy(artifact, seed, network, stacked, meta, env, train_params, eval_params,
                  control_hz, recorded_paths(inputs))
