"""A real arm's safety settings are pinned by its robot config file: overrides that would switch
off a timeout, run the valves out of real time, change the number of valves or the fault preload,
or publish around the guard are refused at composition with one clear line."""

from __future__ import annotations

import pytest

from pipeline.config import PROJECT_ROOT
from pipeline.schemas import ConfigError
from pipeline.validation import validate_config
from tests.test_envelope import pipeline

ROS2_YAML = PROJECT_ROOT / "conf/robot/ros2.yaml"


def refused(cfg) -> str:
    with pytest.raises(ConfigError) as err:
        validate_config(cfg, "ros2")
    return str(err.value)


@pytest.mark.parametrize(("overrides", "message"), [
    (["stage=guard", "robot.command_timeout_s=1e9"],
     "robot.command_timeout_s=1000000000.0 s exceeds its bound "
     "robot.safety_bounds.command_timeout_s=2.0 s"),
    (["stage=collect", "robot.watchdog_s=1e9"],
     "robot.watchdog_s=1000000000.0 s exceeds its bound robot.safety_bounds.watchdog_s=1.0 s"),
    (["stage=collect", "robot.watchdog_s=1.5"],  # just above the bound
     "robot.watchdog_s=1.5 s exceeds its bound robot.safety_bounds.watchdog_s=1.0 s"),
    (["stage=collect", "robot.time_scale=10"],
     "robot.time_scale=10.0: a real arm runs in real time (time_scale=1)"),
    (["stage=collect", "robot.time_scale=0.25"],
     "robot.time_scale=0.25: a real arm runs in real time (time_scale=1)"),
    (["stage=collect", "robot.n_valves=2"],
     "robot.n_valves=2 differs from the arm's rating robot.rating.n_valves=3"),
    (["stage=control", "robot.limits.preload=4.3"],
     "robot.limits.preload=4.3 kPa differs from the arm's rating robot.rating.preload=2.0 kPa"),
    (["stage=collect", "robot.command_topic=/control_pressure/guarded"],
     "robot.command_topic=/control_pressure/guarded is the guard's output"),
    (["stage=collect", "robot.safety_bounds.watchdog_s=100"],
     f"robot.safety_bounds.watchdog_s=100.0 differs from 1.0 in {ROS2_YAML}: the safety bounds "
     f"of a real arm (robot=ros2) cannot be overridden"),
    (["stage=collect", "robot.rating.n_valves=2", "robot.n_valves=2"],
     f"robot.rating.n_valves=2 differs from 3 in {ROS2_YAML}"),
    (["stage=control", "robot.max_missed_periods=10"],
     "robot.max_missed_periods=10 must lie in [1, robot.safety_bounds.max_missed_periods=3]"),
    (["stage=collect", "robot.max_pose_latency_s=5"],
     "robot.max_pose_latency_s=5.0 s must lie in (0, robot.safety_bounds.max_pose_latency_s=0.5]"),
    # a rehearsal's durations are bounded in wall seconds: 8 arm s at 4x is 2 wall s
    (["stage=collect", "robot.rehearsal=true", "robot.time_scale=4", "robot.watchdog_s=8"],
     "robot.watchdog_s=8.0 s (2 wall s at robot.time_scale=4) exceeds its bound"),
])
def test_unsafe_overrides_of_a_real_arm_are_refused(make_cfg, overrides, message):
    assert refused(make_cfg("robot=ros2", *overrides)).startswith(message)


@pytest.mark.parametrize("overrides", [
    [],
    ["robot.watchdog_s=0.3", "robot.command_timeout_s=1.0", "robot.max_missed_periods=1"],
    ["robot.rehearsal=true", "robot.time_scale=4", "robot.watchdog_s=4"],
    ["stage=twin", "robot.time_scale=4", "robot.watchdog_s=4"],  # the twin is no real arm
])
def test_tighter_settings_and_rehearsals_pass(make_cfg, overrides):
    validate_config(make_cfg("robot=ros2", *overrides), "ros2")


def test_a_lab_arm_file_may_set_its_own_bounds(tmp_path, make_cfg):
    robot = tmp_path / "robot"
    robot.mkdir()
    (robot / "lab_arm.yaml").write_text("defaults:\n  - ros2\n  - _self_\nname: lab_arm\n"
                                        "safety_bounds:\n  watchdog_s: 2.0\n")
    cfg = make_cfg("robot=ros2", "robot.watchdog_s=1.5", "robot.safety_bounds.watchdog_s=2.0")
    validate_config(cfg, "lab_arm", [tmp_path])
    with pytest.raises(ConfigError, match=r"robot\.safety_bounds\.watchdog_s=2\.0 differs from 1\.0"):
        validate_config(cfg, "ros2")


def test_an_unbounded_deadman_fails_on_the_command_line_with_one_line(tmp_path):
    result = pipeline(tmp_path, "stage=guard", "robot=ros2", "robot.command_timeout_s=1e9")
    output = result.stdout + result.stderr
    assert result.returncode == 1, output
    assert ("ConfigError: robot.command_timeout_s=1000000000.0 s exceeds its bound "
            "robot.safety_bounds.command_timeout_s=2.0 s") in output
    assert "Traceback" not in output and output.count("ERROR") == 1


def test_without_the_ros_extra_the_safety_tests_fail_loudly(monkeypatch):
    import sys

    from tests.ros_required import require_ros

    monkeypatch.setitem(sys.modules, "rclpy", None)  # import rclpy -> ImportError
    monkeypatch.delenv("SOROLEARN_WITHOUT_ROS", raising=False)
    with pytest.raises(pytest.fail.Exception, match=r"the ROS 2 extra is not installed .*"
                                                    r"`make setup`"):
        require_ros("rclpy")
    monkeypatch.setenv("SOROLEARN_WITHOUT_ROS", "1")
    with pytest.raises(pytest.skip.Exception, match="SOROLEARN_WITHOUT_ROS=1"):
        require_ros("rclpy")


@pytest.mark.parametrize("recorded_on_twin, real_arm, refused_", [
    (True, True, True),     # a real-arm collect never reuses the twin's runs
    (True, False, False),   # a rehearsal may reuse its own
    (False, True, False),   # the arm's own runs are reused as ever
])
def test_a_real_arm_collect_refuses_a_rehearsals_data_under_its_key(
        make_cfg, recorded_on_twin, real_arm, refused_):
    from tests.ros_required import require_ros

    require_ros("rclpy")  # collect imports the ros extra before the check
    from pipeline import keys
    from pipeline.infra.artifacts import ArtifactStore, produce
    from pipeline.stages.collect import STAGE, collect

    rehearsal = make_cfg("robot=ros2", "robot.rehearsal=true")
    cfg = make_cfg("robot=ros2") if real_arm else rehearsal
    assert keys.key("collect", cfg) == keys.key("collect", rehearsal)  # the key ignores it
    store = ArtifactStore(cfg.paths.artifact_dir)

    def build(writer):
        (writer.path / "commands.parquet").write_bytes(b"")
        writer.summary = {"rehearsal": recorded_on_twin}

    recorded = produce(store, STAGE, *keys.collect_spec(cfg), build)
    if refused_:
        with pytest.raises(ConfigError, match="holds a rehearsal recorded on the digital twin"):
            collect(cfg)
        assert recorded.path.is_dir()  # nothing moved or deleted
    else:
        assert collect(cfg).path == recorded.path
