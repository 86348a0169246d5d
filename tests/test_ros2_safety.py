"""Arm-side safety over ROS 2: the twin's deadman after a killed collect, and the guard node.

Like ``test_ros2_link.py``: separate rclpy processes, the arm's time 4x the wall clock, one
ROS_DOMAIN_ID per test, discovery on localhost only.
"""

from __future__ import annotations

import json
import signal
import time

import pytest

from tests.ros_required import require_ros
from tests.test_ros2_link import TIME_SCALE, Pipeline, stop

require_ros("rclpy")
pytestmark = pytest.mark.ros

COMMAND_TIMEOUT_S = 1.5  # conf/robot/ros2.yaml: three control periods
TIMEOUT_WALL_S = COMMAND_TIMEOUT_S / TIME_SCALE
SLACK_S = 1.0  # wall: scheduling on a busy machine (2 cores, the suite running beside it)
PRELOAD = [2.0, 2.0, 2.0]  # the rating's


@pytest.mark.slow  # two processes; fast: the twin's deadman by hand (test_ros2_faults.py)
def test_twin_returns_to_the_preload_when_collect_is_killed(tmp_path, ros_domain):
    pipe = Pipeline(tmp_path, ros_domain, "exploration.num_steps=40")
    record = tmp_path / "twin_received.jsonl"
    with pipe.twin(record):
        collect = pipe.start("collect")
        try:
            pipe.wait_for_log("collect", "run ros2-000 started")
            time.sleep(1.0)  # 8 walk commands
            collect.send_signal(signal.SIGKILL)  # no safe stop: the last walk command stays
            collect.wait(timeout=30)
        finally:
            if collect.poll() is None:
                collect.kill()
        pipe.wait_for_log("twin", "back to the preload", timeout_s=TIMEOUT_WALL_S + 10)
        time.sleep(0.2)
    rows = [json.loads(line) for line in record.read_text().splitlines()]
    commands = [r for r in rows if not r.get("deadman")]
    (deadman,) = [r for r in rows if r.get("deadman")]
    assert rows[-1] is deadman and len(commands) >= 4
    assert commands[-1]["pressures"] != PRELOAD  # killed mid-walk: no preload was sent
    assert deadman["pressures"] == PRELOAD
    silent_s = (deadman["receipt_ns"] - commands[-1]["receipt_ns"]) / 1e9
    assert TIMEOUT_WALL_S <= silent_s <= TIMEOUT_WALL_S + SLACK_S
    assert (f"twin: no command on /control_pressure for robot.command_timeout_s="
            f"{COMMAND_TIMEOUT_S} s: back to the preload [2.0, 2.0, 2.0] kPa") in pipe.log("twin")


class ValveDriver:
    """The test's side of the guard: publishes commands, records what the guard forwards."""

    def __init__(self, node, executor):
        from std_msgs.msg import Float64MultiArray

        self.node, self.executor, self.type = node, executor, Float64MultiArray
        self.publisher = node.create_publisher(Float64MultiArray, "/control_pressure", 10)
        self.received: list[tuple[float, list[float]]] = []
        node.create_subscription(Float64MultiArray, "/control_pressure/guarded",
                                 lambda m: self.received.append((time.monotonic(), list(m.data))),
                                 10)

    def spin(self, seconds: float) -> None:
        until = time.monotonic() + seconds
        while time.monotonic() < until:
            self.executor.spin_once(timeout_sec=0.005)

    def send(self, pressures: list[float]) -> float:
        message = self.type()
        message.data = [float(p) for p in pressures]
        self.publisher.publish(message)
        return time.monotonic()

    def after(self, t: float) -> list[tuple[float, list[float]]]:
        return [(s, p) for s, p in self.received if s > t]


def test_guard_forwards_inside_the_rating_and_falls_back_to_the_preload(
        tmp_path, ros_domain, monkeypatch):
    from pipeline.ros2.node import ros_node

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    pipe = Pipeline(tmp_path, ros_domain)
    guard = pipe.start("guard", "robot.guard.max_duration_s=120")
    try:
        with ros_node("valve_driver_test", ros_domain) as (node, executor):
            driver = ValveDriver(node, executor)
            deadline = time.monotonic() + 90
            while not driver.received:  # before any command: the preload, repeatedly
                assert time.monotonic() < deadline, pipe.log("guard")
                driver.spin(0.05)
            while driver.publisher.get_subscription_count() == 0:
                driver.spin(0.05)
            driver.spin(0.5)
            assert {tuple(p) for _, p in driver.received} == {tuple(PRELOAD)}

            # commands inside the rating are forwarded as they came
            for _ in range(8):
                last = driver.send([3.0, 3.0, 3.5])
                driver.spin(0.125)
            forwarded = [p for _, p in driver.received if p != PRELOAD]
            assert len(forwarded) >= 6 and all(p == [3.0, 3.0, 3.5] for p in forwarded)
            # ... until they stop: the preload within robot.command_timeout_s
            driver.spin(TIMEOUT_WALL_S + SLACK_S + 0.3)
            (first_after, _), *_ = [(s, p) for s, p in driver.after(last)
                                            if p == PRELOAD]
            assert TIMEOUT_WALL_S <= first_after - last <= TIMEOUT_WALL_S + SLACK_S
            assert all(p == PRELOAD for _, p in driver.after(first_after))

            # a command outside the rating (7 kPa per valve) is never forwarded: the preload is
            refused_at = driver.send([7.5, 0.0, 0.0])
            driver.spin(0.2)
            after = driver.after(refused_at)
            assert after and after[0][1] == PRELOAD and after[0][0] - refused_at < 0.15
            sent = driver.send([4.0, 4.0, 6.0])  # sum 14 > 13: outside as well
            driver.spin(0.2)
            assert driver.after(sent)[0][1] == PRELOAD
            assert max(max(p) for _, p in driver.received) <= 7.0
            assert max(sum(p) for _, p in driver.received) <= 13.0
    finally:
        code = stop(guard)
    log = pipe.log("guard")
    assert code == 1, log
    assert "guard: 2 command(s) outside the arm's rating were refused" in log
    assert ("refusing pressure command [7.5, 0.0, 0.0] kPa outside the arm's rating robot.rating: "
            "[0.0, 7.0] per valve, sum <= 13.0") in log
    assert ("guard: no command on /control_pressure for robot.command_timeout_s=1.5 s: "
            "publishing the preload [2.0, 2.0, 2.0] kPa") in log
