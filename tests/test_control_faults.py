"""The control loop's faults on a scripted arm (no ROS, no policy network): stalls and clock steps
without catch-up, stale and NaN poses, a non-finite action, a stop that fails.

The arm's clock moves only when the loop waits (one mocap frame of 10 ms per wait) or when the
script makes it jump; the policy adds 0.5 kPa to valve 0 and takes 0.5 kPa from valve 2 each
period, so every command is known by hand.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.control.goals import GoalSchedule
from pipeline.control.loop import ControlFault, ControlLoop, LoopSettings
from pipeline.control.records import PeriodRecorder
from pipeline.ros2.gate import CommandGate
from pipeline.schemas import PressureLimits

PERIOD_S = 0.5
FRAME_S = 0.01
PRELOAD = [2.0, 2.0, 2.0]
LIMITS = PressureLimits(p_min=0.0, p_max=7.0, sum_max=13.0, preload=2.0)
SETTINGS = LoopSettings(control_hz=1 / PERIOD_S, watchdog_s=0.5, max_missed_periods=2,
                        max_pose_jump_mm=20.0, workspace_margin_mm=2.0, flush_every_s=1e6)
STEP = np.array([0.5, 0.0, -0.5])


class ScriptedArm:
    """Frames every 10 ms of its clock; ``jumps`` {at arm s: seconds} move the clock (a stall,
    or a step of the clock when negative) the first time it passes ``at``; ``stale_after_jump``
    delivers, after a jump, only frames stamped before it (the queue behind a stall)."""

    def __init__(self, jumps=None, nan_from: float | None = None, poses: bool = True,
                 stale_after_jump: bool = False, fail_stop: bool = False):
        self.t = 0.0
        self.jumps = dict(jumps or {})
        self.nan_from, self.poses = nan_from, poses
        self.stale_after_jump, self.fail_stop = stale_after_jump, fail_stop
        self.jumped_at: float | None = None
        self.frames: list = []
        self.published: list[tuple[float, list[float]]] = []  # (arm s, kPa)
        self.elapsed = 0.0  # true time: frames waited, whatever the clock says

    def start(self) -> None:
        self.advance(0.0)

    def now(self) -> float:
        return self.t

    def advance(self, until: float) -> None:
        for at, jump in list(self.jumps.items()):
            if self.t >= at:
                del self.jumps[at]
                self.jumped_at = self.t
                self.t += jump
                self.elapsed += max(jump, 0.0)
        stamp = self.t
        if self.stale_after_jump and self.jumped_at is not None:
            stamp = self.jumped_at - FRAME_S  # only old frames arrive
        position = np.array([0.03, 0.35, 0.2])
        if self.nan_from is not None and self.t >= self.nan_from:
            position = np.full(3, np.nan)
        if self.poses:
            self.frames.append((stamp, stamp, position))
        self.t += FRAME_S
        self.elapsed += FRAME_S

    def receive(self) -> None:
        pass

    def take_frames(self):
        frames, self.frames = self.frames, []
        return frames

    def take_goals(self):
        return []

    def publish(self, pressures) -> float:
        self.published.append((self.elapsed, np.asarray(pressures, float).tolist()))
        return self.t

    def stop_safely(self):
        if self.fail_stop:
            raise RuntimeError("the middleware is gone")
        self.publish(np.array(PRELOAD))
        return True


class StepPolicy:
    """``pressure = last + STEP``; NaN from period ``nan_at`` on."""

    hidden = None
    workspace_m = np.array([[0.0, 0.3, 0.1], [0.1, 0.4, 0.3]])
    preview = 0  # reference points ahead it observes

    def __init__(self, nan_at: int | None = None):
        self.nan_at, self.calls = nan_at, 0

    def act(self, hidden, first, position, goal, preview, last):
        assert preview.shape == (0, 3)
        action = np.ones(3) * (np.nan if self.nan_at is not None and self.calls >= self.nan_at
                               else 1.0)
        self.calls += 1
        return hidden, np.zeros(4), action, np.asarray(last) + STEP * action


def run(tmp_path, arm, periods: int = 10, policy=None):
    schedule = GoalSchedule(np.array([[0.03, 0.35, 0.2]]), np.array([0]), periods, "test")
    recorder = PeriodRecorder(tmp_path / "rec", 4, {}, {})
    gate = CommandGate(LIMITS, 3, LIMITS)
    loop = ControlLoop(policy or StepPolicy(), schedule, gate, arm, recorder, SETTINGS)
    return loop.run(), recorder


def commands(arm) -> list[float]:
    """Valve 0 of every command published, the final preload included."""
    return [p[0] for _, p in arm.published]


def one_per_period(arm) -> None:
    """Never two commands within one control period of true time (the final preload aside)."""
    windows = [int((t + FRAME_S / 2) // PERIOD_S) for t, _ in arm.published[:-1]]
    assert len(set(windows)) == len(windows), windows


def test_on_time_every_period_acts_once(tmp_path):
    arm = ScriptedArm()
    outcome, recorder = run(tmp_path, arm)
    assert outcome.reason is None and outcome.missed_periods == 0
    assert commands(arm) == [2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5, 6.0, 6.5, 7.0, 2.0]
    one_per_period(arm)
    assert set(recorder.read_all()["event"]) == {""}


def test_a_stall_of_one_period_holds_the_last_command_then_acts_on_a_fresh_pose(tmp_path):
    # after the command of period 3 (t = 1.5 s) the process stalls 1.2 s: it wakes at 2.8 s for
    # period 4's tick (2.0 s), 0.8 s late: period 4 gets no command, period 5 holds 4.0 kPa,
    # period 6 acts again on a pose stamped after the stall
    arm = ScriptedArm(jumps={1.6: 1.2})
    outcome, recorder = run(tmp_path, arm)
    assert outcome.reason is None
    assert outcome.missed_periods == 1 and outcome.holds == 1
    assert commands(arm) == [2.5, 3.0, 3.5, 4.0, 4.0, 4.5, 5.0, 5.5, 6.0, 2.0]
    one_per_period(arm)
    table = recorder.read_all()
    rows = table[table["goal_index"] >= 0].set_index("period")
    assert 4 not in rows.index
    assert rows.loc[5, "event"] == "late" and rows.loc[5, "missed_periods"] == 1
    assert rows.loc[5, "p_cmd_0"] == 4.0 and np.isnan(rows.loc[5, "action_0"])
    assert rows.loc[6, "event"] == "" and rows.loc[6, "pose_t"] > 2.8


def test_a_forward_clock_step_of_three_periods_goes_to_the_preload_with_a_clear_error(tmp_path):
    arm = ScriptedArm(jumps={1.6: 2.0})  # wakes 1.6 s after period 4's tick: 3 periods missed
    outcome, _ = run(tmp_path, arm)
    assert isinstance(outcome.error, ControlFault)
    assert ("the control loop woke 1.61 s after the tick of period 4: 3 periods missed in a row, "
            "more than robot.max_missed_periods=2") in outcome.reason
    assert commands(arm) == [2.5, 3.0, 3.5, 4.0, 2.0]  # nothing between the stall and the preload


def test_a_backward_clock_step_waits_for_the_tick_again_without_a_burst(tmp_path):
    arm = ScriptedArm(jumps={1.6: -1.0})
    outcome, _ = run(tmp_path, arm)
    assert outcome.reason is None and outcome.missed_periods == 0
    assert commands(arm)[:-1] == [2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5, 6.0, 6.5, 7.0]
    one_per_period(arm)


def test_queued_stale_poses_do_not_satisfy_the_watchdog(tmp_path):
    # after a stall of 0.7 s only poses stamped before it arrive: the loop holds, then the
    # watchdog (their stamps, not their arrival) stops it; the policy never acts on them
    arm = ScriptedArm(jumps={1.6: 0.7}, stale_after_jump=True)
    policy = StepPolicy()
    outcome, _ = run(tmp_path, arm, policy=policy)
    assert "mocap watchdog: the latest pose is" in outcome.reason
    assert policy.calls == 4
    assert commands(arm)[-1] == 2.0 and max(commands(arm)) == 4.0


def test_lost_markers_are_skipped_until_the_watchdog_stops(tmp_path):
    arm = ScriptedArm(nan_from=1.2)
    policy = StepPolicy()
    outcome, _ = run(tmp_path, arm, policy=policy)
    assert "mocap watchdog: the latest pose is" in outcome.reason
    # periods 0-3 act (at 1.5 s the last pose, 1.19 s, is 0.31 s old); at 2.0 s it is 0.81 s old
    assert policy.calls == 4
    assert "the latest pose is 0.81 s old" in outcome.reason
    assert commands(arm)[-1] == 2.0


def test_no_pose_before_the_first_command_commands_only_the_preload(tmp_path):
    arm = ScriptedArm(poses=False)
    outcome, recorder = run(tmp_path, arm)
    assert outcome.reason == "no pose received before the first command"
    assert arm.published == [(arm.published[0][0], PRELOAD)]
    assert recorder.read_all().empty


def test_a_non_finite_action_after_the_first_period_stops_at_the_preload(tmp_path):
    arm = ScriptedArm()
    outcome, recorder = run(tmp_path, arm, policy=StepPolicy(nan_at=2))
    assert isinstance(outcome.error, ControlFault)
    assert outcome.reason.startswith("ControlFault: non-finite policy output at period 2")
    assert commands(arm) == [2.5, 3.0, 2.0]
    assert len(recorder.read_all()) == 2


def test_a_failing_stop_still_flushes_the_records(tmp_path):
    arm = ScriptedArm(fail_stop=True)
    schedule = GoalSchedule(np.array([[0.03, 0.35, 0.2]]), np.array([0]), 4, "test")
    recorder = PeriodRecorder(tmp_path / "rec", 4, {}, {})
    loop = ControlLoop(StepPolicy(), schedule, CommandGate(LIMITS, 3, LIMITS), arm, recorder,
                       SETTINGS)
    with pytest.raises(RuntimeError, match="the middleware is gone"):
        loop.run()
    # the periods and every pose frame taken, each in its first chunk
    assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == ["frames-00000.parquet",
                                                                     "periods-00000.parquet"]
    assert len(recorder.read_all()) == 5  # 4 periods and the final pose
    assert len(recorder.read_frames()) >= 5


def test_the_float64_check_refuses_inside_the_publish_path(tmp_path, monkeypatch):
    # a projection that lets an unsafe command through (a bug upstream): the float64 check right
    # before publishing stops it, the preload goes out, nothing unsafe is published
    arm = ScriptedArm()
    gate = CommandGate(LIMITS, 3, LIMITS)
    monkeypatch.setattr(gate, "project", lambda p: np.asarray(p, np.float64) + np.array([3.0, 0, 0]))
    schedule = GoalSchedule(np.array([[0.03, 0.35, 0.2]]), np.array([0]), 10, "test")
    recorder = PeriodRecorder(tmp_path / "rec", 4, {}, {})
    outcome = ControlLoop(StepPolicy(), schedule, gate, arm, recorder, SETTINGS).run()
    # 2 + 0.5 + 3 = 5.5 kPa goes out; then 5.5 + 0.5 + 3 = 9 kPa is refused, the preload follows
    assert ("UnsafeCommandError: refusing pressure command [9.0, 2.0, 1.0] kPa outside the arm's "
            "rating") in outcome.reason
    assert commands(arm) == [5.5, 2.0]
