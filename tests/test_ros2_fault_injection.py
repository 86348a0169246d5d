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
    with pipe.twin(record):
        code, resumed_ns = stopped_5_s(pipe, pipe.start("collect"), "collect",
                                       "run ros2-000 started", timeout_s=120, running_s=1.0)
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
    with pipe.twin(record):
        code, resumed_ns = stopped_5_s(
            pipe, pipe.start("control", *control_overrides(sim_cfg, policy_file)), "control",
            "arm ready", timeout_s=240, running_s=1.5)
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


# ---- the arm side killed mid-run; a twin left running -------------------------------------------
def one_line_error(log: str, kind: str) -> str:
    """The stage's error: one line naming ``kind``, no traceback (HYDRA_FULL_ERROR unset)."""
    assert "Traceback" not in log, log
    (line,) = [line for line in log.splitlines() if f"{kind}: " in line]
    return line[line.index(f"{kind}: "):]  # after the log record's time and logger


def plain_errors(pipe: Pipeline) -> Pipeline:
    """Known errors as users see them: one line, no traceback."""
    pipe.env.pop("HYDRA_FULL_ERROR", None)
    return pipe


def killed_mid_run(pipe, stage_process, stage: str, ready: str, victim, running_s: float,
                   timeout_s: float = 120) -> tuple[int, float]:
    """Once ``stage`` logs ``ready`` and ran ``running_s`` more, SIGKILL ``victim`` (the arm
    side): ``(the stage's exit code, time.time_ns() at the kill)``."""
    try:
        pipe.wait_for_log(stage, ready, timeout_s=timeout_s)
        time.sleep(running_s)
        victim.send_signal(signal.SIGKILL)
        killed_ns = time.time_ns()
        victim.wait(timeout=30)
        code = stage_process.wait(timeout=60)
    finally:
        for process in (stage_process, victim):
            if process.poll() is None:
                process.kill()
    return code, killed_ns


def test_the_twin_killed_mid_collect_stops_it_with_one_line_and_keeps_the_records(
        tmp_path, ros_domain):
    import pandas as pd

    from pipeline.data.schemas import CMD_COLUMNS
    from pipeline.infra.artifacts import ArtifactStore
    from pipeline.keys import key
    from pipeline.stages.collect import STAGE

    pipe = plain_errors(Pipeline(tmp_path, ros_domain, "exploration.num_steps=200"))
    record = tmp_path / "twin.jsonl"
    twin = pipe.start_twin(record)
    code, _ = killed_mid_run(pipe, pipe.start("collect"), "collect", "run ros2-000 started", twin,
                             running_s=1.0)
    log = pipe.log("collect")
    assert code == 1, log
    line = one_line_error(log, "CollectionInterrupted")
    assert "collect interrupted: mocap watchdog: no pose on /mocap_rigid_bodies/" in line, line
    cfg = pipe.cfg()
    artifact = ArtifactStore(cfg.paths.artifact_dir).require(STAGE, key("collect", cfg))
    assert artifact.manifest["summary"]["interrupted"].startswith("mocap watchdog: no pose on")
    runs = pd.read_parquet(artifact.file("runs.parquet"))
    assert not runs.loc[0, "complete"] and runs.loc[0, "n_frames"] > 100
    recorded = pd.read_parquet(artifact.file("commands.parquet"))[CMD_COLUMNS].to_numpy()
    rows = wire(record)
    assert_safe_wire(rows)
    assert not any(r.get("deadman") or "refused" in r for r in rows)  # killed mid-walk
    on_wire = np.array([r["pressures"] for r in rows])
    # what the twin received before it died is what collect recorded first; collect sent a few
    # more into the void until the watchdog (robot.watchdog_s: 1 s of wall time) stopped it
    assert len(on_wire) >= 6
    np.testing.assert_allclose(recorded[:len(on_wire)], on_wire, atol=1e-9)
    assert 0 <= len(recorded) - len(on_wire) <= 1.0 / PERIOD_WALL_S + 4
    assert_safe_wire([{"pressures": p} for p in recorded.tolist()])


def test_the_twin_killed_mid_control_stops_it_with_one_line_and_keeps_the_records(
        tmp_path, ros_domain):
    import pandas as pd

    from pipeline.data.schemas import CMD_COLUMNS
    from tests.test_control_ros import ROS, control_artifact, control_overrides, sim_policy

    sim_cfg, policy_file = sim_policy(tmp_path, "ppo_ff", hold_s=60.0)
    pipe = plain_errors(Pipeline(tmp_path, ros_domain))
    pipe.overrides = ROS
    record = tmp_path / "twin.jsonl"
    twin = pipe.start_twin(record)
    overrides = control_overrides(sim_cfg, policy_file)
    code, _ = killed_mid_run(pipe, pipe.start("control", *overrides), "control", "arm ready",
                             twin, running_s=1.5, timeout_s=240)
    log = pipe.log("control")
    assert code == 1, log
    line = one_line_error(log, "ControlInterrupted")
    assert "control interrupted: mocap watchdog: " in line, line
    artifact = control_artifact(pipe, *overrides)
    assert artifact.manifest["summary"]["interrupted"].startswith("mocap watchdog: ")
    periods = pd.read_parquet(artifact.file("periods.parquet"))
    sent = periods[periods["goal_index"] >= 0][CMD_COLUMNS].to_numpy()
    rows = wire(record)
    assert_safe_wire(rows, {"p_min": 0.0, "p_max": 7.0, "sum_max": 13.0})  # the rating
    on_wire = np.array([r["pressures"] for r in rows if not r.get("deadman")])
    assert len(on_wire) >= 4
    np.testing.assert_allclose(sent[:len(on_wire)], on_wire, atol=1e-9)
    # periods after the kill until the watchdog (robot.watchdog_s=1 s: 0.25 s of wall time, two
    # periods; up to 1 s of wall time on a busy machine)
    assert 0 <= len(sent) - len(on_wire) <= 1.0 / PERIOD_WALL_S


def test_a_twin_left_running_refuses_a_rehearsal_before_any_command(tmp_path, ros_domain):
    from pipeline.infra.artifacts import ArtifactStore
    from pipeline.keys import key
    from pipeline.stages.collect import STAGE

    pipe = plain_errors(Pipeline(tmp_path, ros_domain, "exploration.num_steps=40"))
    records = [tmp_path / "left_over.jsonl", tmp_path / "twin.jsonl"]
    twins = [pipe.start("twin", f"robot.twin.record_path={record}", "robot.twin.max_duration_s=90",
                        name=record.stem) for record in records]
    try:
        for record in records:
            pipe.wait_for_log(record.stem, "twin: simulated arm on", timeout_s=120)
        collect = pipe.start("collect")
        code = collect.wait(timeout=120)
    finally:
        codes = [stop(twin) for twin in twins]
    log = pipe.log("collect")
    assert code == 1, log
    line = one_line_error(log, "ArmRefused")
    # which of the two the stage sees first is a matter of discovery (a node's name too: until
    # it is known the graph says _NODE_NAME_UNKNOWN_)
    subscribers = (line.startswith("ArmRefused: refusing to publish on /control_pressure: 2 "
                                   "subscriber(s) of /control_pressure: [")
                   and line.endswith("only the twin 'sorolearn_twin' may listen (a twin or "
                                     "recorder left running on the rehearsal domain? stop it)"))
    publishers = "ArmFault: 2 publishers on /mocap_rigid_bodies/rigid_bodies_1/pose: " in line
    assert subscribers or publishers, line
    assert "nothing was commanded" in log
    assert codes == [0, 0], [pipe.log(record.stem) for record in records]
    for record in records:  # not even the preload: a refused start commands nothing
        assert wire(record) == []
    cfg = pipe.cfg()
    assert ArtifactStore(cfg.paths.artifact_dir).find(STAGE, key("collect", cfg)) is None
    assert not list((pipe.out / "recovery").glob("*/*"))


# A killed node stays on the ROS graph until its DDS lease runs out (Fast DDS: 20 s by default);
# the arm side's processes announce a 2 s lease here, as docs/safety.md advises for a lab.
SHORT_LEASE = """<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <participant profile_name="short_lease" is_default_profile="true">
      <rtps><builtin><discovery_config>
        <leaseDuration><sec>2</sec></leaseDuration>
        <leaseAnnouncement><sec>0</sec><nanosec>500000000</nanosec></leaseAnnouncement>
      </discovery_config></builtin></rtps>
    </participant>
  </profiles>
</dds>
"""
REAL_ARM = ["robot=ros2", "robot.stop_timeout_s=0.5", "robot.flush_every_s=0.5",
            "robot.startup_timeout_s=60", "exploration.pad_steps=2", "exploration.num_steps=200",
            *(f"robot.limits.{k}={v}" for k, v in LIMITS.items())]


class LabSide:
    """The lab around a real guard, in this process: a motion capture publishing poses at 100 Hz
    (stamped on receipt's clock, frame ``mocap``) and a valve driver recording what the guard
    forwards (``received``: (time.time_ns(), kPa)), spun in a thread."""

    def __init__(self, domain: int):
        self.domain = domain
        self.received: list[tuple[float, list[float]]] = []

    def __enter__(self) -> LabSide:
        import threading

        from geometry_msgs.msg import PoseStamped
        from std_msgs.msg import Float64MultiArray

        from pipeline.ros2.node import ros_node

        self._context = ros_node("lab_side", self.domain)
        node, executor = self._context.__enter__()
        poses = node.create_publisher(PoseStamped, "/mocap_rigid_bodies/rigid_bodies_1/pose", 10)

        def publish_pose() -> None:
            message = PoseStamped()
            message.header.stamp = node.get_clock().now().to_msg()
            message.header.frame_id = "mocap"
            message.pose.position.x, message.pose.position.y = 0.03, 0.35
            message.pose.position.z = 0.2
            poses.publish(message)

        node.create_timer(0.01, publish_pose)
        node.create_subscription(Float64MultiArray, "/control_pressure/guarded",
                                 lambda m: self.received.append((time.time_ns(), list(m.data))),
                                 10)
        self._running = True

        def spin() -> None:
            while self._running:
                executor.spin_once(timeout_sec=0.005)

        self._thread = threading.Thread(target=spin, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._running = False
        self._thread.join(timeout=10)
        self._context.__exit__(*exc)


def lab_with_a_guard(tmp_path, ros_domain, monkeypatch):
    """A pipeline of the real arm's config (real time, no rehearsal, on its domain) and its
    guard process, started."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    pipe = plain_errors(Pipeline(tmp_path, ros_domain))
    pipe.overrides = REAL_ARM
    (tmp_path / "lease.xml").write_text(SHORT_LEASE)
    pipe.env["FASTDDS_DEFAULT_PROFILES_FILE"] = str(tmp_path / "lease.xml")
    return pipe, pipe.start("guard", "robot.guard.max_duration_s=300")


GUARD_KILLED = ("ArmFault: the guard 'sorolearn_guard' no longer subscribes to /control_pressure "
                "(stopped or killed): nothing guards the valves")


def test_the_guard_killed_mid_collect_stops_it_with_one_line(tmp_path, ros_domain, monkeypatch):
    import pandas as pd

    from pipeline.data.schemas import CMD_COLUMNS
    from pipeline.infra.artifacts import ArtifactStore
    from pipeline.keys import key
    from pipeline.stages.collect import STAGE

    pipe, guard = lab_with_a_guard(tmp_path, ros_domain, monkeypatch)
    with LabSide(ros_domain) as lab:
        pipe.wait_for_log("guard", "answering on", timeout_s=120)
        collect = pipe.start("collect")
        code, killed_ns = killed_mid_run(pipe, collect, "collect", "run ros2-000 started", guard,
                                         running_s=2.0)
        time.sleep(0.5)
    log = pipe.log("collect")
    assert code == 1, log
    line = one_line_error(log, "CollectionInterrupted")
    assert f"collect interrupted: {GUARD_KILLED}" in line, line
    cfg = pipe.cfg()
    artifact = ArtifactStore(cfg.paths.artifact_dir).require(STAGE, key("collect", cfg))
    assert "no longer subscribes" in artifact.manifest["summary"]["interrupted"]
    assert not pd.read_parquet(artifact.file("runs.parquet")).loc[0, "complete"]
    recorded = pd.read_parquet(artifact.file("commands.parquet"))[CMD_COLUMNS].to_numpy()
    # what reached the valve driver: the guard's preloads, then the walk as collect recorded it,
    # nothing once the guard was killed
    driver = np.array([p for _, p in lab.received])
    assert_safe_wire([{"pressures": p} for p in driver.tolist()])
    assert all(t < killed_ns + 50_000_000 for t, _ in lab.received)
    walk = [p for p in recorded.tolist() if p != PRELOAD]
    forwarded = [p for p in driver.tolist() if p != PRELOAD]
    assert len(forwarded) >= 2 and forwarded == walk[:len(forwarded)]
    # the graph drops the killed guard after its lease (2 s), counted every 0.5 s: until then
    # collect sends a few commands into the void (2 Hz)
    (run,) = artifact.manifest["summary"]["ros2"]["runs"]
    sent_ns = run["start_ns"] + pd.read_parquet(artifact.file("commands.parquet"))["t"] * 1e9
    assert 1 <= (sent_ns > killed_ns).sum() <= (2.0 + 0.5 + 1.0) / 0.5


def test_the_guard_killed_mid_control_stops_it_with_one_line(tmp_path, ros_domain, monkeypatch):
    import pandas as pd

    from pipeline.data.schemas import CMD_COLUMNS
    from tests.test_control_ros import control_artifact, control_overrides, sim_policy

    sim_cfg, policy_file = sim_policy(tmp_path, "ppo_ff", hold_s=60.0)
    pipe, guard = lab_with_a_guard(tmp_path, ros_domain, monkeypatch)
    overrides = control_overrides(sim_cfg, policy_file)
    with LabSide(ros_domain) as lab:
        pipe.wait_for_log("guard", "answering on", timeout_s=120)
        code, killed_ns = killed_mid_run(pipe, pipe.start("control", *overrides), "control",
                                         "arm ready", guard, running_s=2.0, timeout_s=240)
        time.sleep(0.5)
    log = pipe.log("control")
    assert code == 1, log
    line = one_line_error(log, "ControlInterrupted")
    assert f"control interrupted: {GUARD_KILLED}" in line, line
    artifact = control_artifact(pipe, *overrides)
    assert "no longer subscribes" in artifact.manifest["summary"]["interrupted"]
    periods = pd.read_parquet(artifact.file("periods.parquet"))
    sent = periods[periods["goal_index"] >= 0]
    driver = [p for _, p in lab.received]
    assert_safe_wire([{"pressures": p} for p in driver], {"p_min": 0.0, "p_max": 7.0,
                                                          "sum_max": 13.0})
    assert all(t < killed_ns + 50_000_000 for t, _ in lab.received)
    forwarded = [p for p in driver if p != PRELOAD]
    policy = [p for p in sent[CMD_COLUMNS].to_numpy().tolist() if p != PRELOAD]
    assert len(forwarded) >= 2 and forwarded == policy[:len(forwarded)]
    # periods sent into the void after the kill, until the graph dropped the guard (its 2 s
    # lease, counted every 0.5 s; 2 Hz)
    assert 1 <= len(policy) - len(forwarded) <= (2.0 + 0.5 + 1.0) / 0.5, len(policy)


@pytest.mark.parametrize(("offset_s", "message"), [
    (0.3, r"ArmFault: clocks: a pose stamped 0\.[23]\d\d s after it was received: the motion "
          r"capture's clock \(its header stamps\) runs ahead of this computer's ROS clock \(pose "
          r"topic /mocap_rigid_bodies/rigid_bodies_1/pose\)$"),
    (-0.5, r"ArmFault: clocks: every pose over the last 1 s arrived at least 0\.5\d\d s after its "
           r"header stamp, above robot\.max_pose_latency_s=0\.25 s: the motion capture's clock "
           r"runs behind this computer's ROS clock"),
])
def test_a_mocap_clock_apart_refuses_collect_with_one_line(tmp_path, ros_domain, offset_s,
                                                           message):
    import re

    pipe = plain_errors(Pipeline(tmp_path, ros_domain, "exploration.num_steps=40"))
    record = tmp_path / "twin.jsonl"
    twin = pipe.start("twin", f"robot.twin.record_path={record}", "robot.twin.max_duration_s=90",
                      f"robot.twin.clock_offset_s={offset_s}")
    try:
        code = pipe.start("collect").wait(timeout=120)
    finally:
        assert stop(twin) == 0, pipe.log("twin")
    log = pipe.log("collect")
    assert code == 1, log
    assert re.search(message, one_line_error(log, "ArmFault")), log
    assert "nothing was commanded" in log
    assert wire(record) == []  # refused before the first command
