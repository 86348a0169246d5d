"""The control loop of ``stage=control``: one implementation for every arm.

Each control period ``k`` (``1 / robot.control_hz`` arm seconds; the settings: :class:`LoopSettings`):

1. wait until the period's tick, taking every pose frame that arrives (a jump above
   ``control.max_pose_jump_mm`` between consecutive frames stops the session);
2. take the latest pose; one older than ``robot.watchdog_s`` stops the session;
3. the observation, exactly as the training environment builds it
   (:func:`pipeline.rl.envs.observation.observe`; the period's goal and, for a policy trained with
   a preview, the goals of the next periods: :meth:`GoalSchedule.preview`; following a
   reference, :class:`pipeline.control.trajectory.TrajectorySchedule`, or one whose points
   arrive live, :class:`~pipeline.control.trajectory.LiveTrajectory`), the deterministic action
   with the recurrent carry (within ``env.deadband_m`` of a goal, the hold's command), the
   pressures (the environment's action mapping): one jitted call,
   compiled before the first command (:class:`pipeline.control.policy.Deployment`); a
   non-finite output stops it;
4. the command gate (:class:`pipeline.ros2.gate.CommandGate`: projection onto ``robot.limits``,
   float64 check), publish, and a row to the records.

No catch-up: never more than one command per period. When the loop wakes more than one period
after a tick (a stall of the process, swap, a forward step of the clock), the overdue periods are
skipped, not run back to back: the current period holds the last safe command (a row with
``event = "late"`` and ``missed_periods``), and the policy acts again only on a pose stamped after
the stall (until one arrives each period holds, ``event = "stale_pose"``). More than
``robot.max_missed_periods`` periods missed in a row: the preload and a :class:`ControlFault`.
A clock that steps back holds the command until its tick comes again.

At the end of the goals, on a stop signal, the watchdog, a fault or any exception the arm is
sent the preload (:meth:`Arm.stop_safely`: published last, its delivery awaited on ROS 2).

An :class:`Arm` is the in-process simulated arm in simulated time (:class:`SimArm`) or the arm
over ROS 2 in real time (:class:`pipeline.control.ros_arm.RosArm`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from pipeline.control.goals import GoalSchedule, workspace_problem
from pipeline.control.policy import MM_PER_M, Deployment
from pipeline.control.records import PeriodRecorder
from pipeline.infra.stalls import MissedPeriods
from pipeline.ros2.gate import CommandGate
from pipeline.schemas import (
    ControlConfig,
    RobotConfig,
    Ros2RobotConfig,
    SimRobotConfig,
    TwinConfig,
)

log = logging.getLogger(__name__)


class Stop(Exception):
    """Ends the session early: a stop signal or the watchdog."""


class ControlFault(RuntimeError):
    """The policy or the pose went wrong (non-finite output, a pose jump)."""


Frame = tuple[float, float, np.ndarray]  # (stamp, receipt) in arm seconds, position [3] m


class Arm(Protocol):
    """What the loop needs of an arm; times in arm seconds since :meth:`start`."""

    def start(self) -> None: ...  # wait until the arm is ready; t = 0 from here

    def now(self) -> float: ...

    def advance(self, until: float) -> None: ...  # a slice of waiting (raises Stop on a stop)

    def receive(self) -> None: ...  # take in what already arrived, without waiting

    def take_frames(self) -> list[Frame]: ...  # frames arrived since the last call, in order

    def take_goals(self) -> list[np.ndarray]: ...  # live goals [3] m arrived since the last call

    # live reference points (arm s they are due, [3] m) arrived since the last call; asked
    # only where the schedule takes them (control.trajectory_topic)
    def take_points(self) -> list[tuple[float, np.ndarray]]: ...

    def publish(self, pressures: np.ndarray) -> float: ...  # gated kPa; returns the publish time

    def stop_safely(self) -> bool | None: ...  # the preload out; acknowledged? (None: n/a)


@dataclass
class Outcome:
    """How a session ended: ``reason`` None when every goal was served."""

    reason: str | None = None
    error: BaseException | None = None
    preload_acknowledged: bool | None = None
    periods: int = 0
    missed_periods: int = 0  # periods skipped after stalls (no command sent in them)
    holds: int = 0  # periods that held the last command (after a stall, for a fresh pose)


@dataclass(frozen=True)
class LoopSettings:
    """What the loop needs of the robot and ``control`` settings (see :meth:`of`)."""

    control_hz: float  # periods per arm second
    watchdog_s: float | None  # arm s: the oldest pose a period may act on (None: no watchdog)
    max_missed_periods: int  # periods late in a row before the preload and a ControlFault
    max_pose_jump_mm: float  # between consecutive frames: the preload and a ControlFault
    workspace_margin_mm: float  # live goals this far outside the training goals' box are allowed
    flush_every_s: float  # wall: rows written to Parquet chunks this often

    @classmethod
    def of(cls, robot: RobotConfig, control: ControlConfig) -> LoopSettings:
        """The settings of ``robot`` and ``control``: the watchdog and the missed periods of a
        ROS 2 robot (``robot.watchdog_s``, ``robot.max_missed_periods``); the simulated arm, in
        simulated time, has no watchdog and is never late (the ROS 2 robot's default bound)."""
        if isinstance(robot, Ros2RobotConfig):
            watchdog_s, max_missed = float(robot.watchdog_s), int(robot.max_missed_periods)
        else:
            watchdog_s, max_missed = None, int(Ros2RobotConfig.max_missed_periods)
        return cls(float(robot.control_hz), watchdog_s, max_missed,
                   float(control.max_pose_jump_mm), float(control.workspace_margin_mm),
                   float(control.flush_every_s))


class ControlLoop:
    def __init__(self, deployment: Deployment, schedule: GoalSchedule, gate: CommandGate,
                 arm: Arm, recorder: PeriodRecorder, settings: LoopSettings):
        self.deployment, self.schedule, self.gate, self.arm = deployment, schedule, gate, arm
        self.recorder = recorder
        self.period_s = 1.0 / float(settings.control_hz)
        watchdog = settings.watchdog_s
        self.watchdog_s = None if watchdog is None else float(watchdog)
        self.max_jump_m = float(settings.max_pose_jump_mm) / MM_PER_M
        self.margin_mm = float(settings.workspace_margin_mm)
        self.flush_every_s = float(settings.flush_every_s)
        self.missed = MissedPeriods(self.period_s, int(settings.max_missed_periods))
        self.holds = 0
        self._fresh_after: float | None = None  # a pose stamped after this, before acting again
        self._latest: Frame | None = None
        self._next_flush = time.monotonic() + self.flush_every_s

    # ---- frames --------------------------------------------------------------------------------
    def _take_frames(self) -> None:
        frames = self.arm.take_frames()
        self.recorder.add_frames(frames)  # every frame, also those the checks below skip
        for frame in frames:
            position = frame[2]
            if not np.all(np.isfinite(position)):
                continue  # a lost marker: the watchdog decides when that is too long
            if self._latest is not None:
                jump = float(np.linalg.norm(position - self._latest[2]))
                if jump > self.max_jump_m:
                    raise ControlFault(
                        f"pose jump of {jump * MM_PER_M:.1f} mm between frames at "
                        f"t={self._latest[0]:.3f} s and {frame[0]:.3f} s (above "
                        f"control.max_pose_jump_mm={self.max_jump_m * MM_PER_M:g}: a marker swap "
                        f"or occlusion?)")
            self._latest = frame

    def _take_goals(self, period: int) -> None:
        for goal in self.arm.take_goals():
            problem = workspace_problem(goal, self.deployment.workspace_m, self.margin_mm)
            if problem:
                log.error("control: live goal refused: %s", problem)
                continue
            log.info("control: new goal %s mm from period %d",
                     np.round(goal * MM_PER_M, 1).tolist(), period)
            self.schedule.add(period, goal)
        if not self.schedule.takes_points:
            return
        for due, point in self.arm.take_points():
            problem = (workspace_problem(point, self.deployment.workspace_m, self.margin_mm)
                       or self.schedule.add_point(due, point, period * self.period_s))
            if problem:
                log.error("control: reference point refused: %s", problem)

    def _wait_until(self, tick: float) -> None:
        while self.arm.now() < tick:
            self.arm.advance(tick)
            self._take_frames()
            if time.monotonic() >= self._next_flush:
                self.recorder.flush()
                self._next_flush += self.flush_every_s
        self._take_frames()

    def _pose(self, now: float) -> tuple[Frame, float]:
        if self._latest is None:
            raise Stop("no pose received before the first command")
        age = now - self._latest[0]
        if self.watchdog_s is not None and age > self.watchdog_s:
            # poses may be queued behind a stall of this process: take them in, then judge
            self.arm.receive()
            self._take_frames()
            age = now - self._latest[0]
        if self.watchdog_s is not None and age > self.watchdog_s:
            raise Stop(f"mocap watchdog: the latest pose is {age:.2f} s old (robot.watchdog_s="
                       f"{self.watchdog_s})")
        return self._latest, age

    # ---- the session ---------------------------------------------------------------------------
    def run(self) -> Outcome:
        """Serve the schedule; always end with the preload (see module doc)."""
        outcome = Outcome()
        try:
            self.arm.start()
            outcome.periods = self._periods()
        except Stop as stop:
            log.warning("control: %s; stopping safely", stop)
            outcome.reason = str(stop)
        except Exception as err:  # any failure: stop safely, keep the records, report it
            log.error("control: %s: %s; stopping safely", type(err).__name__, err)
            outcome.reason, outcome.error = f"{type(err).__name__}: {err}", err
        finally:
            try:
                outcome.preload_acknowledged = self.arm.stop_safely()
            finally:
                self.recorder.flush()
        if outcome.periods == 0:
            outcome.periods = self.recorder.periods
        outcome.missed_periods, outcome.holds = self.missed.total, self.holds
        return outcome

    def _late(self, period: int, now: float) -> int:
        """Periods missed when the loop wakes at ``now`` for ``period`` (0: on time); more than
        ``max_missed_periods`` in a row raise :class:`ControlFault`."""
        late = now - period * self.period_s
        missed = self.missed.count(late)
        if not missed:
            return 0
        if self.missed.exceeded:
            raise ControlFault(
                f"the control loop woke {late:.2f} s after the tick of period {period}: "
                f"{self.missed.in_row} periods missed in a row, more than "
                f"robot.max_missed_periods={self.missed.max_in_row} (the process stalled or its "
                f"clock jumped)")
        log.warning("control: woke %.3f s after the tick of period %d: %d period(s) skipped, "
                    "holding the last command", late, period, missed)
        return missed

    def _hold(self, period: int, pressure: np.ndarray, event: str, missed: int,
              goal: tuple[int, np.ndarray] | None) -> None:
        """Publish the last safe command again for ``period`` and record why."""
        safe = self.gate.check(pressure)
        published = self.arm.publish(safe)
        self.holds += 1
        latest = self._latest
        position = latest[2] if latest is not None else np.full(3, np.nan)
        pose_t = latest[0] if latest is not None else np.nan
        index, target = goal if goal is not None else (-2, np.full(3, np.nan))
        self.recorder.add(period=period, t=period * self.period_s, publish_t=published,
                          pose_t=pose_t, pose_age_s=self.arm.now() - pose_t, position=position,
                          goal_index=index, goal=target, observation=None,
                          action=np.full(len(safe), np.nan), command=safe, latency_ms=np.nan,
                          cpu_ms=np.nan, event=event, missed_periods=missed,
                          reference=self.schedule.reference(period))

    def _periods(self) -> int:
        deployment, schedule = self.deployment, self.schedule
        hidden, first = deployment.hidden, True
        last_pressure = self.gate.preload
        period = 0
        while schedule.end is None or period < schedule.end:
            self._wait_until(period * self.period_s)
            now = self.arm.now()
            missed = self._late(period, now)
            if missed:
                period += missed  # the overdue periods get no command at all
                if schedule.end is not None and period >= schedule.end:
                    break
                self._fresh_after = now
                self._take_goals(period)
                self._hold(period, last_pressure, "late", missed, schedule.goal(period))
                period += 1
                continue
            tick = period * self.period_s
            self._take_goals(period)
            current = schedule.goal(period)
            started, cpu_started = time.perf_counter(), time.process_time()
            frame, age = self._pose(now)
            if current is None:  # live goals: none yet, hold the preload
                safe = self.gate.check(self.gate.preload)
                self.arm.publish(safe)
                last_pressure = safe
                self.missed.reset()
                period += 1
                continue
            if self._fresh_after is not None and frame[0] <= self._fresh_after:
                self._hold(period, last_pressure, "stale_pose", 0, current)
                period += 1
                continue
            self._fresh_after = None
            self.missed.reset()
            index, goal = current
            hidden, obs, action, pressure = deployment.act(
                hidden, first, frame[2], goal, schedule.preview(period, deployment.preview),
                last_pressure)
            if not (np.all(np.isfinite(action)) and np.all(np.isfinite(pressure))):
                raise ControlFault(f"non-finite policy output at period {period}: action "
                                   f"{action.tolist()} from observation {obs.tolist()}")
            safe = self.gate(pressure)
            published = self.arm.publish(safe)
            latency_ms = (time.perf_counter() - started) * 1e3
            cpu_ms = (time.process_time() - cpu_started) * 1e3
            self.recorder.add(period=period, t=tick, publish_t=published, pose_t=frame[0],
                              pose_age_s=age, position=frame[2], goal_index=index, goal=goal,
                              observation=obs, action=action, command=safe,
                              latency_ms=latency_ms, cpu_ms=cpu_ms,
                              reference=schedule.reference(period))
            last_pressure, first = safe, False
            period += 1
        # the pose at the end of the last period: where the last goal ended
        self._wait_until(period * self.period_s)
        frame, age = self._pose(self.arm.now())
        self.recorder.add(period=period, t=period * self.period_s, publish_t=np.nan,
                          pose_t=frame[0], pose_age_s=age, position=frame[2], goal_index=-1,
                          goal=np.full(3, np.nan), observation=None, action=np.full(3, np.nan),
                          command=np.full(3, np.nan), latency_ms=np.nan, cpu_ms=np.nan,
                          reference=schedule.reference(period))
        return period


# ------------------------------------------------------------------------------------------------
# the in-process simulated arm
# ------------------------------------------------------------------------------------------------
class SimArm:
    """The simulated arm in simulated time: one mocap frame per :meth:`advance`.

    The same simulator as the digital twin (:class:`pipeline.ros2.twin.ArmSimulator`: physics,
    mocap noise, jitter and dropped frames, session drawn from ``seed``), so with ``seed`` equal
    to ``robot.twin.seed`` a session here starts where the twin's does. A command takes effect at
    the next frame, as on the twin. ``signals`` (a :class:`pipeline.ros2.node.StopSignals`) is
    polled each frame.
    """

    def __init__(self, robot: SimRobotConfig, seed: int, gate: CommandGate, signals: Any = None):
        from pipeline.ros2.twin import ArmSimulator  # no ROS: only the simulator

        settings = TwinConfig(seed=int(seed), physics=robot.physics, mocap=robot.mocap)
        self.simulator = ArmSimulator(settings, float(robot.limits.preload), int(robot.n_valves))
        self.frame_s = 1.0 / float(robot.mocap.rate_hz)
        self.gate, self.signals = gate, signals
        self._frame = self._origin = 0
        self._frames: list[Frame] = []
        self.commands: list[np.ndarray] = []  # every command sent, in order

    def start(self) -> None:
        """Frames until the first pose arrives (as the twin publishes before a command);
        ``t = 0`` is the time after it."""
        while not self._frames:
            self.advance(0.0)
        self._origin = self._frame

    def now(self) -> float:
        return (self._frame - self._origin) * self.frame_s

    def advance(self, until: float) -> None:
        if self.signals is not None and self.signals.received:
            raise Stop(f"{self.signals.received} received")
        position, jitter = self.simulator.next_frame()
        stamp = (self._frame - self._origin) * self.frame_s + jitter
        if position is not None:
            self._frames.append((stamp, stamp, np.asarray(position, np.float64)))
        self._frame += 1

    def receive(self) -> None:
        """Nothing arrives outside :meth:`advance` in simulated time."""

    def take_frames(self) -> list[Frame]:
        frames, self._frames = self._frames, []
        return frames

    def take_goals(self) -> list[np.ndarray]:
        return []

    def take_points(self) -> list[tuple[float, np.ndarray]]:
        return []

    def publish(self, pressures: np.ndarray) -> float:
        self.commands.append(np.asarray(pressures, np.float64))
        self.simulator.set_command(pressures)
        return self.now()

    def stop_safely(self) -> bool | None:
        self.publish(self.gate.check(self.gate.preload))
        return None
