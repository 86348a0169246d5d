"""The arm side's answer: which node guards the valves, and the rating it enforces.

The guard (``stage=guard``, beside a real arm's valve driver) and the digital twin
(``stage=twin``) publish one latched ``std_msgs/msg/String`` on ``robot.guard.handshake_topic``
(reliable, transient local: a stage started later still receives it), JSON::

    {"role": "guard" | "twin", "node": <its node name>, "command_topic": ..., "time_scale": ...,
     "rating": {"p_min": ..., "p_max": ..., "sum_max": ..., "preload": ..., "n_valves": ...}}

A stage that publishes commands (collect, control) starts only once an answer arrived and
:func:`handshake_problem` finds nothing wrong: the answering node enforces the robot config's
rating on its command topic, it is the only subscriber of that topic, a rehearsal
(``robot.rehearsal=true``, or any ``robot.time_scale`` other than 1) is answered by a twin, and
any other stage (a real arm's) by a guard: a twin's poses are never recorded as the arm's.
"""

from __future__ import annotations

import json
import logging
from typing import Any

log = logging.getLogger(__name__)

HANDSHAKE_TYPE = "std_msgs/msg/String"
RATING_FIELDS = ("p_min", "p_max", "sum_max", "preload", "n_valves")
ROLES = ("guard", "twin")


def handshake_qos() -> Any:
    """Reliable, transient local, depth 1: the latest answer reaches a late subscriber."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def rating_of(robot: Any) -> dict[str, float]:
    """The rating a config enforces, as the handshake states it."""
    rating = robot.rating
    return {name: (int(getattr(rating, name)) if name == "n_valves"
                   else float(getattr(rating, name))) for name in RATING_FIELDS}


def answer_of(robot: Any, role: str, node_name: str) -> dict[str, Any]:
    """The handshake of the arm-side node ``node_name`` (``role`` guard or twin)."""
    if role not in ROLES:
        raise ValueError(f"handshake role {role!r}: expected one of {ROLES}")
    return {"role": role, "node": node_name, "command_topic": str(robot.command_topic),
            "time_scale": float(robot.time_scale), "rating": rating_of(robot)}


def handshake_problem(answer: dict[str, Any], robot: Any, subscribers: list[str]) -> str | None:
    """Why a stage of ``robot`` must not publish to the arm side that gave ``answer`` while
    ``subscribers`` (node names) listen to its command topic; None if it may."""
    role, node = answer.get("role"), answer.get("node")
    topic = str(robot.command_topic)
    if role not in ROLES:
        return f"the arm side answered with role {role!r}; expected a guard or a twin"
    if answer.get("command_topic") != topic:
        return (f"the {role} '{node}' guards {answer.get('command_topic')}, but "
                f"robot.command_topic={topic}")
    expected = rating_of(robot)
    theirs = answer.get("rating") or {}
    differing = [f"{k}: {theirs.get(k)} there, {v} here" for k, v in expected.items()
                 if theirs.get(k) != v]
    if differing:
        return (f"the {role} '{node}' enforces another rating than robot.rating of this config "
                f"({'; '.join(differing)}): start the guard with the same robot config")
    rehearsal = bool(robot.rehearsal) or float(robot.time_scale) != 1.0
    if rehearsal and role != "twin":
        return (f"robot.rehearsal=true / robot.time_scale={robot.time_scale}, but the arm side is "
                f"a {role} ('{node}'), not the digital twin: a rehearsal never drives a real arm")
    if not rehearsal and role == "twin":
        return (f"robot.rehearsal=false (a real arm), but the arm side is the digital twin "
                f"('{node}'): its poses would be recorded as the real arm's. To rehearse, add "
                f"robot.rehearsal=true; to drive the arm, use the arm's ROS domain, where the "
                f"guard answers")
    if float(answer.get("time_scale", 1.0)) != float(robot.time_scale):
        return (f"the {role} '{node}' runs at time_scale {answer.get('time_scale')}, this stage "
                f"at robot.time_scale={robot.time_scale}: both sides need the same")
    if subscribers != [node]:
        hint = ("a twin or recorder left running on the rehearsal domain? stop it" if role == "twin"
                else "the valve driver subscribes to the guard's output, robot.guard.output_topic")
        return (f"{len(subscribers)} subscriber(s) of {topic}: {subscribers or 'none'}; only the "
                f"{role} '{node}' may listen ({hint})")
    return None


class HandshakeAnswer:
    """The arm side's latched answer, published once (guard, twin)."""

    def __init__(self, node: Any, robot: Any, role: str):
        from pipeline.data.ros_messages import message_class

        self.answer = answer_of(robot, role, node.get_name())
        kind = message_class(HANDSHAKE_TYPE)
        self._publisher = node.create_publisher(kind, str(robot.guard.handshake_topic),
                                                handshake_qos())
        message = kind()
        message.data = json.dumps(self.answer)
        self._publisher.publish(message)


class HandshakeListener:
    """A stage's side: the latest answer received (None until one arrives)."""

    def __init__(self, node: Any, robot: Any):
        from pipeline.data.ros_messages import message_class

        self.answer: dict[str, Any] | None = None
        self.unreadable: str | None = None
        node.create_subscription(message_class(HANDSHAKE_TYPE), str(robot.guard.handshake_topic),
                                 self._on_answer, handshake_qos())

    def _on_answer(self, message: Any) -> None:
        try:
            answer = json.loads(message.data)
            if not isinstance(answer, dict):
                raise ValueError("not a JSON object")
        except ValueError as err:
            self.unreadable = f"{message.data[:80]!r} ({err})"
            return
        self.answer = answer
