"""The arm over ROS 2 for the control loop, in real time on the arm's clock.

Built on collect's node (:class:`pipeline.ros2.collector.ArmLink`: command publisher, pose
subscriber) and its session helpers (:meth:`~pipeline.ros2.collector.Session.wait_for_arm`: the
guard's handshake; :meth:`~pipeline.ros2.collector.Session.check_sources` and
:meth:`~pipeline.ros2.collector.Session.check_clock`: one pose source, one listener, clocks
together; :meth:`~pipeline.ros2.collector.Session.stop_safely`: the preload published last and
its delivery awaited). Arm time is ``robot.time_scale`` times the monotonic seconds since
:meth:`RosArm.start` (the loop's deadlines: a step of the wall clock moves none); pose and
publish times are ROS times (header stamps) since the ROS time of the start, on the same scale.
Live goals arrive as ``geometry_msgs/msg/PointStamped`` (metres) on ``control.goal_topic``; a
live reference's points as the same messages on ``control.trajectory_topic``, each due at its
header stamp (ROS time; a zero stamp: on arrival).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from pipeline.control.loop import Frame, Stop
from pipeline.data.ros_messages import NS_PER_S, message_class, read_stamp_ns
from pipeline.ros2.collector import ArmLink, Session
from pipeline.ros2.gate import CommandGate
from pipeline.schemas import Ros2RobotConfig

log = logging.getLogger(__name__)
_SPIN_SLICE_S = 0.002  # wall: longest wait inside the executor
MAX_QUEUED_GOALS = 8  # live goals kept between two periods (the oldest dropped beyond)
MAX_QUEUED_POINTS = 256  # reference points kept between two periods (the oldest dropped beyond)


class RosArm:
    def __init__(self, node: Any, executor: Any, robot: Ros2RobotConfig, goal_topic: str | None,
                 gate: CommandGate, signals: Any, trajectory_topic: str | None = None):
        self.link = ArmLink(node, executor, robot)
        self.session = Session(robot, self.link, gate, None, signals)
        self.robot, self.signals = robot, signals
        self.scale = float(robot.time_scale)
        self.watchdog_wall_s = float(robot.watchdog_s) / self.scale
        self._t0_ns, self._t0_s = 0, 0.0  # the start: ROS ns, monotonic s (session.clock)
        self._goals: list[np.ndarray] = []
        self._points: list[tuple[int, np.ndarray]] = []  # (stamp ns, 0: on arrival; [3] m)
        for topic, callback, depth in ((goal_topic, self._on_goal, 10),
                                       (trajectory_topic, self._on_point, MAX_QUEUED_POINTS)):
            if topic:
                from rclpy.qos import QoSProfile

                node.create_subscription(message_class("geometry_msgs/msg/PointStamped"),
                                         str(topic), callback, QoSProfile(depth=depth))

    def _on_goal(self, message: Any) -> None:
        point = message.point
        if len(self._goals) >= MAX_QUEUED_GOALS:  # only the latest goals matter
            dropped = self._goals.pop(0)
            log.warning("control: more than %d live goals queued within a period: dropped %s m",
                        MAX_QUEUED_GOALS, dropped.tolist())
        self._goals.append(np.array([point.x, point.y, point.z], np.float64))

    def _on_point(self, message: Any) -> None:
        if len(self._points) >= MAX_QUEUED_POINTS:
            dropped = self._points.pop(0)
            log.warning("control: more than %d reference points queued within a period: "
                        "dropped %s m", MAX_QUEUED_POINTS, dropped[1].tolist())
        point = message.point
        self._points.append((read_stamp_ns(message, "header.stamp"),
                             np.array([point.x, point.y, point.z], np.float64)))

    def _arm_time(self, ns: int) -> float:
        return (ns - self._t0_ns) / NS_PER_S * self.scale

    def start(self) -> None:
        self.session.wait_for_arm()
        self._t0_ns, self._t0_s = self.link.now_ns(), self.session.clock()

    def now(self) -> float:
        return (self.session.clock() - self._t0_s) * self.scale

    def advance(self, until: float) -> None:
        if self.signals.received:
            raise Stop(f"{self.signals.received} received")
        remaining_wall = (until - self.now()) / self.scale
        self.link.spin_once(min(max(remaining_wall, 0.0), _SPIN_SLICE_S))
        self.session.check_sources()
        silent = self.link.silence_s(self.watchdog_wall_s)
        if silent > self.watchdog_wall_s:
            raise Stop(f"mocap watchdog: no pose on {self.robot.pose_topic} for "
                       f"{silent * self.scale:.2f} s (robot.watchdog_s={self.robot.watchdog_s})")

    def receive(self) -> None:
        """Run the callbacks of messages already queued (up to the pose queue's depth)."""
        for _ in range(int(self.robot.pose_qos.depth)):
            self.link.spin_once(0.0)

    def take_frames(self) -> list[Frame]:
        frames = []
        for stamp, receipt, xyz in self.link.take_poses():
            self.session.check_clock(stamp, receipt)
            frames.append((self._arm_time(stamp), self._arm_time(receipt),
                           np.asarray(xyz, np.float64)))
        return frames

    def take_goals(self) -> list[np.ndarray]:
        goals, self._goals = self._goals, []
        return goals

    def take_points(self) -> list[tuple[float, np.ndarray]]:
        """The reference points arrived since the last call, each with the arm time it is due
        (a zero stamp, or one already past: now)."""
        now = self.now()
        points, self._points = self._points, []
        return [(self._arm_time(ns) if ns else now, point) for ns, point in points]

    def publish(self, pressures: np.ndarray) -> float:
        return self._arm_time(self.link.publish(pressures))

    def stop_safely(self) -> bool | None:
        self.session.stop_safely()
        return self.session.preload_acknowledged
