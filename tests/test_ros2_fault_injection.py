"""Fault injection over ROS 2 on localhost: the digital twin and the stages as separate rclpy
processes (the arm's time 4x the wall clock, each test on its own ROS domain, as in
``test_ros2_link.py``). In every case the arm ends at the preload, no command leaves the rating,
and never more than one command per control period reaches the arm.
"""

from __future__ import annotations

import json
import signal
import time

import numpy as np
import pytest

from tests.ros_required import require_ros
from tests.test_ros2_link import LIMITS, TIME_SCALE, Pipeline, stop

require_ros("rclpy")
pytestmark = [pytest.mark.ros, pytest.mark.slow]

PERIOD_WALL_S = 0.5 / TIME_SCALE
PRELOAD = [2.0, 2.0, 2.0]


def wire(record) -> list[dict]:
    return [json.loads(line) for line in record.read_text().splitlines()]


def commands_after(rows: list[dict], t_ns: int) -> list[dict]:
    return [r for r in rows if r["receipt_ns"] >= t_ns and not r.get("deadman")
            and not r.get("ignored") and "refused" not in r]


def assert_safe_wire(rows: list[dict], limits: dict = LIMITS) -> None:
    pressures = np.array([r["pressures"] for r in rows if not r.get("ignored")])
    assert np.isfinite(pressures).all()
    assert pressures.min() >= limits["p_min"] and pressures.max() <= limits["p_max"]
    assert pressures.sum(axis=1).max() <= limits["sum_max"] + 1e-9


def stopped_5_s(pipe, process, stage: str, ready: str, timeout_s: float, running_s: float
                ) -> tuple[int, int]:
    """Once ``stage`` logs ``ready`` and has run ``running_s`` more, SIGSTOP it for 5 s, then
    SIGCONT: ``(its exit code, time.time_ns() at the SIGCONT)``; killed if still running."""
    try:
        pipe.wait_for_log(stage, ready, timeout_s=timeout_s)
        time.sleep(running_s)
        process.send_signal(signal.SIGSTOP)
        time.sleep(5.0)
        resumed_ns = time.time_ns()
        process.send_signal(signal.SIGCONT)
        code = process.wait(timeout=60)
        time.sleep(0.3)
    finally:
        if process.poll() is None:
            process.kill()
    return code, resumed_ns


def test_collect_stopped_5_s_ends_at_the_preload_without_a_burst(tmp_path, ros_domain):
    pipe = Pipeline(tmp_path, ros_domain, "exploration.num_steps=200")
    record = tmp_path / "twin.jsonl"
    twin = pipe.start_twin(record)
    try:
        code, resumed_ns = stopped_5_s(pipe, pipe.start("collect"), "collect",
                                       "run ros2-000 started", timeout_s=120, running_s=1.0)
    finally:
        assert stop(twin) == 0, pipe.log("twin")
    log = pipe.log("collect")
    assert code != 0, log
    assert "CollectionInterrupted" in log
    rows = wire(record)
    assert_safe_wire(rows)
    assert any(r.get("deadman") for r in rows)  # the twin's deadman during the stall
    after = commands_after(rows, resumed_ns)
    # after the stall: the preload only (a command already in flight at most)
    assert after and after[-1]["pressures"] == PRELOAD, after
    assert len(after) <= 2, after


def test_control_stopped_5_s_ends_at_the_preload_without_a_burst(tmp_path, ros_domain):
    from tests.test_control_ros import ROS, control_overrides, sim_policy

    sim_cfg, policy_file = sim_policy(tmp_path, "ppo_ff", hold_s=60.0)
    pipe = Pipeline(tmp_path, ros_domain)
    pipe.overrides = ROS
    record = tmp_path / "twin.jsonl"
    twin = pipe.start_twin(record)
    try:
        code, resumed_ns = stopped_5_s(
            pipe, pipe.start("control", *control_overrides(sim_cfg, policy_file)), "control",
            "arm ready", timeout_s=240, running_s=1.5)
    finally:
        assert stop(twin) == 0, pipe.log("twin")
    log = pipe.log("control")
    assert code != 0, log
    assert "ControlInterrupted" in log
    rows = wire(record)
    assert_safe_wire(rows, {"p_min": 0.0, "p_max": 7.0, "sum_max": 13.0})  # the rating
    after = commands_after(rows, resumed_ns)
    assert after and after[-1]["pressures"] == PRELOAD, after
    assert len(after) <= 2, after


def test_a_second_publisher_sends_the_twin_to_the_preload(tmp_path, ros_domain):
    from std_msgs.msg import Float64MultiArray

    from pipeline.ros2.node import ros_node

    pipe = Pipeline(tmp_path, ros_domain, "exploration.num_steps=200")
    record = tmp_path / "twin.jsonl"
    twin = pipe.start_twin(record)
    try:
        collect = pipe.start("collect")
        pipe.wait_for_log("collect", "run ros2-000 started", timeout_s=120)
        with ros_node("second_publisher", ros_domain) as (node, executor):
            publisher = node.create_publisher(Float64MultiArray, "/control_pressure", 10)
            until = time.monotonic() + 60.0  # discovery takes a while on a busy machine
            while "exactly one is accepted" not in pipe.log("twin"):
                assert time.monotonic() < until, pipe.log("twin")
                message = Float64MultiArray()
                message.data = [4.0, 4.0, 4.0]
                publisher.publish(message)
                executor.spin_once(timeout_sec=0.05)
        stop(collect)
        code = stop(twin)
    finally:
        for process in (collect, twin):
            if process.poll() is None:
                process.kill()
    assert code == 1, pipe.log("twin")
    assert "UnsafeCommandError: twin: 2 publishers on /control_pressure" in pipe.log("twin")
    rows = wire(record)
    assert_safe_wire(rows)
    (refusal,) = [r for r in rows if "refused" in r]
    later = [r for r in rows if r["receipt_ns"] > refusal["receipt_ns"]]
    assert refusal["pressures"] == PRELOAD
    assert all(r.get("ignored") for r in later)  # nothing applied after the refusal
    # what the second publisher sent before the twin saw it on the graph may have been applied
    # (discovery lags delivery): within the rating, and the arm ended at the preload
