"""rclpy plumbing shared by the collect node and the digital twin: context, QoS and signals."""

from __future__ import annotations

import contextlib
import logging
import signal
from collections.abc import Iterator
from typing import Any

from pipeline.schemas import QosConfig, QosDurability, QosReliability, Ros2RobotConfig

log = logging.getLogger(__name__)


ROS_INSTALL_HINT = (
    "robot=ros2 and stage=twin need ROS 2's rclpy, which is not installed: "
    "`pip install -e .[ros]` (or `make setup-ros`) adds it"
)


class RosUnavailableError(ImportError):
    """rclpy (the ``ros`` extra) is missing."""


class ArmRefused(RuntimeError):
    """The arm side is missing or not the one configured (no pose, no guard's handshake or one
    that does not match, a second listener or pose source, clocks apart): the stage refuses."""


def arm_domain(robot: Ros2RobotConfig) -> int | None:
    """The ROS domain a stage of ``robot`` runs on: the twin's (``robot.rehearsal_domain_id``)
    in a rehearsal (``robot.rehearsal=true``), else ``robot.domain_id`` (None: ROS_DOMAIN_ID)."""
    if robot.rehearsal:
        return int(robot.rehearsal_domain_id)
    return None if robot.domain_id is None else int(robot.domain_id)


def require_rclpy() -> Any:
    """The rclpy module, or :class:`RosUnavailableError` with the install hint."""
    try:
        import rclpy
    except ImportError as err:
        raise RosUnavailableError(f"{ROS_INSTALL_HINT} ({err})") from err
    return rclpy



def qos_profile(qos: QosConfig) -> Any:
    """An rclpy ``QoSProfile`` from a :class:`pipeline.schemas.QosConfig`."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    reliability = {QosReliability.reliable: ReliabilityPolicy.RELIABLE,
                   QosReliability.best_effort: ReliabilityPolicy.BEST_EFFORT}
    durability = {QosDurability.volatile: DurabilityPolicy.VOLATILE,
                  QosDurability.transient_local: DurabilityPolicy.TRANSIENT_LOCAL}
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(qos.depth),
                      reliability=reliability[QosReliability(qos.reliability)],
                      durability=durability[QosDurability(qos.durability)])


@contextlib.contextmanager
def ros_node(node_name: str, domain_id: int | None) -> Iterator[tuple[Any, Any]]:
    """A node in its own rclpy context with a single-threaded executor: ``(node, executor)``.

    rclpy's own signal handlers stay off: on SIGINT they would shut the context down before the
    preload could be published (:class:`StopSignals` handles the signals instead).
    """
    rclpy = require_rclpy()
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    try:
        # No parameter services or /rosout publisher: fewer endpoints to discover.
        node = Node(node_name, context=context, start_parameter_services=False,
                    enable_rosout=False)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            yield node, executor
        finally:
            executor.shutdown()
            node.destroy_node()
    finally:
        context.try_shutdown()


class StopSignals:
    """SIGINT and SIGTERM set a flag (:attr:`received`) that the node's loop polls.

    A stop therefore never interrupts a publish or a Parquet write halfway, and repeated Ctrl-C
    cannot cut the safe stop short (SIGKILL still can). Handlers are restored on exit.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.received: str | None = None
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, _frame: Any) -> None:
        name = signal.Signals(signum).name
        if self.received is None:
            self.received = name
            log.warning("%s received: stopping safely", name)
        else:
            log.warning("%s received again: still stopping safely", name)

    def __enter__(self) -> StopSignals:
        for sig in self.SIGNALS:
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *_exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
