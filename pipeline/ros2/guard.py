"""``stage=guard``: an arm-side deadman and rating filter between collect and the valve driver.

A lab runs it beside its valve driver, which subscribes to ``robot.guard.output_topic`` instead of
``robot.command_topic``::

    collect --robot.command_topic--> guard --robot.guard.output_topic--> valve driver

- A command inside the arm's rating (``robot.rating``, float64) is forwarded as it came.
- A command outside the rating (or not finite, or of the wrong length) is never forwarded: it is
  logged, counted (the stage fails at the end) and the rating's preload goes out instead.
- While no command arrived within ``robot.command_timeout_s`` (arm seconds; collect killed, the
  network down), the preload is republished at ``robot.control_hz``; from the start, too, until
  the first command.
- It accepts exactly one publisher on ``robot.command_topic``: once a second one appears (a
  second collect, a bag replay) it forwards nothing more, logs the publishers, republishes the
  preload at ``robot.control_hz`` until stopped and the stage fails at the end.
- It answers for the arm (:mod:`pipeline.ros2.handshake`): the stages that publish commands
  start only after its answer, which names the rating it enforces.
- The preload is published last, however the guard ends (in a ``finally``).

The deadman logic (:class:`Deadman`) is the one the digital twin uses. Runs until SIGINT/SIGTERM
or ``robot.guard.max_duration_s`` (wall).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from pipeline.arm.limits import UnsafeCommandError, assert_safe
from pipeline.data.ros_messages import message_class, read_pressures, write_pressures
from pipeline.ros2.handshake import HandshakeAnswer
from pipeline.ros2.node import StopSignals, arm_domain, qos_profile, require_rclpy, ros_node
from pipeline.schemas import RobotConfig, RobotKind, Ros2RobotConfig

log = logging.getLogger(__name__)
_SPIN_SLICE_S = 0.005  # wall: longest wait inside the executor
_PUBLISHERS_EVERY_S = 0.1  # wall: how often the command topic's publishers are counted


class Deadman:
    """Whether the commands stopped: none within ``timeout_wall_s`` of the last (or ever).

    Times are ``time.monotonic()`` seconds (wall); :meth:`feed` on every command received.
    """

    def __init__(self, timeout_wall_s: float):
        if not timeout_wall_s > 0:
            raise ValueError(f"deadman timeout {timeout_wall_s} s must be positive")
        self.timeout_wall_s = float(timeout_wall_s)
        self.last_command_at: float | None = None

    def feed(self, now: float) -> None:
        self.last_command_at = now

    def stale(self, now: float) -> bool:
        """True before the first command and once ``timeout_wall_s`` passed since the last."""
        return self.last_command_at is None or now - self.last_command_at > self.timeout_wall_s


class SinglePublisher:
    """Exactly one publisher on a command topic: :meth:`check` latches a refusal (the reason,
    naming the publishers) once more than one node publishes on it. ``node`` is an rclpy node
    (``get_publishers_info_by_topic``); times are ``time.monotonic()`` seconds."""

    def __init__(self, node: Any, topic: str, every_s: float = _PUBLISHERS_EVERY_S):
        self._node, self.topic, self.every_s = node, str(topic), float(every_s)
        self.refusal: str | None = None
        self._next = 0.0

    def check(self, now: float, force: bool = False) -> str | None:
        """The refusal (latched), or None while at most one node publishes."""
        if self.refusal is not None or (not force and now < self._next):
            return self.refusal
        self._next = now + self.every_s
        publishers = sorted(str(info.node_name)
                            for info in self._node.get_publishers_info_by_topic(self.topic))
        if len(publishers) > 1:
            self.refusal = (f"{len(publishers)} publishers on {self.topic}: "
                            f"{', '.join(publishers)}; exactly one is accepted (a second collect "
                            f"or control, a bag replay?): nothing more is forwarded, the preload "
                            f"holds until this node is restarted")
        return self.refusal


def rating_preload(robot: Ros2RobotConfig) -> np.ndarray:
    """The rating's preload on every valve [kPa], float64, checked against the rating."""
    preload = np.full(int(robot.n_valves), float(robot.rating.preload))
    return assert_safe(preload, robot.rating, "the arm's rating robot.rating")


class GuardNode:
    """Forwards commands inside the rating; the preload instead of any other or when stale."""

    def __init__(self, node: Any, executor: Any, robot: Ros2RobotConfig):
        self._node, self._executor, self._robot = node, executor, robot
        self._field, self._n_valves = str(robot.command_field), int(robot.n_valves)
        self._type = message_class(robot.command_type)
        self._rating = robot.rating
        self.preload = rating_preload(robot)
        scale = float(robot.time_scale)
        self.deadman = Deadman(float(robot.command_timeout_s) / scale)
        self._republish_wall_s = 1.0 / (float(robot.control_hz) * scale)
        self._publisher = node.create_publisher(self._type, robot.guard.output_topic,
                                                qos_profile(robot.command_qos))
        node.create_subscription(self._type, robot.command_topic, self._on_command,
                                 qos_profile(robot.command_qos))
        self.single = SinglePublisher(node, robot.command_topic)
        self.forwarded = 0
        self.refused = 0
        self.ignored = 0  # commands not forwarded after a second publisher appeared
        self.preloads = 0
        self._next_preload = 0.0
        self.handshake = HandshakeAnswer(node, robot, "guard")

    def _send(self, pressures: np.ndarray) -> None:
        message = self._type()
        write_pressures(message, self._field, pressures)
        self._publisher.publish(message)

    def _send_preload(self, now: float) -> None:
        self._send(self.preload)
        self.preloads += 1
        self._next_preload = now + self._republish_wall_s

    def _refusing(self, now: float, force: bool = False) -> bool:
        latched = self.single.refusal is not None
        refusal = self.single.check(now, force)
        if refusal is not None and not latched:
            log.error("guard: %s", refusal)
            self._send_preload(now)
        return refusal is not None

    def _on_command(self, message: Any) -> None:
        now = time.monotonic()
        if self._refusing(now, force=True):
            self.ignored += 1
            return
        was_stale = self.deadman.stale(now) and self.deadman.last_command_at is not None
        self.deadman.feed(now)
        try:
            pressures = read_pressures(message, self._field, self._n_valves)
            safe = assert_safe(pressures, self._rating, "the arm's rating robot.rating")
        except (UnsafeCommandError, ValueError) as err:
            self.refused += 1
            log.error("guard: not forwarded, the preload instead: %s", err)
            self._send_preload(now)
            return
        if was_stale:
            log.info("guard: commands resumed")
        self._send(safe)
        self.forwarded += 1

    def finish(self) -> None:
        """Leave the valves at the preload: publish it, wait for its acknowledgement."""
        from rclpy.duration import Duration

        self._send_preload(time.monotonic())
        settle_until = time.monotonic() + 0.1
        while time.monotonic() < settle_until:
            self._executor.spin_once(timeout_sec=_SPIN_SLICE_S)
        timeout_ns = int(float(self._robot.stop_timeout_s) * 1e9)
        if not self._publisher.wait_for_all_acked(Duration(nanoseconds=timeout_ns)):
            log.warning("guard: the final preload was not acknowledged within "
                        "robot.stop_timeout_s=%s s", self._robot.stop_timeout_s)

    def serve(self, signals: StopSignals) -> str:
        """Guard until a stop signal or ``guard.max_duration_s``; return why it ended."""
        max_wall_s = self._robot.guard.max_duration_s
        start = time.monotonic()
        warned = False
        while not signals.received:
            now = time.monotonic()
            if max_wall_s is not None and now - start > float(max_wall_s):
                return f"robot.guard.max_duration_s={max_wall_s} s elapsed"
            if self._refusing(now):
                if now >= self._next_preload:
                    self._send_preload(now)
            elif self.deadman.stale(now):
                if self.deadman.last_command_at is not None and not warned:
                    log.warning("guard: no command on %s for robot.command_timeout_s=%s s: "
                                "publishing the preload %s kPa", self._robot.command_topic,
                                self._robot.command_timeout_s, self.preload.tolist())
                    warned = True
                if now >= self._next_preload:
                    self._send_preload(now)
            else:
                warned = False
            self._executor.spin_once(timeout_sec=_SPIN_SLICE_S)
        return f"{signals.received} received"


def guard(robot: RobotConfig) -> None:
    """Serve the guard on ``robot``'s topics (``robot=ros2``) until stopped."""
    if RobotKind(robot.kind) is not RobotKind.ros2:
        raise ValueError(f"stage=guard guards the valves of a ROS 2 robot; got robot={robot.name} "
                         f"(add robot=ros2)")
    if robot.guard.output_topic == robot.command_topic:
        raise ValueError(f"robot.guard.output_topic={robot.guard.output_topic} must differ from "
                         f"robot.command_topic (the valve driver subscribes to the guard's output)")
    require_rclpy()
    reason = "an error"
    with StopSignals() as signals, ros_node(robot.guard.node_name, arm_domain(robot)) as (
            node, executor):
        node_ = GuardNode(node, executor, robot)
        try:
            log.info("guard: %s -> %s inside the rating [%s, %s] kPa per valve, sum <= %s; "
                     "preload %s kPa after robot.command_timeout_s=%s s without a command; "
                     "answering on %s", robot.command_topic, robot.guard.output_topic,
                     robot.rating.p_min, robot.rating.p_max, robot.rating.sum_max,
                     node_.preload.tolist(), robot.command_timeout_s,
                     robot.guard.handshake_topic)
            reason = node_.serve(signals)
        finally:
            node_.finish()
    log.info("guard: stopped (%s): %d commands forwarded, %d refused, %d ignored, %d preloads "
             "published", reason, node_.forwarded, node_.refused, node_.ignored, node_.preloads)
    if node_.single.refusal is not None:
        raise UnsafeCommandError(f"guard: {node_.single.refusal}")
    if node_.refused:
        raise UnsafeCommandError(f"guard: {node_.refused} command(s) outside the arm's rating "
                                 f"were refused (the preload went out instead)")
