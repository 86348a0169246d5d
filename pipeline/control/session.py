"""A control session: a trained policy drives the arm toward goals, and what it achieved.

- ``robot=ros2``: the arm (or the digital twin, ``stage=twin``) over ROS 2, in real time on the
  arm's clock (``robot.time_scale`` arm seconds per wall second for the twin).
- ``robot=sim``: the in-process simulated arm in simulated time, no ROS.

Both run :class:`pipeline.control.loop.ControlLoop`. The ``control`` artifact (keyed by the
policy's train_ppo key, the goals, the robot and its session label) holds ``periods.parquet``
(every control period, :mod:`pipeline.control.records`), ``goals.parquet`` (per goal,
:mod:`pipeline.control.results`) or, following a reference, ``tracking.parquet``
(:func:`pipeline.control.trajectory.trajectory_metrics`), figures and ``report.md`` /
``report.html``
(:func:`report_session`); the stage (:mod:`pipeline.stages.control`) writes it. Rows are written
to Parquet chunks in a recovery folder (``<paths.output_dir>/recovery/control-<key>-<time>/``)
while the session runs, so a killed session keeps them; the stage removes the folder once the
artifact holds them.

A session cut short (Ctrl-C, SIGTERM, the watchdog, a fault, an error) still fills the artifact,
marked ``interrupted``, and then fails with :class:`ControlInterrupted`; a later session with the
same config sets such an artifact aside (``<key>.interrupted-<time>``) and runs anew. With live
goals and no ``control.duration_s``, Ctrl-C is how a session ends: it is not an interruption.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.control.goals import GoalSchedule
from pipeline.control.loop import ControlLoop, LoopSettings, Outcome, SimArm
from pipeline.control.policy import MM_PER_M, Deployment
from pipeline.control.records import PeriodRecorder
from pipeline.control.results import (
    latency_summary,
    make_figures,
    tracking_figures,
    write_control_report,
)
from pipeline.control.trajectory import ReferenceSchedule
from pipeline.data.raw import CollectionInterrupted
from pipeline.evaluation.tracking import SCORES
from pipeline.infra.artifacts import ArtifactStore
from pipeline.ros2.gate import CommandGate
from pipeline.ros2.node import StopSignals
from pipeline.schemas import ControlConfig, RobotConfig, RobotKind

log = logging.getLogger(__name__)
STAGE = "control"


class ControlInterrupted(CollectionInterrupted):
    """A session was cut short; what was recorded is in the artifact, marked interrupted."""


def set_aside_interrupted(store: ArtifactStore, key: str) -> None:
    """Rename an interrupted control artifact of ``key`` out of the way (``<key>.interrupted-
    <time>``), so that this config runs anew."""
    with store.lock(STAGE, key):
        existing = store.find(STAGE, key)
        if existing is None or not existing.manifest.get("summary", {}).get("interrupted"):
            return
        aside = store.set_aside(existing, "interrupted")
        log.warning("control: the artifact for this config was interrupted; moved it to %s and "
                    "running anew", aside)


@dataclass
class SessionRecord:
    """A session's rows (``periods``, :mod:`pipeline.control.records`), how it ended, its recorder
    (whose :meth:`~pipeline.control.records.PeriodRecorder.write` writes the table with its
    metadata) and its recovery folder (to remove once the artifact holds the rows)."""

    periods: pd.DataFrame
    outcome: Outcome
    recorder: PeriodRecorder
    recovery: Path


def run_session(robot: RobotConfig, control: ControlConfig, deployment: Deployment,
                schedule: GoalSchedule, recovery: Path, spec: dict[str, Any]) -> SessionRecord:
    """Run the loop on ``robot`` (the simulated arm, or the arm over ROS 2), its rows saved to
    chunks in ``recovery`` while it runs; :class:`ControlInterrupted` when it ended before the
    policy commanded anything."""
    kind = RobotKind(robot.kind)
    gate = CommandGate.for_robot(robot)  # robot.limits inside the arm's rating
    obs_dim = int(deployment.env.obs_dim)
    recorder = PeriodRecorder(recovery, obs_dim, spec, {"stage": STAGE, "robot": robot.name,
                                                        "recovery": True})
    log.info("control: periods are saved to %s every %s s while running", recovery,
             control.flush_every_s)
    settings = LoopSettings.of(robot, control)
    with StopSignals() as signals:
        if kind is RobotKind.sim:
            arm = SimArm(robot, int(control.arm_seed), gate, signals)
            outcome = ControlLoop(deployment, schedule, gate, arm, recorder, settings).run()
        else:
            from pipeline.control.ros_arm import RosArm
            from pipeline.ros2.node import arm_domain, ros_node

            with ros_node(str(control.node_name), arm_domain(robot)) as (node, executor):
                arm = RosArm(node, executor, robot, control.goal_topic, gate, signals,
                             control.trajectory_topic)
                outcome = ControlLoop(deployment, schedule, gate, arm, recorder, settings).run()
    periods = recorder.read_all()
    if periods.empty or not (periods["goal_index"] >= 0).any():
        raise ControlInterrupted(f"control: {outcome.reason or 'no goal arrived'}, before the "
                                 f"policy commanded anything. The preload was commanded; nothing "
                                 f"to keep") from outcome.error
    return SessionRecord(periods, outcome, recorder, recovery)


def report_session(folder: Path, record: SessionRecord, metrics: pd.DataFrame,
                   deployment: Deployment, schedule: GoalSchedule, robot: RobotConfig
                   ) -> dict[str, Any]:
    """Figures and ``report.md`` / ``report.html`` of a session into ``folder``; returns the
    summary for the artifact's manifest. ``metrics``: :func:`goal_metrics` of its periods, or
    following a reference (a :class:`ReferenceSchedule`) its :func:`trajectory_metrics`."""
    periods, outcome = record.periods, record.outcome
    tracking = isinstance(schedule, ReferenceSchedule)
    figures = (tracking_figures(folder / "figures", periods, robot.limits, schedule.settle_s)
               if tracking else make_figures(folder / "figures", periods, robot.limits))
    latency = latency_summary(periods)
    summary: dict[str, Any] = {
        "policy": str(deployment.artifact.path), "seed": deployment.seed,
        "robot": robot.name, "periods": int((periods["goal_index"] >= 0).sum()),
        **(_tracking_summary(metrics, schedule) if tracking else _goal_summary(metrics)),
        **latency, "preload_acknowledged": outcome.preload_acknowledged,
    }
    if outcome.reason is not None:
        summary["interrupted"] = outcome.reason
    summary["missed_periods"], summary["held_periods"] = outcome.missed_periods, outcome.holds
    stalls = (f" **{outcome.missed_periods} period(s) missed after stalls** of the loop (no "
              f"command sent in them), {outcome.holds} period(s) held the last command (rows "
              f"with an `event` in periods.parquet)." if outcome.missed_periods or outcome.holds
              else "")
    what = "reference" if tracking else "goals"
    served = (f"the {what} {'was' if tracking else 'were'} served with gaps." if stalls
              else f"every {'period of the reference' if tracking else 'goal'} served.")
    ahead = (f" (observing {deployment.preview} reference points ahead)" if deployment.preview
             else "")
    header = [f"Policy `{deployment.artifact.path}` seed {deployment.seed}{ahead}, on "
              f"robot={robot.name}; {what} from {schedule.source}.",
              f"{summary['periods']} control periods at {deployment.control_hz:g} Hz; "
              + (f"**interrupted**: {outcome.reason}." if outcome.reason else served) + stalls]
    if tracking:
        row = metrics.iloc[0]
        header.append(f"After the first {schedule.settle_s:g} s: RMSE {row['rmse_mm']:.2f} mm, "
                      f"p95 {row['p95_mm']:.2f} mm, max {row['max_mm']:.2f} mm, lag "
                      f"{row['lag_s']:.2f} s, {100 * row['within_1mm']:.0f} % of the ticks "
                      f"within 1 mm; steady offset {row['offset_mm']:.2f} mm (x, y, z: "
                      f"{row['offset_x_mm']:.2f}, {row['offset_y_mm']:.2f}, "
                      f"{row['offset_z_mm']:.2f} mm); the command on the limits of "
                      f"robot.limits {100 * row['at_limits']:.0f} % of the periods.")
        section = ("Tracking", "after the settle time: errors in mm, lag in s (positive: the "
                             "path behind the reference), within_1mm a share of the ticks, "
                             "offset the mean of the path less the reference, at_limits the "
                             "share of the periods whose command lay on the limits (a valve "
                             "at p_min or p_max, or the sum at sum_max)")
    else:
        header.append(f"Median final distance {np.median(metrics['final_distance_mm']):.2f} mm "
                      f"over {len(metrics)} goal(s); workspace (training goals, mm): "
                      f"{np.round(deployment.workspace_m * MM_PER_M, 1).tolist()}.")
        section = ("Per goal", "distances in mm, times in arm seconds")
    write_control_report(folder, f"sorolearn control: robot={robot.name}", header, metrics,
                         latency, figures, section)
    log.info("control: %s", summary)
    return summary


def _goal_summary(metrics: pd.DataFrame) -> dict[str, Any]:
    return {"final_distance_mm": metrics["final_distance_mm"].round(3).tolist(),
            "time_to_1mm_s": [None if not np.isfinite(v) else float(v)
                              for v in metrics["time_to_1mm_s"]]}


def _tracking_summary(metrics: pd.DataFrame, schedule: ReferenceSchedule) -> dict[str, Any]:
    row = metrics.iloc[0]
    return {"trajectory": schedule.source, "settle_s": schedule.settle_s,
            **{name: None if not np.isfinite(row[name]) else round(float(row[name]), 4)
               for name in SCORES}}
