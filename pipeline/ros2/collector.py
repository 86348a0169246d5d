"""``collect`` with ``robot=ros2``: play the exploration on the arm over ROS 2 and record it.

Each of ``robot.num_runs`` runs is one :func:`pipeline.arm.exploration.exploration_run` (same draws as
``robot=sim`` with the same ``exploration.seed``), published command by command at
``control_hz`` on ``robot.command_topic``, while every pose on ``robot.pose_topic`` is recorded.

Clocks: a run's ``t = 0`` is the publish time of its first command. Command rows carry their
publish time, mocap rows the pose's header stamp (``robot.stamp_field``), both on the ROS clock
(system time; when the motion capture runs on another computer, synchronise the clocks, e.g.
chrony). Times are multiplied by ``robot.time_scale`` so they are in the arm's seconds.

Safety: every command passes :class:`pipeline.ros2.gate.CommandGate` right before it is
published. On SIGINT/SIGTERM (:class:`pipeline.ros2.node.StopSignals`), on an exception, when the
watchdog sees no pose for ``robot.watchdog_s`` and at the end, the preload is published and its
delivery awaited (``robot.stop_timeout_s``) before the node is destroyed.

Nothing recorded is lost: rows go to Parquet chunks (:class:`pipeline.ros2.recorder.
ChunkedRecorder`) every ``robot.flush_every_s`` and at the end of each run, in the recovery
folder the stage names (``<paths.output_dir>/recovery/collect-<key>-<time>/``). The tables are
read back from the chunks (:class:`RosCollection`); an interrupted session still returns them (the
cut run with ``complete = False``) with an :class:`Interruption`, which ``collect`` writes and then
turns into a non-zero exit. The stage removes the recovery folder once the artifact holds the
data; after a hard kill (SIGKILL, power loss) it is what remains.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.arm.exploration import exploration_plan
from pipeline.data.raw import STAGE, CollectionInterrupted
from pipeline.data.ros_messages import (
    NS_PER_S,
    is_finite,
    message_class,
    read_position,
    read_stamp_ns,
    write_pressures,
)
from pipeline.infra.stalls import MissedPeriods
from pipeline.ros2.gate import CommandGate
from pipeline.ros2.handshake import HandshakeListener, handshake_problem
from pipeline.ros2.node import (
    ArmRefused,
    StopSignals,
    arm_domain,
    qos_profile,
    require_rclpy,
    ros_node,
)
from pipeline.ros2.recorder import ChunkedRecorder
from pipeline.schemas import ExplorationConfig, Ros2RobotConfig

log = logging.getLogger(__name__)
_SPIN_SLICE_S = 0.005  # wall: longest wait inside the executor, so stops and deadlines are seen
_SETTLE_S = 0.1  # wall: spin this long after the preload so it goes out even if not acknowledged


@dataclass
class Interruption:
    """Why a session stopped early; ``error`` is the exception behind it, if any."""

    reason: str
    error: BaseException | None = None


class _Stop(Exception):
    """Ends the recording early (a stop signal or the watchdog)."""


class ArmFault(ArmRefused):
    """The arm's streams cannot be trusted: two pose sources, a changed frame, clocks apart, a
    second listener of the commands."""


_CLOCK_TOLERANCE_S = 0.01  # wall: a pose stamped later than its receipt by more: clocks apart
_CLOCK_WINDOW_S = 1.0  # wall: latencies judged over the poses received in this span
_SOURCES_EVERY_S = 0.5  # wall: how often the pose topic's publishers are counted
# wall: a mismatch must last this long (graph discovery) to refuse, and a match to start (a
# second twin or listener is discovered a little after the first)
_HANDSHAKE_GRACE_S = 1.0


class ClockCheck:
    """Pose latency (receipt - header stamp, wall s) as a check of the clocks.

    A latency below ``-tolerance_s`` (a pose from the future) is refused at once; above
    ``max_latency_s`` it is refused once every pose received over ``window_s`` of receipts was
    that late: poses queued behind a stall of this process arrive at once with large latencies,
    but the fresh ones after them are on time, whereas clocks apart stay apart.
    """

    def __init__(self, max_latency_s: float, tolerance_s: float = _CLOCK_TOLERANCE_S,
                 window_s: float = _CLOCK_WINDOW_S):
        self.max_latency_s, self.tolerance_s, self.window_s = max_latency_s, tolerance_s, window_s
        self._recent: list[tuple[float, float]] = []  # (receipt s, latency s), oldest first

    def problem(self, stamp_ns: int, receipt_ns: int) -> str | None:
        """Why this pose shows the clocks apart, or None."""
        receipt, latency = receipt_ns / NS_PER_S, (receipt_ns - stamp_ns) / NS_PER_S
        if latency < -self.tolerance_s:
            return (f"a pose stamped {-latency:.3f} s after it was received: the motion "
                    f"capture's clock (its header stamps) runs ahead of this computer's ROS clock")
        self._recent.append((receipt, latency))
        while self._recent and self._recent[0][0] < receipt - self.window_s:
            self._recent.pop(0)
        spans = self._recent[-1][0] - self._recent[0][0] >= 0.9 * self.window_s
        best = min(late for _, late in self._recent)
        if spans and best > self.max_latency_s:
            return (f"every pose over the last {self.window_s:g} s arrived at least {best:.3f} s "
                    f"after its header stamp, above robot.max_pose_latency_s="
                    f"{self.max_latency_s:g} s: the motion capture's clock runs behind this "
                    f"computer's ROS clock (synchronise them, e.g. chrony) or the link lags")
        return None


@dataclass
class RunRecord:
    run_id: str
    start_ns: int  # ROS time of the first command's publish
    end_ns: int  # planned end: start + commands / control_hz (wall)
    complete: bool = False
    frames: int = 0


@dataclass
class LinkStats:
    """Timing of the link, in wall milliseconds (see :meth:`Session.link_summary`)."""

    receipt_intervals_ms: list[float] = field(default_factory=list)
    pose_latency_ms: list[float] = field(default_factory=list)  # receipt - header stamp
    command_lateness_ms: list[float] = field(default_factory=list)  # publish - schedule
    poses_out_of_order: int = 0
    poses_outside_runs: int = 0


class ArmLink:
    """The collect node's command publisher and pose subscriber."""

    def __init__(self, node: Any, executor: Any, robot: Ros2RobotConfig):
        self._node, self._executor, self._robot = node, executor, robot
        # plain strings: a config node read per pose would cost more than the pose itself
        self._command_field = str(robot.command_field)
        self._stamp_field, self._position_field = str(robot.stamp_field), str(robot.position_field)
        self._command_type = message_class(robot.command_type)
        self._publisher = node.create_publisher(self._command_type, robot.command_topic,
                                                qos_profile(robot.command_qos))
        node.create_subscription(message_class(robot.pose_type), robot.pose_topic, self._on_pose,
                                 qos_profile(robot.pose_qos))
        self.handshake = HandshakeListener(node, robot)
        self.published = 0  # commands published
        self.poses: list[tuple[int, int, tuple[float, float, float]]] = []  # stamp, receipt, xyz
        self.last_pose_at: float | None = None  # monotonic s of the last pose's callback
        self.newest_stamp_ns: int | None = None  # the newest pose's stamp (ROS ns)
        self.frame_id: str | None = None
        self.frame_id_changed: str | None = None  # the first other frame_id seen, if any

    def now_ns(self) -> int:
        return self._node.get_clock().now().nanoseconds

    def _on_pose(self, message: Any) -> None:
        receipt = self.now_ns()
        stamp = read_stamp_ns(message, self._stamp_field) if self._stamp_field else receipt
        self.poses.append((stamp, receipt, read_position(message, self._position_field)))
        self.last_pose_at = time.monotonic()
        if self.newest_stamp_ns is None or stamp > self.newest_stamp_ns:
            self.newest_stamp_ns = stamp
        frame_id = str(getattr(getattr(message, "header", None), "frame_id", ""))
        if self.frame_id is None:
            self.frame_id = frame_id
        elif frame_id != self.frame_id and self.frame_id_changed is None:
            self.frame_id_changed = frame_id

    def take_poses(self) -> list[tuple[int, int, tuple[float, float, float]]]:
        poses, self.poses = self.poses, []
        return poses

    def silence_s(self, watchdog_wall_s: float) -> float:
        """Wall seconds since the newest pose was taken (its stamp, not when its callback ran:
        poses queued behind a stall of this process are as old as their stamps say); past
        ``watchdog_wall_s`` the poses already queued are taken in first, so only a real silence
        counts."""
        silent = (self.now_ns() - self.newest_stamp_ns) / NS_PER_S
        if silent > watchdog_wall_s:
            for _ in range(int(self._robot.pose_qos.depth)):
                self.spin_once(0.0)
            silent = (self.now_ns() - self.newest_stamp_ns) / NS_PER_S
        return silent

    def spin_once(self, timeout_s: float) -> None:
        self._executor.spin_once(timeout_sec=timeout_s)

    def publish(self, pressures: np.ndarray) -> int:
        """Publish ``pressures`` [kPa] (already gated); return the ROS time of the publish [ns]."""
        message = self._command_type()
        write_pressures(message, self._command_field, pressures)
        stamp = self.now_ns()
        self._publisher.publish(message)
        self.published += 1
        return stamp

    def subscribers(self) -> int:
        return self._publisher.get_subscription_count()

    def wait_for_acks(self, timeout_s: float) -> bool:
        """True once every reliable subscriber acknowledged what was published."""
        from rclpy.duration import Duration

        return self._publisher.wait_for_all_acked(Duration(nanoseconds=int(timeout_s * NS_PER_S)))

    def command_subscribers(self) -> list[str]:
        """Node names of every subscriber of the command topic."""
        infos = self._node.get_subscriptions_info_by_topic(self._robot.command_topic)
        return sorted(str(info.node_name) for info in infos)

    def pose_publishers(self) -> list[str]:
        """``node (type)`` of every publisher on the pose topic, for error messages."""
        infos = self._node.get_publishers_info_by_topic(self._robot.pose_topic)
        return [f"{info.node_name} ({info.topic_type})" for info in infos]


class Session:
    """One collect session on the arm: runs played out, streams recorded, a safe stop."""

    def __init__(self, robot: Ros2RobotConfig, link: ArmLink, gate: CommandGate,
                 recorder: ChunkedRecorder | None,
                 signals: StopSignals, clock: Callable[[], float] = time.monotonic):
        self.robot, self.link, self.gate, self.recorder = robot, link, gate, recorder
        self.signals = signals
        self.clock = clock  # wall seconds (monotonic); injectable for tests
        self.time_scale = float(robot.time_scale)
        self.period_wall_s = 1.0 / (float(robot.control_hz) * self.time_scale)
        self.watchdog_wall_s = float(robot.watchdog_s) / self.time_scale
        self.flush_every_s = float(robot.flush_every_s)
        self.runs: list[RunRecord] = []
        self.stats = LinkStats()
        self.preload_acknowledged: bool | None = None
        self.missed = MissedPeriods(self.period_wall_s, int(robot.max_missed_periods))
        self.stalls: list[dict[str, Any]] = []  # periods skipped after a stall, per event
        self.clock_check = ClockCheck(float(robot.max_pose_latency_s))
        self._next_sources = 0.0
        self.guard_node: str | None = None  # the node that answered the handshake
        self._last_stamp = -1
        self._last_receipt: int | None = None
        self._next_flush = self.clock() + self.flush_every_s

    # ---- start ---------------------------------------------------------------------------------
    def wait_for_arm(self) -> None:
        """Wait for a first pose, the arm side's handshake and its subscription to the commands,
        all matching for ``_HANDSHAKE_GRACE_S`` (what is discovered late counts too), and the
        clocks of the poses received meanwhile; refuse (:class:`ArmRefused`, one line) if they
        lack or do not match."""
        robot = self.robot
        deadline = self.clock() + float(robot.startup_timeout_s)
        mismatch_since, matched_since, problem = None, None, None
        while True:
            if self.signals.received:
                raise ArmRefused(f"stopped by {self.signals.received} before the first command; "
                                 f"nothing was commanded or recorded")
            answer = self.link.handshake.answer
            if (self.link.last_pose_at is not None and answer is not None
                    and self.link.subscribers() > 0):
                problem = handshake_problem(answer, robot, self.link.command_subscribers())
                if problem is None:
                    matched_since = matched_since or self.clock()
                    if self.clock() - matched_since >= _HANDSHAKE_GRACE_S:
                        break
                    self.link.spin_once(_SPIN_SLICE_S)
                    continue
                matched_since = None
                mismatch_since = mismatch_since or self.clock()
                if self.clock() - mismatch_since > _HANDSHAKE_GRACE_S:
                    raise ArmRefused(f"refusing to publish on {robot.command_topic}: {problem}")
            if self.clock() > deadline:
                raise ArmRefused(problem or self._startup_problem())
            self.link.spin_once(_SPIN_SLICE_S)
        self.guard_node = str(answer["node"])
        self.check_sources(force=True)
        for stamp, receipt, _ in self.link.poses:  # the clocks, before the first command
            self.check_clock(stamp, receipt)
        log.info("collect: arm ready (poses on %s from frame '%s'; the %s '%s' answers for the "
                 "arm with the rating %s and is the only subscriber of %s)", robot.pose_topic,
                 self.link.frame_id, answer["role"], answer["node"], answer["rating"],
                 robot.command_topic)

    def _startup_problem(self) -> str:
        robot = self.robot
        domain = arm_domain(robot)
        where = (f"ROS domain {domain}" if domain is not None
                 else "the ROS domain of ROS_DOMAIN_ID")
        if robot.rehearsal:
            hint = (f"is the digital twin (`python -m pipeline stage=twin robot=ros2`) running? "
                    f"Rehearsals run on robot.rehearsal_domain_id={robot.rehearsal_domain_id}")
        else:
            hint = (f"are the arm's driver and the guard (`python -m pipeline stage=guard "
                    f"robot=ros2`) running on {where}? (a rehearsal on the twin needs "
                    f"robot.rehearsal=true)")
        if self.link.last_pose_at is None:
            publishers = self.link.pose_publishers()
            return (f"no pose on {robot.pose_topic} ({robot.pose_type}) within "
                    f"robot.startup_timeout_s={robot.startup_timeout_s} s: {hint}, with a QoS "
                    f"compatible with robot.pose_qos? Publishers seen: {publishers or 'none'}")
        if self.link.handshake.answer is None:
            unreadable = self.link.handshake.unreadable
            return (f"no answer from a guard on {robot.guard.handshake_topic} within "
                    f"robot.startup_timeout_s={robot.startup_timeout_s} s"
                    + (f" (unreadable: {unreadable})" if unreadable else "")
                    + f": {hint}; commands are published only through the guard")
        return (f"nobody subscribes to {robot.command_topic} ({robot.command_type}) within "
                f"robot.startup_timeout_s={robot.startup_timeout_s} s: {hint}")

    # ---- runs ----------------------------------------------------------------------------------
    def play(self, plan: Iterable[tuple[str, np.ndarray]]) -> Interruption | None:
        """Play every run of ``plan``; stop at the first signal, watchdog timeout or error."""
        try:
            for run_id, commands in plan:
                self._play_run(run_id, commands)
        except _Stop as stop:
            return Interruption(str(stop))
        except Exception as err:  # any failure: stop safely, keep the data, report it
            log.error("collect: %s: %s; stopping safely", type(err).__name__, err)
            return Interruption(f"{type(err).__name__}: {err}", err)
        return None

    def _play_run(self, run_id: str, commands: np.ndarray) -> None:
        """Publish ``commands`` one per period. No catch-up: a period whose tick is more than a
        period past (a stall) gets no command; the current one holds the last command (a stall
        event in the summary); more than ``robot.max_missed_periods`` in a row stop the run."""
        start, last = None, None
        i = 0
        while i < len(commands):
            projected = self.gate.project(commands[i])  # ahead of the deadline: it takes a while
            if start is not None:
                due = start + i * self.period_wall_s
                self._wait_until(due)
                missed = self._missed(run_id, i, self.clock() - due)
                if missed:
                    i += missed  # the overdue commands are never sent
                    if i >= len(commands):
                        break
                    projected = last  # this period holds the last command
                else:
                    self.missed.reset()
            due = start + i * self.period_wall_s if start is not None else self.clock()
            safe = self.gate.check(projected)
            stamp = self.link.publish(safe)
            self.stats.command_lateness_ms.append((self.clock() - due) * 1e3)
            if start is None:
                start = due
                end = stamp + round(len(commands) * self.period_wall_s * NS_PER_S)
                self.runs.append(RunRecord(run_id, stamp, end))
                log.info("collect: run %s started (%d commands at %g Hz)", run_id, len(commands),
                         float(self.robot.control_hz))
            self.recorder.add_command(run_id, self._run_time(stamp), safe)
            last = safe
            i += 1
        self._wait_until(start + len(commands) * self.period_wall_s)  # the last command's period
        self._drain()
        run = self.runs[-1]
        run.complete = True
        self.recorder.flush()
        log.info("collect: run %s complete (%d commands, %d frames)", run_id, len(commands),
                 run.frames)

    def _missed(self, run_id: str, index: int, late_wall_s: float) -> int:
        """Periods missed when command ``index`` is ``late_wall_s`` past its tick (0: on time);
        recorded as a stall event; too many in a row stop the session."""
        missed = self.missed.count(late_wall_s)
        if not missed:
            return 0
        late_s = late_wall_s * self.time_scale
        self.stalls.append({"run_id": run_id, "command": index, "late_s": round(late_s, 4),
                            "missed_periods": missed})
        if self.missed.exceeded:
            raise _Stop(f"the command loop woke {late_s:.2f} s after the tick of command {index} "
                        f"of run {run_id}: {self.missed.in_row} periods missed in a row, more "
                        f"than robot.max_missed_periods={self.missed.max_in_row} (the process "
                        f"stalled or its clock jumped)")
        log.warning("collect: woke %.3f s after the tick of command %d: %d command(s) skipped, "
                    "holding the last command", late_s, index, missed)
        return missed

    def _run_time(self, stamp_ns: int) -> float:
        """Seconds on the current run's clock (arm seconds) of a ROS time."""
        return (stamp_ns - self.runs[-1].start_ns) / NS_PER_S * self.time_scale

    def _wait_until(self, deadline: float) -> None:
        """Receive poses until the monotonic ``deadline``, checking stops and flushing chunks."""
        while True:
            self._check()
            remaining = deadline - self.clock()
            if remaining <= 0:
                return
            self.link.spin_once(min(remaining, _SPIN_SLICE_S))
            self._drain()
            if self.clock() >= self._next_flush:
                self.recorder.flush()
                self._next_flush += self.flush_every_s

    def check_sources(self, force: bool = False) -> None:
        """One pose source in one frame: :class:`ArmFault` when the pose topic has more than one
        publisher (a twin left running beside the motion capture, a bag replay) or the poses'
        ``frame_id`` changed. The publishers are counted every ``_SOURCES_EVERY_S``."""
        robot = self.robot
        if self.link.frame_id_changed is not None:
            raise ArmFault(f"the poses on {robot.pose_topic} changed frame_id from "
                           f"'{self.link.frame_id}' to '{self.link.frame_id_changed}': two "
                           f"sources of poses? (a digital twin left running, a bag replay)")
        now = self.clock()
        if not force and now < self._next_sources:
            return
        self._next_sources = now + _SOURCES_EVERY_S
        listeners = self.link.command_subscribers()
        if len(listeners) > 1:
            raise ArmFault(f"{len(listeners)} subscribers of {robot.command_topic}: "
                           f"{', '.join(listeners)}; only the guard (or the twin) may listen")
        if self.guard_node is not None and listeners != [self.guard_node]:
            raise ArmFault(f"the guard '{self.guard_node}' no longer subscribes to "
                           f"{robot.command_topic} (stopped or killed): nothing guards the "
                           f"valves")
        publishers = self.link.pose_publishers()
        if len(publishers) > 1:
            raise ArmFault(f"{len(publishers)} publishers on {robot.pose_topic}: "
                           f"{', '.join(publishers)}; exactly one source of poses is required "
                           f"(stop the digital twin or the bag replay beside the motion capture)")

    def check_clock(self, stamp_ns: int, receipt_ns: int) -> None:
        problem = self.clock_check.problem(stamp_ns, receipt_ns)
        if problem is not None:
            raise ArmFault(f"clocks: {problem} (pose topic {self.robot.pose_topic})")

    def _check(self) -> None:
        if self.signals.received:
            raise _Stop(f"{self.signals.received} received")
        self.check_sources()
        silent = self.link.silence_s(self.watchdog_wall_s)
        if silent > self.watchdog_wall_s:
            raise _Stop(f"mocap watchdog: no pose on {self.robot.pose_topic} for "
                        f"{silent * self.time_scale:.2f} s (robot.watchdog_s="
                        f"{self.robot.watchdog_s})")

    def _drain(self) -> None:
        """Move received poses into the current run (by stamp); count what does not fit."""
        run = self.runs[-1] if self.runs else None
        for stamp, receipt, xyz in self.link.take_poses():
            self.check_clock(stamp, receipt)
            if run is None or not run.start_ns <= stamp < run.end_ns:
                self.stats.poses_outside_runs += 1
                continue
            if stamp <= self._last_stamp:
                self.stats.poses_out_of_order += 1
                continue
            if self._last_receipt is not None and run.frames > 0:
                self.stats.receipt_intervals_ms.append((receipt - self._last_receipt) / 1e6)
            self._last_stamp, self._last_receipt = stamp, receipt
            self.stats.pose_latency_ms.append((receipt - stamp) / 1e6)
            self.recorder.add_frame(run.run_id, self._run_time(stamp), xyz, is_finite(xyz))
            run.frames += 1

    # ---- stop ----------------------------------------------------------------------------------
    def stop_safely(self) -> None:
        """Publish the preload, give it a moment to go out, wait for its acknowledgement
        (nothing, if nothing was published: a refused start commands nothing)."""
        if self.link.published == 0:
            log.info("collect: nothing was commanded")
            return
        preload = self.gate.check(self.gate.preload)
        self.link.publish(preload)
        settle_until = self.clock() + _SETTLE_S
        while self.clock() < settle_until:
            self.link.spin_once(_SPIN_SLICE_S)
        # Poses from now on show the arm going to the preload, which no command row explains:
        # they are not recorded.
        # Fast DDS acknowledges reliable samples on its heartbeat, so this can take a second or
        # more although the sample itself arrives within milliseconds.
        self.preload_acknowledged = self.link.wait_for_acks(float(self.robot.stop_timeout_s))
        if self.preload_acknowledged:
            log.info("collect: commanded the preload %s kPa (acknowledged by %d subscriber(s))",
                     preload.tolist(), self.link.subscribers())
        else:
            log.warning("collect: commanded the preload %s kPa; its delivery was not acknowledged "
                        "within robot.stop_timeout_s=%s s (check that the valves went to it)",
                        preload.tolist(), self.robot.stop_timeout_s)

    def link_summary(self) -> dict[str, Any]:
        """Rates and latencies of the session (wall ms unless named otherwise) for the manifest."""

        def describe(values: list[float]) -> dict[str, float] | None:
            if not values:
                return None
            v = np.asarray(values)
            return {"n": len(v), "mean": float(v.mean()), "std": float(v.std()),
                    "median": float(np.median(v)), "p99": float(np.percentile(v, 99)),
                    "max": float(v.max())}

        intervals = self.stats.receipt_intervals_ms
        return {
            "time_scale": self.time_scale,
            "pose_frame_id": self.link.frame_id,
            "runs": [{"run_id": r.run_id, "start_ns": r.start_ns} for r in self.runs],
            "pose_receipt_rate_hz_wall": 1e3 / float(np.mean(intervals)) if intervals else None,
            "pose_receipt_interval_ms": describe(intervals),
            "pose_latency_ms": describe(self.stats.pose_latency_ms),
            "command_lateness_ms": describe(self.stats.command_lateness_ms),
            "poses_out_of_order": self.stats.poses_out_of_order,
            "poses_outside_runs": self.stats.poses_outside_runs,
            "preload_acknowledged": self.preload_acknowledged,
            "stalls": self.stalls,
            "missed_periods": int(sum(event["missed_periods"] for event in self.stalls)),
        }


# --------------------------------------------------------------------------------------------
# the collect stage's entry
# --------------------------------------------------------------------------------------------
@dataclass
class RosCollection:
    """What a session on the arm recorded, for the stage to write as a ``collect`` artifact:
    the raw tables (:mod:`pipeline.data.schemas` ``COMMANDS``, ``MOCAP``, ``RUNS``), the plan's
    figure key (:func:`pipeline.arm.exploration.plot_walks`), the link's timing
    (:meth:`Session.link_summary`), why it stopped early (None: every run completed) and the
    recovery folder of its chunks (to remove once the artifact holds the rows)."""

    commands: pd.DataFrame
    mocap: pd.DataFrame
    runs: pd.DataFrame
    figure_key: Any
    link: dict[str, Any]
    interruption: Interruption | None
    recovery: Path


def record(robot: Ros2RobotConfig, exploration: ExplorationConfig, recovery: Path,
           spec: dict[str, Any]) -> RosCollection:
    """Run a session on the arm, its rows saved to chunks in ``recovery`` while it runs, and
    return what it recorded (see module doc)."""
    if not float(robot.time_scale) > 0:
        raise ValueError(f"robot.time_scale={robot.time_scale} must be positive")
    plan = exploration_plan(exploration, robot.limits, robot.n_valves, robot.num_runs)
    gate = CommandGate.for_robot(robot)
    recorder = ChunkedRecorder(recovery, spec, {"stage": STAGE, "robot": robot.name,
                                                "recovery": True})
    log.info("collect: streams are saved to %s every %s s while recording", recovery,
             robot.flush_every_s)

    with (StopSignals() as signals,
          ros_node(robot.node_name, arm_domain(robot)) as (node, executor)):
        session = Session(robot, ArmLink(node, executor, robot), gate, recorder, signals)
        try:
            try:
                session.wait_for_arm()
            except ArmRefused:
                shutil.rmtree(recovery, ignore_errors=True)  # nothing was recorded
                raise
            interruption = session.play(
                (f"ros2-{i:03d}", run) for i, run in enumerate(plan.commands))
        finally:
            try:
                session.stop_safely()
            finally:
                recorder.flush()

    commands, mocap = recorder.read_all()
    if commands.empty or mocap.empty:
        reason = interruption.reason if interruption else "no pose arrived during the runs"
        raise CollectionInterrupted(f"collect: nothing to keep ({len(commands)} commands, {len(mocap)} "
                           f"frames recorded): {reason}") from (interruption and interruption.error)
    source = f"{robot.pose_topic} [{session.link.frame_id}]"
    runs = pd.DataFrame([
        {"run_id": r.run_id, "source": source, "complete": r.complete,
         "n_commands": int((commands["run_id"] == r.run_id).sum()), "n_frames": r.frames}
        for r in session.runs])
    return RosCollection(commands, mocap, runs, plan.figure_key, session.link_summary(),
                         interruption, recovery)


def collect_ros2(robot: Ros2RobotConfig, exploration: ExplorationConfig, recovery: Path,
                 spec: dict[str, Any]) -> RosCollection:
    """Record ``robot.num_runs`` exploration runs on the arm; see the module doc.

    Its ``interruption`` is None when every run completed, else the :class:`Interruption` (the
    tables then hold the runs recorded so far, the last one marked incomplete).
    """
    require_rclpy()
    return record(robot, exploration, recovery, spec)
