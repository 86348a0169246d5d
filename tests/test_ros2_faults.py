"""The real-arm path's safety logic on fake nodes and an injectable clock (no ROS graph): collect's
command loop without catch-up, its pose-source and clock checks and its refused start; the
guard's deadman, refusals, single publisher and final preload; the handshake's rules."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from omegaconf import OmegaConf

from pipeline.arm.limits import UnsafeCommandError
from pipeline.ros2.collector import ArmFault, ClockCheck, Session
from pipeline.ros2.gate import CommandGate
from pipeline.ros2.guard import Deadman, GuardNode
from pipeline.ros2.handshake import answer_of, handshake_problem
from pipeline.ros2.node import ArmRefused
from pipeline.ros2.recorder import ChunkedRecorder
from pipeline.schemas import Ros2RobotConfig
from tests.ros_required import require_ros

require_ros("std_msgs")

NS = 1_000_000_000
PRELOAD = [2.0, 2.0, 2.0]
RATING = {"p_min": 0.0, "p_max": 7.0, "sum_max": 13.0, "preload": 2.0, "n_valves": 3}


def robot_config(**overrides):
    values = {
        "name": "ros2", "n_valves": 3, "control_hz": 2.0, "time_scale": 1.0, "watchdog_s": 0.5,
        "command_timeout_s": 1.5, "startup_timeout_s": 2.0, "flush_every_s": 100.0,
        "stop_timeout_s": 0.1, "max_missed_periods": 2, "max_pose_latency_s": 0.25,
        "rehearsal": False, "rehearsal_domain_id": 42, "domain_id": None,
        "command_topic": "/control_pressure", "command_type": "std_msgs/msg/Float64MultiArray",
        "command_field": "data", "pose_topic": "/mocap/pose", "pose_type": "x",
        "command_qos": {"reliability": "reliable", "durability": "volatile", "depth": 10},
        "pose_qos": {"reliability": "best_effort", "durability": "volatile", "depth": 100},
        "limits": {k: v for k, v in RATING.items() if k != "n_valves"}, "rating": RATING,
        "guard": {"output_topic": "/control_pressure/guarded", "node_name": "sorolearn_guard",
                  "handshake_topic": "/sorolearn/arm_handshake", "max_duration_s": None},
    }
    schema = OmegaConf.structured(Ros2RobotConfig)
    return OmegaConf.to_object(OmegaConf.merge(schema, {**values, **overrides}))


# ---- collect's loop on a fake link -----------------------------------------------------------
class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class FakeLink:
    """Poses every 10 ms of the clock (stamped by it, so latency 0, or ``clock_offset_s`` ahead
    of it); ``jumps`` {at s: seconds} stall the process once the clock passes ``at``."""

    def __init__(self, clock: Clock, jumps=None, answer=None, publishers=("mocap",),
                 subscribers=("sorolearn_guard",), poses: bool = True, clock_offset_s=0.0):
        self.clock, self.jumps = clock, dict(jumps or {})
        self.poses: list = []
        self.wire: list[tuple[float, list[float]]] = []
        self.published = 0
        self.last_pose_at = clock() if poses else None
        self.newest_stamp_ns = None
        self.frame_id, self.frame_id_changed = "mocap", None
        self.handshake = SimpleNamespace(answer=answer, unreadable=None)
        self.publishers, self.listeners, self.emit = list(publishers), list(subscribers), poses
        self.offset_ns = round(clock_offset_s * NS)  # the stamps' clock ahead of ours
        self._next_pose = clock()
        self.spin_once(0.0)  # a first pose, as collect has before its first command

    def now_ns(self) -> int:
        return round(self.clock() * NS)

    def spin_once(self, timeout_s: float) -> None:
        for at, jump in list(self.jumps.items()):
            if self.clock() - 100.0 >= at:
                del self.jumps[at]
                self.clock.t += jump
                self._next_pose = self.clock()
        self.clock.t += max(timeout_s, 1e-4)
        skew = self.now_ns() - round(self.clock() * NS)  # this computer's ROS clock - the true
        while self.emit and self._next_pose <= self.clock():
            true = round(self._next_pose * NS)
            stamp = true + self.offset_ns
            self.poses.append((stamp, true + skew, (0.03, 0.35, 0.2)))
            self.newest_stamp_ns, self.last_pose_at = stamp, self.clock()
            self._next_pose += 0.01

    def take_poses(self):
        poses, self.poses = self.poses, []
        return poses

    def silence_s(self, watchdog_wall_s: float) -> float:
        return (self.now_ns() - self.newest_stamp_ns) / NS

    def publish(self, pressures) -> int:
        self.wire.append((self.clock() - 100.0, np.asarray(pressures, float).tolist()))
        self.published += 1
        return self.now_ns()

    def subscribers(self) -> int:
        return len(self.listeners)

    def command_subscribers(self) -> list[str]:
        return self.listeners

    def pose_publishers(self) -> list[str]:
        return self.publishers

    def wait_for_acks(self, timeout_s: float) -> bool:
        return True


def session(tmp_path, link, clock, **robot):
    cfg = robot_config(**robot)
    gate = CommandGate.for_robot(cfg)
    recorder = ChunkedRecorder(tmp_path / "rec", {}, {})
    return Session(cfg, link, gate, recorder, SimpleNamespace(received=None), clock=clock)


def walk(n: int = 10) -> np.ndarray:
    """Valve 0 from 2.5 kPa up by 0.5 per command, valves 1 and 2 at 2."""
    steps = np.arange(1, n + 1)[:, None] * np.array([0.5, 0.0, 0.0])
    return np.full((n, 3), 2.0) + steps


def windows(wire) -> list[int]:
    return [int((t + 0.005) // 0.5) for t, _ in wire]


def test_collect_on_time_publishes_the_walk_one_command_per_period(tmp_path):
    clock = Clock()
    link = FakeLink(clock)
    run = session(tmp_path, link, clock)
    assert run.play([("r0", walk())]) is None
    assert [p[0] for _, p in link.wire] == [2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5, 6.0, 6.5, 7.0]
    assert len(set(windows(link.wire))) == 10 and run.stalls == []


def test_collect_after_a_stall_skips_the_overdue_commands_and_holds_the_last(tmp_path):
    # stalled 1.2 s after command 3 (t = 1.5 s): at 2.8 s command 4 is 0.8 s overdue, so it is
    # never sent; command 5's period holds command 3's pressures; the walk goes on with command 6
    clock = Clock()
    link = FakeLink(clock, jumps={1.6: 1.2})
    run = session(tmp_path, link, clock)
    assert run.play([("r0", walk())]) is None
    assert [p[0] for _, p in link.wire] == [2.5, 3.0, 3.5, 4.0, 4.0, 5.5, 6.0, 6.5, 7.0]
    assert len(set(windows(link.wire))) == len(link.wire)  # never two in one period
    (stall,) = run.stalls
    assert stall["command"] == 4 and stall["missed_periods"] == 1
    assert stall["late_s"] == pytest.approx(0.8, abs=0.02)
    assert run.link_summary()["missed_periods"] == 1
    commands, _ = run.recorder.read_all()
    np.testing.assert_allclose(commands[["p_cmd_0", "p_cmd_1", "p_cmd_2"]].to_numpy(),
                               [p for _, p in link.wire])  # the rows are what went out


def test_collect_stalled_beyond_max_missed_periods_stops_then_commands_the_preload(tmp_path):
    clock = Clock()
    link = FakeLink(clock, jumps={1.6: 2.0})
    run = session(tmp_path, link, clock)
    stopped = run.play([("r0", walk())])
    assert stopped.reason.startswith("the command loop woke 1.6")
    assert ("s after the tick of command 4 of run r0: 3 periods missed in a row, more than "
            "robot.max_missed_periods=2") in stopped.reason
    run.stop_safely()
    assert [p for _, p in link.wire][-2:] == [[4.0, 2.0, 2.0], PRELOAD]
    assert len(link.wire) == 5


def test_a_stop_signal_mid_collect_ends_at_the_preload_and_keeps_the_records(tmp_path):
    # Ctrl-C (or SIGTERM) as collect's StopSignals record it, after the third command went out
    clock = Clock()
    link = FakeLink(clock)
    run = session(tmp_path, link, clock)
    publish = link.publish

    def publish_then_signal(pressures):
        stamp = publish(pressures)
        if len(link.wire) == 3:
            run.signals.received = "SIGINT"
        return stamp

    link.publish = publish_then_signal
    stopped = run.play([("r0", walk())])
    assert stopped.reason == "SIGINT received"
    run.stop_safely()
    assert [p for _, p in link.wire] == [[2.5, 2.0, 2.0], [3.0, 2.0, 2.0], [3.5, 2.0, 2.0],
                                         PRELOAD]
    commands, _ = run.recorder.read_all()
    assert len(commands) == 3  # every command that went out, and only those


def test_stop_signals_become_a_flag_the_loop_polls_and_the_handlers_come_back():
    import os
    import signal

    from pipeline.ros2.node import StopSignals

    before = {sig: signal.getsignal(sig) for sig in StopSignals.SIGNALS}
    with StopSignals() as signals:
        os.kill(os.getpid(), signal.SIGTERM)  # delivered before kill returns (own thread)
        assert signals.received == "SIGTERM"
        os.kill(os.getpid(), signal.SIGINT)  # a second signal cannot cut the safe stop short
        assert signals.received == "SIGTERM"
    assert {sig: signal.getsignal(sig) for sig in StopSignals.SIGNALS} == before


def test_the_float64_check_refuses_inside_collects_publish_path(tmp_path, monkeypatch):
    # a projection that lets an unsafe command through (a bug upstream): 2.5 + 4.5 kPa on valve 0
    # is 7.0 kPa, at the rating, and goes out; 3 + 4.5 = 7.5 kPa is refused
    clock = Clock()
    link = FakeLink(clock)
    run = session(tmp_path, link, clock)
    monkeypatch.setattr(run.gate, "project", lambda p: np.asarray(p, float) + np.array([4.5, 0, 0]))
    stopped = run.play([("r0", walk())])
    assert isinstance(stopped.error, UnsafeCommandError)
    assert ("refusing pressure command [7.5, 2.0, 2.0] kPa outside the arm's rating"
            in stopped.reason)
    run.stop_safely()
    assert [p for _, p in link.wire] == [[7.0, 2.0, 2.0], PRELOAD]


@pytest.mark.parametrize(("change", "message"), [
    ({"publishers": ["mocap", "sorolearn_twin"]},
     "2 publishers on /mocap/pose: mocap, sorolearn_twin; exactly one source of poses"),
    ({"frame_id_changed": "sorolearn_twin"},
     "the poses on /mocap/pose changed frame_id from 'mocap' to 'sorolearn_twin'"),
    ({"listeners": ["sorolearn_guard", "rosbag2_recorder"]},
     "2 subscribers of /control_pressure: sorolearn_guard, rosbag2_recorder"),
    ({"listeners": []}, "the guard 'sorolearn_guard' no longer subscribes to /control_pressure"),
])
def test_collect_stops_on_a_second_source_or_listener(tmp_path, change, message):
    clock = Clock()
    link = FakeLink(clock)
    run = session(tmp_path, link, clock)
    run.guard_node = "sorolearn_guard"  # as the handshake left it

    def plan():
        yield "r0", walk(3)
        for name, value in change.items():
            setattr(link, name, value)
        yield "r1", walk(10)

    stopped = run.play(plan())
    assert isinstance(stopped.error, ArmFault) and message in stopped.reason
    assert len(link.wire) <= 3 + 2  # the second run stopped within a check (0.5 s)


def test_the_clock_check_by_hand():
    check = ClockCheck(max_latency_s=0.25)
    # a pose stamped 20 ms in the future: the clocks are apart at once
    assert "stamped 0.020 s after it was received" in check.problem(10_020_000_000, 10 * NS)
    check = ClockCheck(max_latency_s=0.25)
    # 100 poses queued behind a stall arrive at once, 1 s late: not judged (no 1 s of receipts)
    for i in range(100):
        assert check.problem(round((9.0 + i * 0.01) * NS), 10 * NS) is None
    # then fresh poses, 5 ms late, for 1 s: the best latency is 5 ms
    for i in range(1, 101):
        assert check.problem(round((10 + i * 0.01 - 0.005) * NS), round((10 + i * 0.01) * NS)) \
            is None
    # a mocap clock 0.3 s behind: refused once a whole second of poses was that late
    check = ClockCheck(max_latency_s=0.25)
    problems = [check.problem(round((20 + i * 0.01 - 0.3) * NS), round((20 + i * 0.01) * NS))
                for i in range(100)]
    assert problems[:89] == [None] * 89
    assert "arrived at least 0.300 s after its header stamp" in problems[95]


@pytest.mark.parametrize(("link_args", "message"), [
    ({"answer": None}, "no answer from a guard on /sorolearn/arm_handshake within "
                       "robot.startup_timeout_s=2.0 s: are the arm's driver and the guard"),
    ({"poses": False}, "no pose on /mocap/pose (x) within robot.startup_timeout_s=2.0 s"),
    ({"subscribers": ["sorolearn_guard", "valve_driver"]},
     "refusing to publish on /control_pressure: 2 subscriber(s) of /control_pressure: "
     "['sorolearn_guard', 'valve_driver']; only the guard 'sorolearn_guard' may listen"),
    ({"answer": answer_of(robot_config(), "twin", "sorolearn_twin"),
      "subscribers": ["sorolearn_twin"]},
     "refusing to publish on /control_pressure: robot.rehearsal=false (a real arm), but the arm "
     "side is the digital twin ('sorolearn_twin')"),
])
def test_collect_refuses_to_start_without_the_guards_answer(tmp_path, link_args, message):
    clock = Clock()
    args = {"answer": answer_of(robot_config(), "guard", "sorolearn_guard"), **link_args}
    link = FakeLink(clock, **args)
    run = session(tmp_path, link, clock)
    with pytest.raises(ArmRefused) as err:
        run.wait_for_arm()
    assert str(err.value).startswith(message) or message in str(err.value), str(err.value)
    run.stop_safely()
    assert link.wire == []  # a refused start commands nothing, not even the preload


def test_collect_refuses_a_second_twin_discovered_after_the_first_answer(tmp_path):
    # a twin left running on the rehearsal domain: its subscription to the commands is discovered
    # 0.3 s after the first twin's answer matched, still before the first command
    clock = Clock()
    answer = answer_of(robot_config(rehearsal=True), "twin", "sorolearn_twin")
    link = FakeLink(clock, answer=answer, subscribers=["sorolearn_twin"])
    spin_once = link.spin_once

    def discovering(timeout_s: float) -> None:
        spin_once(timeout_s)
        if clock() >= 100.3:
            link.listeners = ["sorolearn_twin", "sorolearn_twin"]

    link.spin_once = discovering
    run = session(tmp_path, link, clock, rehearsal=True)
    with pytest.raises(ArmRefused) as err:
        run.wait_for_arm()
    assert str(err.value).startswith(
        "refusing to publish on /control_pressure: 2 subscriber(s) of /control_pressure: "
        "['sorolearn_twin', 'sorolearn_twin']; only the twin 'sorolearn_twin' may listen (a twin "
        "or recorder left running on the rehearsal domain? stop it)"), str(err.value)
    run.stop_safely()
    assert link.wire == []


@pytest.mark.parametrize(("offset_s", "message"), [
    (0.3, "clocks: a pose stamped 0.300 s after it was received: the motion capture's clock (its "
          "header stamps) runs ahead of this computer's ROS clock (pose topic /mocap/pose)"),
    (-0.3, "clocks: every pose over the last 1 s arrived at least 0.300 s after its header "
           "stamp, above robot.max_pose_latency_s=0.25 s: the motion capture's clock runs behind "
           "this computer's ROS clock"),
])
def test_collect_refuses_to_start_when_the_clocks_are_apart(tmp_path, offset_s, message):
    clock = Clock()
    link = FakeLink(clock, answer=answer_of(robot_config(), "guard", "sorolearn_guard"),
                    clock_offset_s=offset_s)
    run = session(tmp_path, link, clock)
    with pytest.raises(ArmFault) as err:
        run.wait_for_arm()
    assert str(err.value).startswith(message), str(err.value)
    run.stop_safely()
    assert link.wire == []


def test_collect_starts_once_the_arm_side_matched_for_a_second(tmp_path):
    clock = Clock()
    link = FakeLink(clock, answer=answer_of(robot_config(), "guard", "sorolearn_guard"))
    run = session(tmp_path, link, clock)
    run.wait_for_arm()
    assert 101.0 <= clock() < 101.1 and run.guard_node == "sorolearn_guard"


# ---- control's deadlines and a step of the wall clock --------------------------------------------
class SteppedLink(FakeLink):
    """This computer's ROS (wall) clock steps by ``step_s`` once the monotonic clock passed ``at``
    (s after 100); the motion capture stamps its poses on its own clock."""

    def __init__(self, clock: Clock, at: float, step_s: float, **kwargs):
        self.at, self.step_ns = at, round(step_s * NS)
        super().__init__(clock, **kwargs)

    def now_ns(self) -> int:
        return super().now_ns() + (self.step_ns if self.clock() - 100.0 >= self.at else 0)


@pytest.mark.parametrize(("step_s", "reason"), [
    (-1.0, "ArmFault: clocks: a pose stamped 1.000 s after it was received: the motion capture's "
           "clock (its header stamps) runs ahead of this computer's ROS clock"),
    (0.2, None),  # under robot.max_pose_latency_s: the session goes on
    (2.0, "mocap watchdog: no pose on /mocap/pose for 2.00 s"),
])
def test_a_step_of_the_wall_clock_moves_no_control_deadline(tmp_path, monkeypatch, step_s,
                                                            reason):
    # the loop's deadlines run on the monotonic clock: whatever the wall clock does, one command
    # per period, none late or early; a step the clocks' checks see ends at the preload at once
    from pipeline.control import ros_arm
    from pipeline.control.goals import GoalSchedule
    from pipeline.control.loop import ControlLoop
    from pipeline.control.records import PeriodRecorder
    from pipeline.control.ros_arm import RosArm
    from tests.test_control_faults import SETTINGS, StepPolicy

    clock = Clock()
    link = SteppedLink(clock, at=3.3, step_s=step_s,
                       answer=answer_of(robot_config(), "guard", "sorolearn_guard"))
    cfg = robot_config()
    gate = CommandGate.for_robot(cfg)
    signals = SimpleNamespace(received=None)
    monkeypatch.setattr(ros_arm, "ArmLink", lambda node, executor, robot: link)
    monkeypatch.setattr(ros_arm, "Session", lambda *args: Session(*args, clock=clock))
    arm = RosArm(None, None, cfg, None, gate, signals)
    schedule = GoalSchedule(np.array([[0.03, 0.35, 0.2]]), np.array([0]), 10, "test")
    recorder = PeriodRecorder(tmp_path / "rec", 4, {}, {})
    outcome = ControlLoop(StepPolicy(), schedule, gate, arm, recorder, SETTINGS).run()
    assert outcome.missed_periods == 0 and outcome.holds == 0
    times = [t for t, _ in link.wire]
    gaps = np.diff(times[:-1])  # the final preload aside
    assert gaps.min() > 0.49 and gaps.max() < 0.51, gaps
    if reason is None:
        assert outcome.reason is None and len(link.wire) == 11
        return
    assert outcome.reason.startswith(reason), outcome.reason
    assert link.wire[-1][1] == PRELOAD
    # the first period after the step (at 3.3 s, the loop's first tick at about 2 s) at most
    assert times[-2] < 3.3 + 0.5 and times[-1] - 3.3 < 0.6, times
    assert 2 <= len(link.wire) - 1 < 10


# ---- the handshake's rules ---------------------------------------------------------------------
@pytest.mark.parametrize(("robot", "answer", "subscribers", "message"), [
    ({}, ("guard", {}), ["sorolearn_guard"], None),
    ({"rehearsal": True, "time_scale": 4.0}, ("twin", {"time_scale": 4.0}), ["sorolearn_guard"],
     None),
    ({}, ("guard", {"rating": {**RATING, "p_max": 9.0}}), ["sorolearn_guard"],
     "the guard 'sorolearn_guard' enforces another rating than robot.rating of this config "
     "(p_max: 9.0 there, 7.0 here)"),
    ({"rehearsal": True}, ("guard", {}), ["sorolearn_guard"],
     "robot.rehearsal=true / robot.time_scale=1.0, but the arm side is a guard"),
    ({"rehearsal": True}, ("twin", {"time_scale": 4.0}), ["sorolearn_guard"],
     "the twin 'sorolearn_guard' runs at time_scale 4.0, this stage at robot.time_scale=1.0"),
    # a real arm's config (no rehearsal, real time) answered by a twin: never recorded as the arm
    ({}, ("twin", {}), ["sorolearn_guard"],
     "robot.rehearsal=false (a real arm), but the arm side is the digital twin "
     "('sorolearn_guard'): its poses would be recorded as the real arm's. To rehearse, add "
     "robot.rehearsal=true"),
    ({}, ("twin", {"time_scale": 4.0}), ["sorolearn_guard"],
     "robot.rehearsal=false (a real arm), but the arm side is the digital twin"),
    # two twins on the rehearsal domain (one left running) both listen to the commands
    ({"rehearsal": True}, ("twin", {}), ["sorolearn_guard", "sorolearn_guard"],
     "2 subscriber(s) of /control_pressure: ['sorolearn_guard', 'sorolearn_guard']; only the "
     "twin 'sorolearn_guard' may listen (a twin or recorder left running on the rehearsal "
     "domain? stop it)"),
    ({}, ("guard", {"command_topic": "/other"}), ["sorolearn_guard"],
     "the guard 'sorolearn_guard' guards /other, but robot.command_topic=/control_pressure"),
    ({}, ("guard", {}), ["sorolearn_guard", "bag_replay"],
     "2 subscriber(s) of /control_pressure"),
    ({}, ("guard", {}), ["valve_driver"], "1 subscriber(s) of /control_pressure: "
                                          "['valve_driver']"),
])
def test_handshake_rules(robot, answer, subscribers, message):
    cfg = robot_config(**robot)
    role, changes = answer
    given = {**answer_of(robot_config(), role, "sorolearn_guard"), **changes}
    problem = handshake_problem(given, cfg, subscribers)
    if message is None:
        assert problem is None
    else:
        assert problem.startswith(message) or message in problem, problem


# ---- the guard on a fake node ------------------------------------------------------------------
class FakePublisher:
    def __init__(self):
        self.sent: list = []

    def publish(self, message) -> None:
        data = message.data
        self.sent.append(data if isinstance(data, str) else list(data))

    def wait_for_all_acked(self, _timeout) -> bool:
        return True


class FakeNode:
    def __init__(self):
        self.publishers: dict[str, FakePublisher] = {}
        self.callbacks: dict[str, object] = {}
        self.command_publishers = ["sorolearn_collect"]

    def get_name(self) -> str:
        return "sorolearn_guard"

    def create_publisher(self, _type, topic, _qos):
        self.publishers[topic] = FakePublisher()
        return self.publishers[topic]

    def create_subscription(self, _type, topic, callback, _qos):
        self.callbacks[topic] = callback

    def get_publishers_info_by_topic(self, topic):
        assert topic == "/control_pressure"
        return [SimpleNamespace(node_name=n) for n in self.command_publishers]


class FakeExecutor:
    def spin_once(self, timeout_sec: float = 0.0) -> None:
        pass


def command(pressures):
    from std_msgs.msg import Float64MultiArray

    message = Float64MultiArray()
    message.data = [float(p) for p in pressures]
    return message


@pytest.fixture
def guard():
    node = FakeNode()
    guard = GuardNode(node, FakeExecutor(), robot_config())
    return guard, node, node.publishers["/control_pressure/guarded"].sent


def test_deadman_by_hand():
    deadman = Deadman(1.5)
    assert deadman.stale(0.0)  # before the first command
    deadman.feed(10.0)
    assert not deadman.stale(11.5) and deadman.stale(11.51)
    deadman.feed(12.0)  # a command again: fresh
    assert not deadman.stale(12.1)
    with pytest.raises(ValueError, match="must be positive"):
        Deadman(0.0)


def test_the_guard_answers_with_its_rating(guard):
    import json

    _, node, _ = guard
    (answer,) = node.publishers["/sorolearn/arm_handshake"].sent
    assert json.loads(answer) == {"role": "guard", "node": "sorolearn_guard",
                                  "command_topic": "/control_pressure", "time_scale": 1.0,
                                  "rating": RATING}


@pytest.mark.parametrize(("pressures", "message"), [
    ([float("nan"), 2.0, 2.0], "refusing non-finite pressure command"),
    ([float("inf"), 2.0, 2.0], "refusing non-finite pressure command"),
    ([2.0, 2.0], "holds 2 values, expected 3 pressures"),
    ([-0.5, 2.0, 2.0], "refusing pressure command [-0.5, 2.0, 2.0] kPa outside the arm's rating"),
    ([6.0, 6.0, 2.0], "refusing pressure command [6.0, 6.0, 2.0] kPa outside the arm's rating"),
])
def test_the_guard_sends_the_preload_instead_of_a_bad_command(guard, caplog, pressures, message):
    node_, node, out = guard
    node.callbacks["/control_pressure"](command([3.0, 3.0, 3.0]))
    node.callbacks["/control_pressure"](command(pressures))
    assert out == [[3.0, 3.0, 3.0], PRELOAD]
    assert node_.refused == 1 and node_.forwarded == 1
    assert message in caplog.text


def test_the_guard_forwards_again_after_a_timeout_and_ends_at_the_preload(guard, monkeypatch):
    import pipeline.ros2.guard as module

    node_, node, out = guard
    now = [50.0]

    def monotonic() -> float:  # 1 ms per reading: the guard's waits end
        now[0] += 0.001
        return now[0]

    monkeypatch.setattr(module.time, "monotonic", monotonic)
    node.callbacks["/control_pressure"](command([3.0, 3.0, 3.0]))
    now[0] += 2.0  # past robot.command_timeout_s = 1.5 s
    assert node_.deadman.stale(now[0])
    node.callbacks["/control_pressure"](command([4.0, 3.0, 3.0]))
    assert not node_.deadman.stale(now[0]) and out == [[3.0, 3.0, 3.0], [4.0, 3.0, 3.0]]
    node_.finish()
    assert out[-1] == PRELOAD


def test_the_guard_refuses_a_second_publisher_and_holds_the_preload(guard, caplog):
    node_, node, out = guard
    node.callbacks["/control_pressure"](command([3.0, 3.0, 3.0]))
    node.command_publishers.append("rosbag2_player")
    node.callbacks["/control_pressure"](command([4.0, 3.0, 3.0]))
    node.command_publishers.pop()  # gone again: the refusal holds until a restart
    node.callbacks["/control_pressure"](command([5.0, 3.0, 3.0]))
    assert out == [[3.0, 3.0, 3.0], PRELOAD]
    assert node_.ignored == 2 and node_.forwarded == 1
    assert ("2 publishers on /control_pressure: rosbag2_player, sorolearn_collect; exactly one "
            "is accepted") in caplog.text


def test_live_goals_queue_without_growing():
    from pipeline.control.ros_arm import MAX_QUEUED_GOALS, RosArm

    arm = object.__new__(RosArm)  # only the goal queue
    arm._goals = []
    for i in range(10):
        arm._on_goal(SimpleNamespace(point=SimpleNamespace(x=float(i), y=0.0, z=0.0)))
    assert MAX_QUEUED_GOALS == 8
    assert [g[0] for g in arm.take_goals()] == [2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]
