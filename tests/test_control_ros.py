"""stage=control over ROS 2 against the digital twin, each stage a separate rclpy process.

The twin and the controller run with the arm's time 4x the wall clock, on their own ROS_DOMAIN_ID
with discovery limited to localhost (see tests/test_ros2_link.py). The same policy, goals and
start (``robot.twin.seed`` = ``control.arm_seed``) on the twin and in-process on the simulated arm
end at the same distances from the goals: the deployed observation is the training one.
"""

from __future__ import annotations

import re
import signal
import time

import numpy as np
import pandas as pd
import pytest

from pipeline.data.schemas import CMD_COLUMNS
from pipeline.infra.artifacts import ArtifactStore
from pipeline.stages.control import control
from tests.conftest import compose_config
from tests.control_fixtures import SMALL, goals_mm, write_policy
from tests.ros_required import require_ros
from tests.test_ros2_link import (
    Pipeline,
    received,
    stop,
)

require_ros("rclpy")
pytestmark = pytest.mark.ros

TIME_SCALE = 4.0
ROS = ["robot=ros2", "robot.rehearsal=true", f"robot.time_scale={TIME_SCALE}", "robot.watchdog_s=1.0",
       "robot.stop_timeout_s=2.0", "robot.startup_timeout_s=60", "control.flush_every_s=0.2"]
PRELOAD = [2.0, 2.0, 2.0]


def assert_within_limits(pressures: np.ndarray) -> None:
    assert np.isfinite(pressures).all()
    assert pressures.min() >= 0.0 and pressures.max() <= 7.0
    assert pressures.sum(axis=1).max() <= 13.0


def sim_policy(tmp_path, policy: str, **overrides):
    """The sim config of a policy artifact (random networks) and its policy file."""
    cfg = compose_config(tmp_path / "sim", *SMALL, f"control.policy={policy}", "stage=control")
    artifact, train_params = write_policy(cfg)
    cfg.control.goals = goals_mm(train_params)
    for name, value in overrides.items():
        cfg.control[name] = value
    return cfg, artifact.file("policy.msgpack")


def control_overrides(cfg, policy_file) -> list[str]:
    goals = str(cfg.control.goals).replace(" ", "")
    return [f"control.policy_file={policy_file}", f"control.goals={goals}",
            f"control.hold_s={cfg.control.hold_s}"]


def final_distances(artifact) -> np.ndarray:
    return pd.read_parquet(artifact.file("goals.parquet"))["final_distance_mm"].to_numpy()


def twin_of(pipe: Pipeline, record):
    """The twin for a control session of up to 15 minutes of its time."""
    return pipe.twin(record, max_duration_s=900)


def control_artifact(pipe: Pipeline, *overrides: str):
    cfg = pipe.cfg(*overrides)
    from pipeline.keys import key

    return ArtifactStore(cfg.paths.artifact_dir).require("control", key("control", cfg))


def twin_session(tmp_path, ros_domain, overrides: list[str]):
    """``stage=control`` with ``overrides`` on the twin over ROS 2, a process each; the control
    artifact."""
    pipe = Pipeline(tmp_path, ros_domain)
    pipe.overrides = ROS
    with twin_of(pipe, tmp_path / "twin_received.jsonl"):
        runner = pipe.start("control", *overrides)
        assert runner.wait(timeout=300) == 0, pipe.log("control")
    return control_artifact(pipe, *overrides)


# a twin session; fast: the loop on a signal (test_control.py), StopSignals (test_ros2_faults.py)
@pytest.mark.slow
def test_twin_matches_the_simulated_arm_then_sigterm_stops_at_the_preload(tmp_path,
                                                                          ros_domain):
    sim_cfg, policy_file = sim_policy(tmp_path, "ppo_rnn", hold_s=3.0)
    in_process = final_distances(control(sim_cfg))

    pipe = Pipeline(tmp_path, ros_domain)
    pipe.overrides = ROS
    record = tmp_path / "twin_received.jsonl"
    overrides = control_overrides(sim_cfg, policy_file)
    with twin_of(pipe, record):
        run = pipe.start("control", *overrides)
        assert run.wait(timeout=240) == 0, pipe.log("control")
        on_twin = final_distances(control_artifact(pipe, *overrides))
        assert np.median(np.abs(on_twin - in_process)) <= 0.3, (on_twin, in_process)
        time.sleep(0.2)
        wire = received(record)[CMD_COLUMNS].to_numpy()
        assert len(wire) == 3 * 6 + 1  # 3 goals x 6 periods, then the preload
        np.testing.assert_allclose(wire[-1], PRELOAD)
        assert_within_limits(wire)

        # ---- SIGTERM mid-session: the preload goes out last, the periods so far are kept ------
        long = [*overrides[:-1], "control.hold_s=60", "robot.session=sigterm"]
        run = pipe.start("control", *long)
        pipe.wait_for_log("control", "arm ready", timeout_s=240)
        time.sleep(1.5)  # 6 s of the arm's time: about 12 periods
        run.send_signal(signal.SIGTERM)
        code = run.wait(timeout=60)
    log = pipe.log("control")
    assert code != 0, log
    assert "SIGTERM received: stopping safely" in log
    assert "ControlInterrupted: control interrupted: SIGTERM received" in log
    artifact = control_artifact(pipe, *long)
    assert artifact.manifest["summary"]["interrupted"] == "SIGTERM received"
    periods = pd.read_parquet(artifact.file("periods.parquet"))
    assert 4 <= (periods["goal_index"] >= 0).sum() < 60
    wire = received(record)[CMD_COLUMNS].to_numpy()
    np.testing.assert_allclose(wire[-1], PRELOAD)
    assert_within_limits(wire)


# a twin session; fast: the loop's watchdog on silent and stale poses (test_control_faults.py)
@pytest.mark.slow
def test_the_watchdog_stops_at_the_preload_when_the_poses_stop(tmp_path, ros_domain):
    sim_cfg, policy_file = sim_policy(tmp_path, "ppo_ff", hold_s=60.0)
    pipe = Pipeline(tmp_path, ros_domain)
    pipe.overrides = [*ROS, "robot.stop_timeout_s=10"]
    record = tmp_path / "twin_received.jsonl"
    twin = pipe.start_twin(record, max_duration_s=900)
    try:
        run = pipe.start("control", *control_overrides(sim_cfg, policy_file))
        pipe.wait_for_log("control", "arm ready", timeout_s=240)
        time.sleep(1.0)
        twin.send_signal(signal.SIGSTOP)  # the arm's driver hangs: no pose, no acknowledgement
        pipe.wait_for_log("control", "mocap watchdog", timeout_s=30)
        time.sleep(0.5)
        twin.send_signal(signal.SIGCONT)  # the preload, still being resent, now arrives
        code = run.wait(timeout=60)
        time.sleep(0.5)
    finally:
        twin.send_signal(signal.SIGCONT)
        assert stop(twin) == 0, pipe.log("twin")
    log = pipe.log("control")
    assert code != 0, log
    # which of the two watchdogs fires first is a race: the link's wall-clock silence while the
    # loop waits, or the latest pose's age when a period starts; both name the mocap watchdog
    assert re.search(r"ControlInterrupted: control interrupted: mocap watchdog: "
                     r"(no pose on \S+ for|the latest pose is) [0-9.]+ s", log), log
    assert "commanded the preload [2.0, 2.0, 2.0] kPa (acknowledged" in log
    wire = received(record)[CMD_COLUMNS].to_numpy()
    np.testing.assert_allclose(wire[-1], PRELOAD)
    assert_within_limits(wire)


@pytest.mark.slow
@pytest.mark.parametrize("policy", ["ppo_ff", "ppo_rnn"])
def test_trained_policies_end_at_the_same_distances_on_the_twin_and_in_process(
        tmp_path, ros_domain, policy):
    """experiment=quick policies trained on the simulated arm's data (env=learned)."""
    from pipeline.__main__ import run

    out = tmp_path / "sim"
    train_cfg = compose_config(out, "experiment=quick", f"agent={policy}", "stage=train_ppo")
    trained = run(train_cfg)["train_ppo"]
    goals = "[[28.6,352.3,202.1],[34,352.5,206.5],[32.8,352.3,207.2]]"
    common = [f"control.policy_file={trained.file('policy.msgpack')}", f"control.goals={goals}",
              "control.hold_s=10"]
    sim_cfg = compose_config(out, "experiment=quick", "stage=control", *common)
    in_process = final_distances(control(sim_cfg))

    on_twin = final_distances(twin_session(tmp_path, ros_domain, common))
    assert np.median(np.abs(on_twin - in_process)) <= 0.3, (on_twin, in_process)


# ---- following a reference ------------------------------------------------------------------------
def tracking_metrics_of(artifact) -> pd.Series:
    return pd.read_parquet(artifact.file("tracking.parquet")).iloc[0]


@pytest.mark.slow  # about 50 s
def test_a_circle_followed_on_the_twin_matches_the_simulated_arm(tmp_path, ros_domain):
    """A tracking policy (random network, preview 3) follows a 2 mm circle for 10 s."""
    cfg = compose_config(tmp_path / "sim", *SMALL, "env.task=track", "env.preview=3",
                         "control.policy=ppo_rnn", "stage=control")
    artifact, train_params = write_policy(cfg)
    centre = np.round(np.median(np.asarray(train_params.goal_set), axis=0) * 1e3, 1).tolist()
    shape = f"{{kind:circle,centre_mm:[{centre[0]},{centre[1]},{centre[2]}],size_mm:2,period_s:8}}"
    common = [f"control.policy_file={artifact.file('policy.msgpack')}",
              f"control.trajectory={shape}", "control.duration_s=10", "control.settle_s=2",
              "control.workspace_margin_mm=10"]
    sim_cfg = compose_config(tmp_path / "sim", *SMALL, "env.task=track", "env.preview=3",
                             "stage=control", *common)
    in_process = tracking_metrics_of(control(sim_cfg))

    pipe = Pipeline(tmp_path, ros_domain)
    pipe.overrides = ROS
    record = tmp_path / "twin_received.jsonl"
    with twin_of(pipe, record):
        run = pipe.start("control", *common)
        assert run.wait(timeout=240) == 0, pipe.log("control")
        time.sleep(0.2)
    on_twin = control_artifact(pipe, *common)
    metrics = tracking_metrics_of(on_twin)
    assert abs(metrics["rmse_mm"] - in_process["rmse_mm"]) <= 0.3, (metrics, in_process)
    periods = pd.read_parquet(on_twin.file("periods.parquet"))
    assert (periods["goal_index"] >= 0).sum() == 20
    assert np.isfinite(periods[["ref_x", "ref_y", "ref_z"]].to_numpy()).all()
    wire = received(record)[CMD_COLUMNS].to_numpy()
    assert len(wire) == 20 + 1  # 20 periods, then the preload
    np.testing.assert_allclose(wire[-1], PRELOAD)
    assert_within_limits(wire)


@pytest.mark.slow
def test_a_trained_tracking_policy_follows_the_circle_alike_on_the_twin_and_in_process(
        tmp_path, ros_domain):
    """An experiment=[quick,tracking] policy trained on the simulated arm's data follows the
    evaluation's circle (5 mm, 20 s a lap) for 30 s: the same RMSE within 0.3 mm."""
    from pipeline.__main__ import run

    out = tmp_path / "sim"
    train_cfg = compose_config(out, "experiment=[quick,tracking]", "agent=ppo_ff",
                               "stage=train_ppo")
    trained = run(train_cfg)["train_ppo"]
    common = [f"control.policy_file={trained.file('policy.msgpack')}",
              "control.trajectory=circle", "control.workspace_margin_mm=3"]
    sim_cfg = compose_config(out, "experiment=[quick,tracking]", "stage=control", *common)
    in_process = tracking_metrics_of(control(sim_cfg))

    on_twin = tracking_metrics_of(twin_session(tmp_path, ros_domain, common))
    assert abs(on_twin["rmse_mm"] - in_process["rmse_mm"]) <= 0.3, (on_twin, in_process)


# a reference publisher in its own rclpy process: a circle in xz, each point stamped (ROS time)
# LEAD arm seconds ahead of when it is sent, one point every 0.05 wall seconds
PUBLISHER = """
import math, sys, time
import rclpy
from pipeline.data.ros_messages import message_class, write_stamp_ns
topic, cx, cy, cz, radius, period, scale, lead, wall = sys.argv[1:]
cx, cy, cz, radius, period, scale, lead, wall = map(float, (cx, cy, cz, radius, period, scale,
                                                          lead, wall))
rclpy.init()
node = rclpy.create_node("reference_publisher")
Point = message_class("geometry_msgs/msg/PointStamped")
publisher = node.create_publisher(Point, topic, 10)
start = time.monotonic()
while time.monotonic() - start < wall:
    message = Point()
    write_stamp_ns(message, "header.stamp",
                   node.get_clock().now().nanoseconds + int(lead / scale * 1e9))
    angle = 2 * math.pi * ((time.monotonic() - start) * scale + lead) / period
    message.point.x = cx + radius * math.cos(angle)
    message.point.y = cy
    message.point.z = cz + radius * math.sin(angle)
    publisher.publish(message)
    time.sleep(0.05)
node.destroy_node()
rclpy.shutdown()
"""


@pytest.mark.slow  # a twin session and a publisher process
def test_a_reference_published_live_is_followed_on_the_twin(tmp_path, ros_domain):
    """A tracking policy (random network, preview 3) follows a 2 mm circle whose points arrive
    on control.trajectory_topic, stamped 2 arm seconds ahead: every period's goal lies on the
    circle, the session is scored, and it ends at the preload within the limits."""
    import subprocess
    import sys

    cfg = compose_config(tmp_path / "sim", *SMALL, "env.task=track", "env.preview=3",
                         "control.policy=ppo_rnn", "stage=control")
    artifact, train_params = write_policy(cfg)
    centre = np.median(np.asarray(train_params.goal_set), axis=0) * 1e3
    common = [f"control.policy_file={artifact.file('policy.msgpack')}",
              "control.trajectory_topic=/reference", "control.duration_s=10",
              "control.settle_s=2", "control.workspace_margin_mm=10"]
    pipe = Pipeline(tmp_path, ros_domain)
    pipe.overrides = ROS
    record = tmp_path / "twin_received.jsonl"
    with twin_of(pipe, record):
        run = pipe.start("control", *common)
        # the points flow from before the first period to after the last: the session is 2.5
        # wall seconds, less than a loaded machine may take to start a publisher's process
        publisher = subprocess.Popen(
            [sys.executable, "-c", PUBLISHER, "/reference", *(str(v / 1e3) for v in centre),
             "0.002", "8.0", str(TIME_SCALE), "2.0", "300.0"], env=pipe.env)
        try:
            assert run.wait(timeout=240) == 0, pipe.log("control")
        finally:
            publisher.kill()
            publisher.wait(timeout=60)
        time.sleep(0.2)
    on_twin = control_artifact(pipe, *common)
    periods = pd.read_parquet(on_twin.file("periods.parquet"))
    followed = periods[periods["goal_index"] >= 0]
    assert 12 <= len(followed) <= 20  # every period once the first point arrived
    goals = followed[["goal_x", "goal_y", "goal_z"]].to_numpy() * 1e3
    radius = np.linalg.norm((goals - centre)[:, [0, 2]], axis=1)
    np.testing.assert_allclose(radius, 2.0, atol=0.05)  # on the circle (chords: 0.01 mm in)
    np.testing.assert_allclose(goals[:, 1], centre[1], atol=1e-6)
    assert np.ptp(goals[:, 0]) > 1.0  # and moving along it
    assert np.isfinite(tracking_metrics_of(on_twin)["rmse_mm"])
    wire = received(record)[CMD_COLUMNS].to_numpy()
    np.testing.assert_allclose(wire[-1], PRELOAD)
    assert_within_limits(wire)
