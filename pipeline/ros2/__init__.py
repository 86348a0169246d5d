"""The arm over ROS 2: ``collect`` with ``robot=ros2``, the digital twin (``stage=twin``), bags.

- ``collector.py``: the collect node (commands out at ``control_hz``, poses in, watchdog,
  safe stop) and :func:`collect_ros2`, which fills the ``collect`` artifact.
- ``twin.py``: the simulated arm (``pipeline/sim_arm.py``) as a ROS 2 node.
- ``bag.py``: ROS 2 bags (sqlite3, MCAP) into the raw schemas (``robot=rosbag``; needs only the
  ``rosbags`` library, not rclpy).
- ``node.py`` (rclpy context, QoS, signals), ``messages.py`` (types and field paths),
  ``gate.py`` (the safety gate of outgoing commands), ``recorder.py`` (Parquet chunks).

rclpy comes from the optional ``ros`` extra; this package imports it only when a node is made,
so that without it ``robot=ros2`` and ``stage=twin`` fail with one line saying how to install it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pipeline.artifacts import ArtifactWriter
    from pipeline.ros2.collector import Interruption

ROS_INSTALL_HINT = (
    "robot=ros2 and stage=twin need ROS 2's rclpy, which is not installed: "
    "`pip install -e .[ros]` (or `make setup-ros`) adds it"
)


class RosUnavailableError(ImportError):
    """rclpy (the ``ros`` extra) is missing."""


def require_rclpy() -> Any:
    """The rclpy module, or :class:`RosUnavailableError` with the install hint."""
    try:
        import rclpy
    except ImportError as err:
        raise RosUnavailableError(f"{ROS_INSTALL_HINT} ({err})") from err
    return rclpy


def collect_ros2(cfg: Any, writer: ArtifactWriter, spec: dict[str, Any]) -> Interruption | None:
    """Record ``robot.num_runs`` exploration runs on the arm into ``writer``; see ``collector``.

    Returns None when every run completed, else the :class:`~pipeline.ros2.collector.Interruption`
    (the artifact then holds the runs recorded so far, the last one marked incomplete).
    """
    require_rclpy()
    from pipeline.ros2.collector import record  # imports rclpy

    return record(cfg, writer, spec)
