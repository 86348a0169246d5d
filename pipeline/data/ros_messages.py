"""ROS 2 message types by name and the dotted field paths the config points into them.

The same helpers read rclpy messages and the messages ``rosbags`` deserialises from a bag: both
are plain attribute trees (``msg.pose.position.x``, ``msg.header.stamp.sec``).
"""

from __future__ import annotations

import importlib
import math
from typing import Any

import numpy as np

NS_PER_S = 1_000_000_000


def message_class(type_name: str) -> type:
    """The rclpy class of ``pkg/msg/Name`` (e.g. ``std_msgs/msg/Float64MultiArray``)."""
    parts = type_name.split("/")
    if len(parts) != 3 or parts[1] != "msg":
        raise ValueError(f"message type {type_name!r} is not of the form 'package/msg/Name'")
    package, _, name = parts
    try:
        module = importlib.import_module(f"{package}.msg")
    except ModuleNotFoundError as err:
        raise ValueError(f"message package {package!r} of {type_name} is not installed (the ROS 2 "
                         f"wheel is ros-{package.replace('_', '-')})") from err
    try:
        return getattr(module, name)
    except AttributeError as err:
        raise ValueError(f"no message {name!r} in {package}.msg (type {type_name})") from err


def get_field(message: Any, path: str) -> Any:
    """The value at dotted ``path`` inside ``message``; an error names the missing part."""
    value = message
    for part in path.split("."):
        try:
            value = getattr(value, part)
        except AttributeError as err:
            raise ValueError(f"{type(message).__name__} has no field {path!r} (no {part!r} in "
                             f"{type(value).__name__})") from err
    return value


def set_field(message: Any, path: str, value: Any) -> None:
    parent, _, name = path.rpartition(".")
    target = get_field(message, parent) if parent else message
    if not hasattr(target, name):
        raise ValueError(f"{type(message).__name__} has no field {path!r}")
    setattr(target, name, value)


def read_pressures(message: Any, path: str, n_valves: int) -> np.ndarray:
    """The ``n_valves`` pressures [kPa] at ``path`` as float64."""
    pressures = np.asarray(get_field(message, path), dtype=np.float64).reshape(-1)
    if pressures.shape != (n_valves,):
        raise ValueError(f"field {path!r} holds {pressures.size} values, expected {n_valves} "
                         f"pressures")
    return pressures


def write_pressures(message: Any, path: str, pressures: np.ndarray) -> None:
    set_field(message, path, [float(p) for p in pressures])


def read_position(message: Any, path: str) -> tuple[float, float, float]:
    """x, y, z [m] of the point at ``path``."""
    point = get_field(message, path)
    return float(point.x), float(point.y), float(point.z)


def write_position(message: Any, path: str, xyz: np.ndarray) -> None:
    point = get_field(message, path)
    point.x, point.y, point.z = (float(v) for v in xyz)


def read_stamp_ns(message: Any, path: str) -> int:
    """A ``builtin_interfaces/Time`` at ``path`` in integer nanoseconds."""
    stamp = get_field(message, path)
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def write_stamp_ns(message: Any, path: str, stamp_ns: int) -> None:
    stamp = get_field(message, path)
    stamp.sec, stamp.nanosec = divmod(int(stamp_ns), NS_PER_S)


def is_finite(xyz: tuple[float, float, float]) -> bool:
    return all(math.isfinite(v) for v in xyz)
