"""ROS 2 bags (sqlite3 and MCAP), written here with rosbags, through collect robot=rosbag + align.

Needs only the rosbags library (a core dependency), not rclpy.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from pipeline.data.schemas import CMD_COLUMNS, DataError
from pipeline.stages.align import align
from pipeline.stages.collect import collect

NS = 1_000_000_000
START_NS = 1_700_000_000 * NS
COMMAND_TOPIC = "/control_pressure"
POSE_TOPIC = "/mocap_rigid_bodies/rigid_bodies_1/pose"
TYPES = get_typestore(Stores.ROS2_HUMBLE)


def recorded_run(seed: int, n_commands: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Commands [n, 3] kPa at 2 Hz and a pose trajectory [frames, 3] m at 100 Hz."""
    rng = np.random.default_rng(seed)
    commands = np.clip(2.0 + rng.normal(0.0, 1.5, (n_commands, 3)), 0.0, 4.0)
    frames = n_commands * 50
    t = np.arange(frames) / 100.0
    poses = np.stack([0.032 + 0.01 * np.sin(t), 0.353 + 0.001 * t, 0.2 + 0.01 * np.cos(t)], 1)
    return commands, poses


def write_bag(path: Path, storage: StoragePlugin, commands: np.ndarray, poses: np.ndarray,
              lost_frame: int | None = None, stamp_shift_ns: int = 0) -> None:
    """A bag like ``ros2 bag record`` of the two topics: commands logged at 2 Hz, poses stamped
    at 100 Hz and logged 1.5 ms later; ``lost_frame`` has a NaN position (marker occluded);
    ``stamp_shift_ns``: the stamps that much earlier (a mocap clock behind)."""
    command_type, pose_type = "std_msgs/msg/Float64MultiArray", "geometry_msgs/msg/PoseStamped"
    T = TYPES.types
    with Writer(path, version=9, storage_plugin=storage) as writer:
        command_conn = writer.add_connection(COMMAND_TOPIC, command_type, typestore=TYPES)
        pose_conn = writer.add_connection(POSE_TOPIC, pose_type, typestore=TYPES)
        messages = []
        for i, pressures in enumerate(commands):
            message = T[command_type](
                layout=T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0),
                data=np.asarray(pressures, np.float64))
            messages.append((START_NS + i * NS // 2 + 300_000, command_conn, command_type, message))
        for k, xyz in enumerate(poses):
            if k == lost_frame:
                xyz = np.full(3, np.nan)
            stamp = START_NS + k * NS // 100 - stamp_shift_ns
            header = T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=stamp // NS, nanosec=stamp % NS),
                frame_id="world")
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
            messages.append((stamp + stamp_shift_ns + 1_500_000, pose_conn, pose_type,
                             T[pose_type](header=header, pose=pose)))
        for log_ns, connection, msgtype, message in sorted(messages, key=lambda m: m[0]):
            writer.write(connection, log_ns, TYPES.serialize_cdr(message, msgtype))


def test_sqlite3_and_mcap_bags_round_trip_through_collect_and_align(tmp_path, make_cfg):
    bags = tmp_path / "bags"
    bags.mkdir()
    runs = {"run-a": (StoragePlugin.SQLITE3, *recorded_run(0), 123),
            "run-b": (StoragePlugin.MCAP, *recorded_run(1), None)}
    for name, (storage, commands, poses, lost) in runs.items():
        write_bag(bags / name, storage, commands, poses, lost)
    (bags / "notes.txt").write_text("not a bag")  # only bag folders are recordings

    cfg = make_cfg("robot=rosbag", f"robot.data_dir={bags}", "robot.limits.p_max=4.0")
    artifact = collect(cfg)
    commands = pd.read_parquet(artifact.file("commands.parquet"))
    mocap = pd.read_parquet(artifact.file("mocap.parquet"))
    table = pd.read_parquet(artifact.file("runs.parquet")).set_index("run_id")
    assert list(table.index) == ["run-a", "run-b"] and table["complete"].all()
    for name, (_, sent, poses, lost) in runs.items():
        run_commands = commands[commands["run_id"] == name]
        run_mocap = mocap[mocap["run_id"] == name]
        np.testing.assert_allclose(run_commands[CMD_COLUMNS], sent)
        np.testing.assert_allclose(run_commands["t"], np.arange(len(sent)) / 2 + 3e-4, atol=1e-9)
        np.testing.assert_allclose(run_mocap["t"], np.arange(len(poses)) / 100, atol=1e-9)
        valid = np.ones(len(poses), bool)
        if lost is not None:
            valid[lost] = False
        np.testing.assert_array_equal(run_mocap["valid"], valid)
        np.testing.assert_allclose(run_mocap.loc[run_mocap["valid"], ["x", "y", "z"]],
                                   poses[valid])
        assert table.loc[name, "n_frames"] == len(poses)

    aligned = align(cfg)
    report = pd.read_parquet(aligned.file("align_report.parquet")).set_index("run_id")
    assert report["matched"].tolist() == [10, 10] and report["unmatched"].sum() == 0
    assert report.loc["run-a", "interpolated"] == 1

    # the same bags, recollected: the artifact follows their content
    assert collect(cfg).path == artifact.path


def test_bag_without_the_configured_topic_names_what_it_holds(tmp_path, make_cfg):
    bags = tmp_path / "bags"
    bags.mkdir()
    write_bag(bags / "run", StoragePlugin.MCAP, *recorded_run(2))
    cfg = make_cfg("robot=rosbag", f"robot.data_dir={bags}", "robot.pose_topic=/elsewhere")
    with pytest.raises(DataError, match=r"no topic '/elsewhere' in the bag; it holds .*"
                                        r"/mocap_rigid_bodies/rigid_bodies_1/pose"):
        collect(cfg)


@pytest.mark.parametrize(("shift_ns", "message"), [
    (300_000_000, r"logged at least 0\.30\d s after their header stamps \(5th percentile\), above "
                  r"robot\.max_clock_offset_s=0\.25 s: the motion capture's clock runs behind"),
    (-50_000_000, r"logged 0\.04\d s before their header stamps \(5th percentile\): the motion "
                  r"capture's clock runs ahead"),
])
def test_a_bag_whose_clocks_disagree_is_refused_naming_them(tmp_path, make_cfg, shift_ns,
                                                             message):
    # the mocap stamps its poses shift_ns earlier (later when negative) than the recording
    # computer logs them, beyond the 1.5 ms of transport
    bags = tmp_path / "bags"
    bags.mkdir()
    commands, poses = recorded_run(3)
    write_bag(bags / "run", StoragePlugin.MCAP, commands, poses, stamp_shift_ns=shift_ns)
    cfg = make_cfg("robot=rosbag", f"robot.data_dir={bags}", "robot.limits.p_max=4.0")
    with pytest.raises(DataError, match=message):
        collect(cfg)
