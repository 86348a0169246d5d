"""ROS 2 bags (sqlite3 or MCAP) of the command and pose topics into the raw schemas.

A bag folder (``metadata.yaml`` plus storage files, as ``ros2 bag record`` writes it) is one run.
The topics, message types and field paths are those of the ``robot=ros2`` config
(:class:`pipeline.schemas.RosTopicsConfig`). Commands are timed by the bag's log time (the
default command type has no header); poses by their header stamp (``stamp_field``; empty: the log
time). ``t = 0`` is the earlier of the first command and the first pose. Poses with a
non-finite position become ``valid = False`` frames; a pose whose stamp does not advance is
dropped. Commands and poses then share a clock only if the motion capture's clock agrees with
the recording computer's: the offset of the poses' log times from their stamps (its 5th
percentile, what transport adds least) must lie within ``[-0.01, robot.max_clock_offset_s]``
seconds, else the bag is refused naming both clocks. Reading uses the ``rosbags`` library (no ROS installation needed); message definitions
come from the bag, or for bags without them from rosbags' built-in ROS 2 types.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from pipeline.data.ros_messages import NS_PER_S, read_position, read_pressures, read_stamp_ns
from pipeline.data.schemas import CMD_COLUMNS, COMMANDS, MOCAP, XYZ, DataError, validate

log = logging.getLogger(__name__)


CLOCK_TOLERANCE_S = 0.01  # a pose logged this much before its stamp: the clocks are apart


def _check_clocks(source: str, robot: Any, offsets_ns: np.ndarray) -> None:
    """Refuse a bag whose pose stamps and log times are on clocks apart (see module doc)."""
    if not offsets_ns.size:
        return
    best = float(np.percentile(offsets_ns, 5)) / NS_PER_S
    bound = float(robot.max_clock_offset_s)
    if best < -CLOCK_TOLERANCE_S:
        raise DataError(source, f"poses on {robot.pose_topic} are logged {-best:.3f} s before "
                        f"their header stamps (5th percentile): the motion capture's clock runs "
                        f"ahead of the recording computer's, so commands (log time) and poses "
                        f"(header stamps) would be shifted against each other; synchronise the "
                        f"clocks (e.g. chrony) and record again")
    if best > bound:
        raise DataError(source, f"poses on {robot.pose_topic} are logged at least {best:.3f} s "
                        f"after their header stamps (5th percentile), above "
                        f"robot.max_clock_offset_s={bound:g} s: the motion capture's clock runs "
                        f"behind the recording computer's, so commands (log time) and poses "
                        f"(header stamps) would be shifted against each other; synchronise the "
                        f"clocks (e.g. chrony) and record again")


def read_rosbag(path: Path, robot: Any, run_id: str | None = None
                ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """One bag folder as ``(commands, mocap)`` tables, validated (limits checked)."""
    path = Path(path)
    run_id = run_id or path.name
    source = str(path)
    commands: list[tuple[int, np.ndarray]] = []
    poses: list[tuple[int, tuple[float, float, float]]] = []
    offsets: list[int] = []  # log time - header stamp of each pose [ns]
    with AnyReader([path], default_typestore=get_typestore(Stores.LATEST)) as reader:
        connections = {}
        for topic, msgtype in ((robot.command_topic, robot.command_type),
                               (robot.pose_topic, robot.pose_type)):
            found = [c for c in reader.connections if c.topic == topic]
            if not found:
                topics = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
                raise DataError(source, f"no topic {topic!r} in the bag; it holds {topics}")
            types = {c.msgtype for c in found}
            if types != {msgtype}:
                raise DataError(source, f"topic {topic!r} carries {sorted(types)}, the config "
                                f"expects {msgtype}")
            connections.update({c.id: c for c in found})
        for connection, log_ns, raw in reader.messages(connections=list(connections.values())):
            message = reader.deserialize(raw, connection.msgtype)
            try:
                if connection.topic == robot.command_topic:
                    commands.append((log_ns, read_pressures(message, robot.command_field,
                                                            robot.n_valves)))
                else:
                    stamp = (read_stamp_ns(message, robot.stamp_field) if robot.stamp_field
                             else log_ns)
                    poses.append((stamp, read_position(message, robot.position_field)))
                    offsets.append(log_ns - stamp)
            except ValueError as err:
                raise DataError(source, f"topic {connection.topic}: {err}") from err
    if not commands:
        raise DataError(source, f"no message on the command topic {robot.command_topic!r}")
    if not poses:
        raise DataError(source, f"no message on the pose topic {robot.pose_topic!r}")

    if robot.stamp_field:
        _check_clocks(source, robot, np.array(offsets, np.int64))
    poses.sort(key=lambda pose: pose[0])
    stamps = np.array([stamp for stamp, _ in poses], np.int64)
    advancing = np.r_[True, np.diff(stamps) > 0]
    if not advancing.all():
        log.warning("%s: dropped %d poses whose stamp repeats an earlier one", source,
                    int((~advancing).sum()))
    t0 = min(commands[0][0], int(stamps[0]))
    xyz = np.array([p for (_, p), keep in zip(poses, advancing) if keep], np.float64)
    mocap = pd.DataFrame({"run_id": run_id, "t": (stamps[advancing] - t0) / NS_PER_S})
    for k, axis in enumerate(XYZ):
        mocap[axis] = xyz[:, k]
    mocap["valid"] = np.isfinite(xyz).all(axis=1)
    pressures = np.stack([p for _, p in commands])
    command_table = pd.DataFrame({"run_id": run_id,
                                  "t": (np.array([t for t, _ in commands]) - t0) / NS_PER_S})
    for j, column in enumerate(CMD_COLUMNS):
        command_table[column] = pressures[:, j]
    return (validate(command_table, COMMANDS, f"{source} ({robot.command_topic})", robot.limits),
            validate(mocap, MOCAP, f"{source} ({robot.pose_topic})"))
