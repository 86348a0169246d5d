"""``stage=control``: a trained policy drives the arm toward goals, and what it achieved.

- ``robot=ros2``: the arm (or the digital twin, ``stage=twin``) over ROS 2, in real time on the
  arm's clock (``robot.time_scale`` arm seconds per wall second for the twin).
- ``robot=sim``: the in-process simulated arm in simulated time, no ROS.

Both run :class:`pipeline.control.loop.ControlLoop`. The ``control`` artifact (keyed by the
policy's train_ppo key, the goals, the robot and its session label) holds ``periods.parquet``
(every control period, :mod:`pipeline.control.records`), ``goals.parquet`` (per goal,
:mod:`pipeline.control.results`), figures and ``report.md`` / ``report.html``. Rows are written
to Parquet chunks under ``<paths.output_dir>/recovery/control-<key>-<time>/`` while the session
runs, so a killed session keeps them; the folder is removed once the artifact holds them.

A session cut short (Ctrl-C, SIGTERM, the watchdog, a fault, an error) still fills the artifact,
marked ``interrupted``, and then fails with :class:`ControlInterrupted`; a later session with the
same config sets such an artifact aside (``<key>.interrupted-<time>``) and runs anew. With live
goals and no ``control.duration_s``, Ctrl-C is how a session ends: it is not an interruption.
"""

from __future__ import annotations

import datetime as _dt
import logging
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import keys
from pipeline.arm.limits import validate_limits
from pipeline.control.goals import GoalError, GoalSchedule, goal_schedule
from pipeline.control.loop import ControlLoop, Outcome, SimArm
from pipeline.control.policy import MM_PER_M, Deployment, load_deployment
from pipeline.control.records import PeriodRecorder
from pipeline.control.results import (
    goal_metrics,
    latency_summary,
    make_figures,
    write_control_report,
)
from pipeline.data.raw import CollectionInterrupted
from pipeline.infra.artifacts import Artifact, ArtifactStore, ArtifactWriter, artifact_key, produce
from pipeline.ros2.gate import CommandGate
from pipeline.ros2.node import StopSignals
from pipeline.schemas import RobotKind
from pipeline.validation import validate_config

log = logging.getLogger(__name__)
STAGE = "control"


class ControlInterrupted(CollectionInterrupted):
    """A session was cut short; what was recorded is in the artifact, marked interrupted."""


def _set_aside_interrupted(store: ArtifactStore, key: str) -> None:
    with store.lock(STAGE, key):
        existing = store.find(STAGE, key)
        if existing is None or not existing.manifest.get("summary", {}).get("interrupted"):
            return
        aside = store.set_aside(existing, "interrupted")
        log.warning("control: the artifact for this config was interrupted; moved it to %s and "
                    "running anew", aside)


def control(cfg: Any) -> Artifact:
    """Run ``control.policy`` (or ``control.policy_file``) on ``cfg.robot``; see the module doc."""
    validate_config(cfg)  # also when called without the entry point (scripts, benchmarks)
    robot = cfg.robot
    kind = RobotKind(robot.kind)
    if kind not in (RobotKind.sim, RobotKind.ros2):
        raise ValueError(f"stage=control drives an arm: robot=ros2 (or the twin) or robot=sim; "
                         f"got robot={robot.name} (recorded data)")
    if kind is RobotKind.sim and cfg.control.goal_topic:
        raise GoalError("control.goal_topic needs robot=ros2 (live goals arrive over ROS 2)")
    if kind is RobotKind.ros2:
        if not float(robot.time_scale) > 0:
            raise ValueError(f"robot.time_scale={robot.time_scale} must be positive")
        from pipeline.ros2.node import require_rclpy

        require_rclpy()
    validate_limits(robot.limits, robot.n_valves)
    store = ArtifactStore(cfg.paths.artifact_dir)
    deployment = load_deployment(cfg, store)
    schedule = goal_schedule(cfg.control, deployment.control_hz, deployment.workspace_m)
    spec, inputs = keys.control_spec(cfg)
    _set_aside_interrupted(store, artifact_key(spec, inputs))
    outcomes: list[Outcome] = []

    def build(writer: ArtifactWriter) -> None:
        outcomes.append(run_session(cfg, deployment, schedule, writer, spec))

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


def run_session(cfg: Any, deployment: Deployment, schedule: GoalSchedule, writer: ArtifactWriter,
                spec: dict[str, Any]) -> Outcome:
    """Run the loop on the configured arm and fill ``writer``."""
    robot, control_cfg = cfg.robot, cfg.control
    kind = RobotKind(robot.kind)
    gate = CommandGate.for_robot(robot)  # robot.limits inside the arm's rating
    started = _dt.datetime.now().strftime("%Y%m%dT%H%M%S")
    recovery = Path(cfg.paths.output_dir) / "recovery" / f"{STAGE}-{writer.key}-{started}"
    obs_dim = int(deployment.env.obs_dim)
    recorder = PeriodRecorder(recovery, obs_dim, spec, {"stage": STAGE, "robot": robot.name,
                                                        "recovery": True})
    log.info("control: periods are saved to %s every %s s while running", recovery,
             control_cfg.flush_every_s)
    with StopSignals() as signals:
        if kind is RobotKind.sim:
            arm = SimArm(robot, int(control_cfg.arm_seed), gate, signals)
            outcome = ControlLoop(deployment, schedule, gate, arm, recorder, control_cfg,
                                  robot).run()
        else:
            from pipeline.control.ros_arm import RosArm
            from pipeline.ros2.node import arm_domain, ros_node

            with ros_node(str(control_cfg.node_name), arm_domain(robot)) as (node, executor):
                arm = RosArm(node, executor, robot, control_cfg, gate, signals)
                outcome = ControlLoop(deployment, schedule, gate, arm, recorder, control_cfg,
                                      robot).run()
    periods = recorder.read_all()
    if periods.empty or not (periods["goal_index"] >= 0).any():
        raise ControlInterrupted(f"control: {outcome.reason or 'no goal arrived'}, before the "
                                 f"policy commanded anything. The preload was commanded; nothing "
                                 f"to keep") from outcome.error
    recorder.write(writer.file("periods.parquet"), periods)
    period_s = 1.0 / deployment.control_hz
    metrics = goal_metrics(periods, period_s)
    metrics.to_parquet(writer.file("goals.parquet"), index=False)
    figures = make_figures(writer.path / "figures", periods, robot.limits)
    latency = latency_summary(periods)
    summary: dict[str, Any] = {
        "policy": str(deployment.artifact.path), "seed": deployment.seed,
        "robot": robot.name, "periods": int((periods["goal_index"] >= 0).sum()),
        "final_distance_mm": metrics["final_distance_mm"].round(3).tolist(),
        "time_to_1mm_s": [None if not np.isfinite(v) else float(v)
                          for v in metrics["time_to_1mm_s"]],
        **latency, "preload_acknowledged": outcome.preload_acknowledged,
    }
    if outcome.reason is not None:
        summary["interrupted"] = outcome.reason
    summary["missed_periods"], summary["held_periods"] = outcome.missed_periods, outcome.holds
    writer.summary = summary
    stalls = (f" **{outcome.missed_periods} period(s) missed after stalls** of the loop (no "
              f"command sent in them), {outcome.holds} period(s) held the last command (rows "
              f"with an `event` in periods.parquet)." if outcome.missed_periods or outcome.holds
              else "")
    served = "the goals were served with gaps." if stalls else "every goal served."
    header = [f"Policy `{deployment.artifact.path}` seed {deployment.seed}, on "
              f"robot={robot.name}; goals from {schedule.source}.",
              f"{summary['periods']} control periods at {deployment.control_hz:g} Hz; "
              + (f"**interrupted**: {outcome.reason}." if outcome.reason else served) + stalls,
              f"Median final distance {np.median(metrics['final_distance_mm']):.2f} mm over "
              f"{len(metrics)} goal(s); workspace (training goals, mm): "
              f"{np.round(deployment.workspace_m * MM_PER_M, 1).tolist()}."]
    write_control_report(writer.path, f"sorolearn control: robot={robot.name}", header, metrics,
                         latency, figures)
    shutil.rmtree(recovery)  # the artifact's temporary folder now holds every row
    log.info("control: %s", summary)
    return outcome
