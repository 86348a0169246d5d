"""stage=control following a reference (control.trajectory): the schedule each period gets, the
refusals before anything moves, and a session on the in-process simulated arm."""

from __future__ import annotations

import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from pipeline.arm.references import InvalidReference
from pipeline.arm.safety import SafeSet
from pipeline.control.goals import GoalSchedule
from pipeline.control.records import GOAL_COLUMNS, REFERENCE_COLUMNS
from pipeline.control.trajectory import (
    live_trajectory,
    trajectory_metrics,
    trajectory_of,
    trajectory_schedule,
)
from pipeline.data.schemas import CMD_COLUMNS
from pipeline.infra.artifacts import ArtifactStore
from pipeline.keys import key
from pipeline.schemas import ConfigError
from pipeline.stages.control import control
from tests.conftest import compose_config
from tests.control_fixtures import SMALL, write_policy

CENTRE_MM = np.array([30.0, 353.0, 200.0])
TRACKING = ["env.task=track", "env.preview=3"]


def circle_mm(t, centre=CENTRE_MM, radius=4.0, period=8.0) -> np.ndarray:
    """``[len(t), 3]`` mm: a circle in xz, counter-clockwise from +x (ReferenceConfig's)."""
    angle = 2 * np.pi * np.asarray(t, np.float64) / period
    return centre + radius * np.stack([np.cos(angle), np.zeros_like(angle), np.sin(angle)], -1)


def ring_m(centre=CENTRE_MM, radius=4.0) -> np.ndarray:
    """Reachable positions: a dense ring of ``radius`` mm around ``centre``, in m."""
    return circle_mm(np.linspace(0, 8, 400, endpoint=False), centre, radius) / 1e3


SHAPE = {"kind": "circle", "centre_mm": CENTRE_MM.tolist(), "size_mm": 4.0, "period_s": 8.0}


# ---- what each period gets -----------------------------------------------------------------------
def test_each_period_gets_the_reference_at_its_end_and_the_next_points_as_preview():
    trajectory = trajectory_of(SHAPE, {}, np.zeros(3))
    schedule = trajectory_schedule(trajectory, 3.0, 1.0, 2.0, 2, ring_m(), 0.5)
    assert schedule.end == 6 and schedule.settle_s == 1.0
    # period 0 (tick 0 s) is sent toward the reference at 0.5 s: an eighth of a lap of 8 s / 2
    index, goal = schedule.goal(0)
    assert index == 0
    np.testing.assert_allclose(goal * 1e3, [30 + 4 * np.cos(np.pi / 8), 353,
                                            200 + 4 * np.sin(np.pi / 8)], atol=1e-4)
    assert schedule.goal(5)[0] == 0
    np.testing.assert_allclose(schedule.goal(5)[1] * 1e3, [30 + 4 * np.cos(3 * np.pi / 4), 353,
                                                           200 + 4 * np.sin(3 * np.pi / 4)],
                               atol=1e-4)
    # period 1's preview: the reference at 1.5 s and 2 s (a quarter lap: straight above)
    np.testing.assert_allclose(schedule.preview(1, 2) * 1e3,
                               [[30 + 4 * np.cos(3 * np.pi / 8), 353, 200 + 4 * np.sin(3 * np.pi / 8)],
                                [30, 353, 204]], atol=1e-4)
    # the pose of tick k is scored against the reference at k / 2 s; 7 ticks for 6 periods
    np.testing.assert_allclose(schedule.reference(0) * 1e3, [34, 353, 200], atol=1e-4)
    np.testing.assert_allclose(schedule.reference(2) * 1e3,
                               [30 + 2 * np.sqrt(2), 353, 200 + 2 * np.sqrt(2)], atol=1e-4)
    np.testing.assert_allclose(schedule.ticks_m * 1e3, circle_mm(np.arange(7) / 2), atol=1e-4)
    with pytest.raises(ValueError, match="previews 2 points, asked for 3"):
        schedule.preview(0, 3)


def test_a_reaching_policy_gets_no_preview_and_goals_preview_the_goals_ahead():
    schedule = trajectory_schedule(trajectory_of(SHAPE, {}, np.zeros(3)), 2.0, 0.0, 2.0, 0,
                                   ring_m(), 0.5)
    assert schedule.preview(3, 0).shape == (0, 3)
    goals = GoalSchedule(np.array([[1.0, 2, 3], [4.0, 5, 6]]), np.array([0, 2]), 4, "test")
    np.testing.assert_array_equal(goals.preview(0, 3), [[1, 2, 3], [4, 5, 6], [4, 5, 6]])
    np.testing.assert_array_equal(goals.preview(3, 2), [[4, 5, 6], [4, 5, 6]])
    assert goals.reference(0) is None


def test_a_named_reference_is_centred_on_the_held_out_goals_median():
    named = {"circle": {"kind": "circle"}, "slow": {"kind": "figure_eight", "period_s": 40}}
    trajectory = trajectory_of("slow", named, CENTRE_MM)
    assert trajectory.duration_s is None
    assert "slow: a figure_eight of 5 mm in xz, 40 s a lap, around [30.0, 353.0, 200.0]" in (
        trajectory.source)
    ticks = trajectory_schedule(trajectory, 10.0, 0.0, 2.0, 0, ring_m(radius=5.0), 5.0).ticks_m
    # a 1:2 Lissajous: x = 5 cos(wt), z = 5 sin(2 wt); at 10 s of 40 s: x = 0, z = 0
    np.testing.assert_allclose(ticks[0] * 1e3, [35, 353, 200], atol=1e-4)
    np.testing.assert_allclose(ticks[-1] * 1e3, [30, 353, 200], atol=1e-4)


def test_a_replayed_recording_is_followed_from_its_start_and_slowed():
    # two recordings the policy's goals came from, x = 30 + t mm (and 40 + t), 10 Hz
    times = np.arange(61) / 10.0
    walk = CENTRE_MM / 1e3 + np.outer(times, [0.001, 0.0, 0.0])
    recorded = {"a": (times, walk + np.array([0.010, 0, 0])), "b": (times, walk)}
    named = {"walk": {"kind": "replay", "run": "b", "slow_down": 2, "start_s": 1}}
    trajectory = trajectory_of("walk", named, CENTRE_MM, recorded)
    assert trajectory.source == "walk: the measured path of b from 1 s, 2 times slower"
    assert trajectory.duration_s == pytest.approx(10.0)  # the 5 s after 1 s, twice as slow
    ticks = trajectory_schedule(trajectory, 4.0, 0.0, 2.0, 1, ring_m(CENTRE_MM, 1.0), 10.0).ticks_m
    np.testing.assert_allclose(ticks[[0, 1, 8]] * 1e3, [[31, 353, 200], [31.25, 353, 200],
                                                        [33, 353, 200]], atol=1e-4)
    first = trajectory_of({"kind": "replay"}, {}, CENTRE_MM, recorded)  # the first recording
    assert "the measured path of a from 0 s, 4 times slower" in first.source
    with pytest.raises(InvalidReference, match=r"^walk: a replayed path needs the recordings"):
        trajectory_of("walk", named, CENTRE_MM, {})


# ---- refusals: one line, before anything moves ---------------------------------------------------
def write_csv(path, rows) -> str:
    pd.DataFrame(rows, columns=["t", "x", "y", "z"]).to_csv(path, index=False)
    return str(path)


@pytest.mark.parametrize("rows, words", [
    ([[0, 30, 353, 200], [1, 31, 353, 200], [1, 32, 353, 200]],
     r"times must increase; row 2 has t=1 s after t=1 s"),
    ([[0, 30, 353, 200], [1, np.nan, 353, 200]], r"row 1 is not finite"),
    ([[0, 0.030, 0.353, 0.200], [1, 0.031, 0.353, 0.2]], r"x, y, z look like metres"),
])
def test_a_bad_csv_is_refused_in_one_line(tmp_path, rows, words):
    path = write_csv(tmp_path / "path.csv", rows)
    with pytest.raises(InvalidReference, match=words) as err:
        trajectory_of(path, {}, CENTRE_MM)
    assert str(tmp_path / "path.csv") in str(err.value) and "\n" not in str(err.value)


def test_a_csv_is_followed_to_its_last_time_and_held_there(tmp_path):
    path = write_csv(tmp_path / "path.csv", [[0, 30, 353, 200], [2, 32, 353, 200],
                                             [3, 32, 353, 201]])
    trajectory = trajectory_of(path, {}, CENTRE_MM)
    assert trajectory.duration_s == 3.0
    schedule = trajectory_schedule(trajectory, 4.0, 0.0, 2.0, 1, ring_m(CENTRE_MM, 1.0), 3.0)
    np.testing.assert_allclose(schedule.ticks_m[[0, 1, 4, 6, 8]] * 1e3,
                               [[30, 353, 200], [30.5, 353, 200], [32, 353, 200],
                                [32, 353, 201], [32, 353, 201]], atol=1e-4)
    np.testing.assert_allclose(schedule.preview(4, 1) * 1e3, [[32, 353, 201]], atol=1e-4)


@pytest.mark.parametrize("given, words", [
    ("square", r"control.trajectory='square': expected a name of evaluation.references "
               r"\['circle'\]"),
    ({"shape": "circle"}, r"control.trajectory: unknown setting\(s\) \['shape'\]"),
    ({"kind": "circle", "size_mm": -1}, r"reference size_mm=-1"),
    ("missing.csv", r"control.trajectory=missing.csv: no such CSV file"),
])
def test_bad_trajectory_settings_are_refused_by_name(given, words):
    with pytest.raises(ConfigError, match=words) as err:
        trajectory_of(given, {"circle": {"kind": "circle"}}, CENTRE_MM)
    assert "\n" not in str(err.value)


def test_a_reference_leaving_the_reachable_set_names_its_first_point_and_the_extent():
    trajectory = trajectory_of({**SHAPE, "size_mm": 6.0}, {}, CENTRE_MM)
    with pytest.raises(InvalidReference) as err:
        trajectory_schedule(trajectory, 8.0, 2.0, 2.0, 3, ring_m(), 1.0)
    message = str(err.value)
    # the 6 mm circle starts 2 mm outside the 4 mm ring, at t = 0
    assert message.startswith("control.trajectory (control.trajectory: a circle of 6 mm")
    assert "refused: its point at t=0 s, [36.0, 353.0, 200.0] mm, lies 2.0 mm from the nearest " \
           "reachable position (tolerance 1 mm)" in message
    assert "spans x [26.0, 34.0], y [353.0, 353.0], z [196.0, 204.0] mm" in message
    assert "\n" not in message
    with pytest.raises(InvalidReference, match=r"control.settle_s=8.0: expected >= 0 s and "
                                               r"shorter than the 8 s"):
        trajectory_schedule(trajectory_of(SHAPE, {}, CENTRE_MM), 8.0, 8.0, 2.0, 3, ring_m(), 1.0)


# ---- a session on the in-process simulated arm ------------------------------------------------------
def tracking_policy(tmp_path, policy="ppo_rnn", task=tuple(TRACKING)):
    """A config of a random-network policy (env=sim; tracking with a preview of 3 unless ``task``
    says otherwise), its training goals [G, 3] m and its error scale (m)."""
    cfg = compose_config(tmp_path, *SMALL, *task, f"control.policy={policy}", "stage=control")
    _, train_params = write_policy(cfg)
    return (cfg, np.asarray(train_params.goal_set, np.float64),
            float(train_params.error_scale_m))


def test_the_simulated_arm_follows_a_circle_with_the_training_preview(tmp_path):
    cfg, goals, error_scale = tracking_policy(tmp_path)
    centre = np.round(np.median(goals, axis=0) * 1e3, 1)
    cfg.control.trajectory = {"kind": "circle", "centre_mm": centre.tolist(), "size_mm": 2.0,
                              "period_s": 8.0}
    cfg.control.duration_s, cfg.control.settle_s = 6.0, 2.0
    cfg.control.workspace_margin_mm = 10.0
    artifact = control(cfg)
    periods = pd.read_parquet(artifact.file("periods.parquet"))
    commanded = periods[periods["goal_index"] >= 0]
    assert len(commanded) == 12 and (commanded["goal_index"] == 0).all()
    assert periods["goal_index"].iloc[-1] == -1 and periods["period"].iloc[-1] == 12
    # the reference at each tick, the goal at each period's end, by hand
    reference = circle_mm(periods["period"] / 2.0, centre, 2.0)
    np.testing.assert_allclose(periods[REFERENCE_COLUMNS].to_numpy() * 1e3, reference, atol=1e-3)
    np.testing.assert_allclose(commanded[GOAL_COLUMNS].to_numpy() * 1e3,
                               circle_mm((commanded["period"] + 1) / 2.0, centre, 2.0),
                               atol=1e-3)
    # the observation ends with the preview, (reference at (k + 1 + j) / 2 s - measured) / scale
    obs = commanded.filter(like="obs_").to_numpy()
    assert obs.shape[1] == 21
    measured = commanded[["x", "y", "z"]].to_numpy()
    for j in range(1, 4):
        ahead = circle_mm((commanded["period"] + 1 + j) / 2.0, centre, 2.0) / 1e3
        np.testing.assert_allclose(obs[:, 9 + 3 * j:12 + 3 * j] * error_scale, ahead - measured,
                                   atol=2e-6)
    commands = commanded[CMD_COLUMNS].to_numpy()
    assert np.isfinite(commands).all() and commands.min() >= 0 and commands.max() <= 7.0
    assert commands.sum(axis=1).max() <= 13.0
    # the metrics: the error at ticks 4 .. 12 (after 2 s), by hand
    error = np.linalg.norm(periods[["x", "y", "z"]].to_numpy() * 1e3 - reference, axis=1)[4:]
    metrics = pd.read_parquet(artifact.file("tracking.parquet"))
    assert len(metrics) == 1 and metrics["periods"][0] == 12 and metrics["interpolated"][0] == 0
    assert metrics["rmse_mm"][0] == pytest.approx(np.sqrt(np.mean(error ** 2)), rel=1e-4)
    assert metrics["max_mm"][0] == pytest.approx(error.max(), rel=1e-4)
    summary = artifact.manifest["summary"]
    assert summary["rmse_mm"] == pytest.approx(metrics["rmse_mm"][0], abs=1e-4)
    assert "a circle of 2 mm" in summary["trajectory"]
    report = artifact.file("report.md").read_text()
    assert "## Tracking" in report and "RMSE" in report and "observing 3 reference points ahead" in report
    for figure in ("path_xz.png", "error.png", "pressures.png"):
        assert artifact.file(f"figures/{figure}").stat().st_size > 5_000
    assert not artifact.file("goals.parquet").exists()


def test_the_simulated_arm_follows_a_replayed_csv_and_its_key_holds_the_content(tmp_path):
    cfg, goals, _ = tracking_policy(tmp_path)
    centre = np.round(np.median(goals, axis=0) * 1e3, 1)
    rows = [[t, centre[0] + t, centre[1], centre[2]] for t in (0.0, 1.0, 2.0)]
    csv = write_csv(tmp_path / "walk.csv", rows)
    cfg.control.trajectory = {"kind": "replay", "file": csv, "slow_down": 2.0}
    cfg.control.duration_s, cfg.control.settle_s = 3.0, 0.0
    cfg.control.workspace_margin_mm = 10.0
    before = key("control", cfg)
    artifact = control(cfg)
    periods = pd.read_parquet(artifact.file("periods.parquet"))
    assert len(periods) == 7  # 6 periods and the last pose
    # the path at half speed: x = centre + t / 2 mm at tick t = k / 2 s
    expected = centre + np.outer(periods["period"] / 4.0, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(periods[REFERENCE_COLUMNS].to_numpy() * 1e3, expected, atol=1e-3)
    assert "the measured path of" in artifact.manifest["summary"]["trajectory"]
    write_csv(tmp_path / "walk.csv", [[t, x + 0.5, y, z] for t, x, y, z in rows])
    assert key("control", cfg) != before  # the file's content, not its name


def test_an_interrupted_session_keeps_its_artifact_and_ends_at_the_preload(tmp_path,
                                                                           monkeypatch):
    from pipeline.control import session
    from pipeline.control.loop import SimArm, Stop
    from pipeline.control.session import ControlInterrupted

    sent = []

    class Interrupted(SimArm):
        def advance(self, until):
            if self.now() >= 1.2:
                raise Stop("SIGINT received")
            super().advance(until)

        def publish(self, pressures):
            sent.append(np.asarray(pressures))
            return super().publish(pressures)

    monkeypatch.setattr(session, "SimArm", Interrupted)
    cfg, _, _ = tracking_policy(tmp_path)
    cfg.control.trajectory = {"kind": "circle", "size_mm": 2.0, "period_s": 8.0}
    cfg.control.duration_s, cfg.control.settle_s = 6.0, 2.0
    cfg.control.workspace_margin_mm = 10.0
    with pytest.raises(ControlInterrupted, match="SIGINT received"):
        control(cfg)
    np.testing.assert_allclose(sent[-1], [2.0, 2.0, 2.0])  # the preload, last
    artifact = ArtifactStore(cfg.paths.artifact_dir).require("control", key("control", cfg))
    assert artifact.manifest["summary"]["interrupted"] == "SIGINT received"
    assert artifact.manifest["summary"]["rmse_mm"] is None  # stopped before the settle time
    periods = pd.read_parquet(artifact.file("periods.parquet"))
    assert list(periods["period"]) == [0, 1, 2]
    assert np.isfinite(periods[REFERENCE_COLUMNS].to_numpy()).all()


def test_missing_periods_are_interpolated_for_the_metrics():
    rows = pd.DataFrame({"period": [0, 1, 3, 4], "goal_index": [0, 0, 0, -1],
                         "x": [0.0, 0.001, 0.003, 0.004], "y": 0.0, "z": 0.0,
                         "ref_x": [0.0, 0.001, 0.003, 0.004], "ref_y": 0.001, "ref_z": 0.0})
    metrics = trajectory_metrics(rows, 2.0, 0.0)
    # period 2 missed (a stall): interpolated; 1 mm off along y at every tick
    assert metrics["interpolated"][0] == 1 and metrics["periods"][0] == 4
    assert metrics["rmse_mm"][0] == pytest.approx(1.0)
    assert metrics["within_1mm"][0] == pytest.approx(1.0)
    # a session interrupted before the settle time: nothing to score, the row is kept
    short = trajectory_metrics(rows, 2.0, 3.0)
    assert np.isnan(short["rmse_mm"][0]) and short["periods"][0] == 4
    # the commands sent: periods 0, 1 and 3 (none at the last tick); period 2's is the one held
    sent = rows.copy()
    sent[CMD_COLUMNS] = [[2.0, 2.0, 2.0], [7.0, 2.0, 2.0], [2.0, 2.0, 2.0], [np.nan] * 3]
    safe = SafeSet.from_limits(SimpleNamespace(p_min=0.0, p_max=7.0, sum_max=13.0, preload=2.0))
    limited = trajectory_metrics(sent, 2.0, 0.0, safe)
    # periods 0 .. 3: 2 kPa, 7 kPa on valve 0, held (7 kPa), 2 kPa: half on a limit
    assert limited["at_limits"][0] == pytest.approx(0.5)
    assert limited["rmse_mm"][0] == pytest.approx(1.0) and np.isnan(metrics["at_limits"][0])


def test_a_reaching_policy_follows_the_moving_goal_and_trajectories_go_alone(tmp_path):
    cfg, goals, _ = tracking_policy(tmp_path, "ppo_ff", task=())
    centre = np.round(np.median(goals, axis=0) * 1e3, 1)
    cfg.control.trajectory = {"kind": "circle", "centre_mm": centre.tolist(), "size_mm": 2.0,
                              "period_s": 8.0}
    cfg.control.duration_s, cfg.control.settle_s = 2.0, 0.0
    cfg.control.workspace_margin_mm = 10.0
    periods = pd.read_parquet(control(cfg).file("periods.parquet"))
    commanded = periods[periods["goal_index"] >= 0]
    assert commanded.filter(like="obs_").shape[1] == 12  # no preview
    np.testing.assert_allclose(commanded[GOAL_COLUMNS].to_numpy() * 1e3,
                               circle_mm((commanded["period"] + 1) / 2.0, centre, 2.0),
                               atol=1e-3)
    cfg.control.goals = [centre.tolist()]
    with pytest.raises(ConfigError, match=r"is followed on its own; leave out control.goals"):
        control(cfg)


@pytest.mark.slow  # a pipeline process of its own: its start and the policy's compile
def test_the_entry_point_refuses_a_far_reference_in_one_line_and_nothing_moves(tmp_path):
    out = tmp_path / "outputs"
    cfg, _, _ = tracking_policy(out)
    far = "control.trajectory={kind:circle,size_mm:40,period_s:20}"
    run = subprocess.run(
        [sys.executable, "-m", "pipeline", "stage=control", f"paths.output_dir={out}", *SMALL,
         *TRACKING, "control.policy=ppo_rnn", far],
        capture_output=True, text=True, timeout=300)
    assert run.returncode == 1, run.stderr
    errors = [line for line in (run.stdout + run.stderr).splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "Traceback" not in run.stderr, run.stderr
    assert "InvalidReference: control.trajectory (control.trajectory: a circle of 40 mm" in (
        errors[0])
    assert "mm from the nearest reachable position" in errors[0]
    store = ArtifactStore(cfg.paths.artifact_dir)
    cfg.control.trajectory = {"kind": "circle", "size_mm": 40, "period_s": 20}
    assert store.find("control", key("control", cfg)) is None
    assert not (out / "recovery").exists()


def test_the_session_key_holds_the_reference_not_its_name(tmp_path):
    from pipeline.keys import control_spec

    cfg = compose_config(tmp_path, *SMALL, *TRACKING, "stage=control", "control.goals=[[30,353,200]]")
    spec = control_spec(cfg)[0]["control"]
    assert "trajectory" not in spec and "settle_s" not in spec  # goals: the key as before
    cfg = compose_config(tmp_path, *SMALL, *TRACKING, "stage=control", "control.trajectory=circle")
    spec = control_spec(cfg)[0]["control"]["trajectory"]
    assert spec["reference"] == {"name": "circle", "kind": "circle"}
    assert spec["tracking_seconds"] == 30.0 and spec["tracking_settle_seconds"] == 10.0
    wider = compose_config(tmp_path, *SMALL, *TRACKING, "stage=control",
                           "control.trajectory=circle", "+evaluation.references.circle.size_mm=3")
    assert key("control", wider) != key("control", cfg)
    csv = write_csv(tmp_path / "path.csv", [[0, 30, 353, 200], [1, 31, 353, 200]])
    by_file = compose_config(tmp_path, *SMALL, *TRACKING, "stage=control",
                             f"control.trajectory={csv}")
    first = key("control", by_file)
    write_csv(tmp_path / "path.csv", [[0, 30, 353, 200], [1, 32, 353, 200]])
    assert key("control", by_file) != first  # the file's content, not its name


def followed_circle(tmp_path, *settings):
    """A 3 s session of a random tracking policy trained with ``settings`` on a 2 mm circle:
    ``(observations [K, obs_dim], goals [K, 3] m, poses [K, 3] m, error scale m)`` of its K
    commanded periods."""
    cfg, _, error_scale = tracking_policy(tmp_path, task=(*TRACKING, *settings))
    cfg.control.trajectory = {"kind": "circle", "size_mm": 2.0, "period_s": 8.0}
    cfg.control.duration_s, cfg.control.settle_s = 3.0, 0.0
    cfg.control.workspace_margin_mm = 10.0
    periods = pd.read_parquet(control(cfg).file("periods.parquet"))
    commanded = periods[periods["goal_index"] >= 0]
    return (commanded.filter(like="obs_").to_numpy(), commanded[GOAL_COLUMNS].to_numpy(),
            commanded[["x", "y", "z"]].to_numpy(), error_scale)


def test_the_accumulated_error_takes_the_goal_of_the_period_that_led_to_the_pose(tmp_path):
    # as the environment's step: integral_k = 0.5 integral_(k-1) + 0.5 (goal_(k-1) - pose_k) / scale
    obs, goals, poses, error_scale = followed_circle(
        tmp_path, "env.include_error_integral=true", "env.error_integral_decay=0.5")
    integral = obs[:, 9:12]
    expected = [np.zeros(3)]
    for k in range(1, len(goals)):
        expected.append(0.5 * expected[-1] + 0.5 * (goals[k - 1] - poses[k]) / error_scale)
    np.testing.assert_allclose(integral, np.array(expected), rtol=1e-4, atol=1e-4)
    # the current goal would differ: the reference moves 0.8 mm a period
    assert np.abs(goals[1:] - goals[:-1]).max() > 5e-4


def test_the_arm_moves_the_observed_reference_as_the_environment_does(tmp_path):
    # shift_k = shift_(k-1) + 0.5 (goal_(k-1) - pose_k), at most 50 mm; the policy observes the
    # goal and the preview moved by it
    obs, goals, poses, error_scale = followed_circle(
        tmp_path, "env.reference_integral_gain=0.5", "env.reference_shift_max_mm=50")
    expected = [np.zeros(3)]
    for k in range(1, len(goals)):
        expected.append(expected[-1] + 0.5 * (goals[k - 1] - poses[k]))
    shift = obs[:, 6:9] * error_scale - (goals - poses)  # the observed error, less the true one
    np.testing.assert_allclose(shift, np.array(expected), atol=2e-6)
    assert np.abs(shift).max() > 1e-4  # it moved
    # the first preview point, moved alike: the next period's goal
    ahead = obs[:, 12:15] * error_scale + poses
    np.testing.assert_allclose(ahead[:-1] - shift[:-1], goals[1:], atol=2e-6)


# ---- a reference that arrives while it is followed (control.trajectory_topic) --------------------
def test_a_live_reference_runs_in_straight_segments_between_its_points():
    """Points due at 1 s (A) and 3 s (B), 2 Hz: period k's goal is the reference at (k + 1) / 2 s,
    A until 1 s, then a quarter of the way to B every half second, B from 3 s on; its preview
    the reference 1, 2 periods later; its tick k / 2 s is scored against the reference then."""
    a, b = np.array([0.03, 0.353, 0.2]), np.array([0.034, 0.353, 0.196])
    schedule = live_trajectory("/reference", 10.0, 2.0, 2.0)
    assert schedule.goal(0) is None and schedule.reference(0) is None  # nothing yet: the preload
    assert schedule.add_point(1.0, a, now_s=0.0) is None
    assert schedule.add_point(3.0, b, now_s=0.0) is None
    np.testing.assert_allclose(schedule.goal(0)[1], a)
    np.testing.assert_allclose(schedule.goal(2)[1], a + 0.25 * (b - a))
    np.testing.assert_allclose(schedule.preview(2, 2), [a + 0.5 * (b - a), a + 0.75 * (b - a)])
    np.testing.assert_allclose(schedule.reference(4), a + 0.5 * (b - a))
    np.testing.assert_allclose(schedule.goal(9)[1], b)
    # a point already past is due now; one due before the last point taken is refused
    c = np.array([0.032, 0.353, 0.2])
    assert schedule.add_point(0.5, c, now_s=4.0) is None
    np.testing.assert_allclose(schedule.goal(7)[1], c)  # the reference at 4 s
    problem = schedule.add_point(3.5, c, now_s=3.5)
    assert "a point due at t=3.500 s arrived after one due at t=4.000 s" in problem
    assert len(schedule.times_s) == 3
    with pytest.raises(InvalidReference, match=r"control.settle_s=12.0: expected >= 0 s"):
        live_trajectory("/reference", 10.0, 12.0, 2.0)


def test_the_arm_follows_live_points_and_refuses_bad_ones(tmp_path):
    """On the simulated arm with a publisher in the loop: nothing before the first point (the
    preload), then each period's goal along the segments; a point outside the workspace and one
    out of order are refused and the session goes on; the metrics score from the first point."""
    from omegaconf import OmegaConf

    from pipeline.control.loop import ControlLoop, LoopSettings, SimArm
    from pipeline.control.records import PeriodRecorder
    from pipeline.ros2.gate import CommandGate
    from pipeline.stages.control import load_deployment, session_schedule

    cfg, goals, _ = tracking_policy(tmp_path, "ppo_ff", task=())
    cfg.control.trajectory_topic, cfg.control.duration_s, cfg.control.settle_s = "/ref", 4.0, 0.5
    deployment = load_deployment(cfg, ArtifactStore(cfg.paths.artifact_dir))
    assert float(deployment.env_params.deadband_m) == 0.0
    schedule = session_schedule(cfg, OmegaConf.to_object(cfg.control), deployment)
    a, b = goals[0], goals[1]
    published = [(1.0, 0.5, a), (1.0, 3.0, b), (1.5, 3.0, np.array([0.5, 0.35, 0.2])),
                 (1.5, 2.0, a)]  # (arm s it is published, s it is due, point)

    class Publisher:
        def __init__(self, arm):
            self.arm, self.sent = arm, 0

        def __getattr__(self, name):
            return getattr(self.arm, name)

        def take_points(self):
            due = [(t, p) for at, t, p in published[self.sent:] if at <= self.arm.now()]
            self.sent += len(due)
            return due

    robot = OmegaConf.to_object(cfg.robot)
    gate = CommandGate(robot.limits, 3)
    arm = Publisher(SimArm(robot, 0, gate))
    recorder = PeriodRecorder(tmp_path / "chunks", deployment.env.obs_dim, {}, {})
    settings = LoopSettings.of(robot, OmegaConf.to_object(cfg.control))
    outcome = ControlLoop(deployment, schedule, gate, arm, recorder, settings).run()
    assert outcome.reason is None and outcome.periods == 8, outcome
    rows = recorder.read_all()
    commanded = rows[rows["goal_index"] >= 0]
    assert commanded["period"].tolist() == [2, 3, 4, 5, 6, 7]  # points from 1 s (period 2)
    # the segment from 1 s (a, published then, due at once) to 3 s (b), at each period's end
    ramp = {2: a + 0.25 * (b - a), 3: a + 0.5 * (b - a), 4: a + 0.75 * (b - a), 5: b, 6: b,
            7: b}
    np.testing.assert_allclose(commanded[GOAL_COLUMNS].to_numpy(),
                               [ramp[k] for k in commanded["period"]], atol=1e-9)
    np.testing.assert_allclose(commanded[REFERENCE_COLUMNS].to_numpy()[0], a)  # tick 1 s
    assert len(schedule.times_s) == 2  # the far point and the one out of order: refused
    np.testing.assert_array_equal(np.asarray(arm.commands)[[0, 1, -1]], [[2.0] * 3] * 3)
    metrics = trajectory_metrics(rows, 2.0, schedule.settle_s)
    assert metrics["periods"][0] == 6 and np.isfinite(metrics["rmse_mm"][0])  # periods 2 .. 7


def test_a_live_reference_goes_alone_needs_ros2_and_keys_the_settle_time(tmp_path):
    from pipeline.keys import control_spec

    cfg, _, _ = tracking_policy(tmp_path, "ppo_ff", task=())
    cfg.control.trajectory_topic = "/ref"
    with pytest.raises(ConfigError, match=r"control.trajectory_topic need robot=ros2"):
        control(cfg)
    spec = control_spec(cfg)[0]
    assert spec["control"]["trajectory_topic"] == "/ref"
    assert spec["control"]["trajectory"] == {"tracking_settle_seconds": 10.0}
    cfg.control.trajectory_topic = None
    assert "trajectory_topic" not in control_spec(cfg)[0]["control"]  # unset: the key as before


def test_reference_points_are_due_at_their_stamps_on_the_arms_clock():
    from types import SimpleNamespace

    from pipeline.control.ros_arm import RosArm

    arm = object.__new__(RosArm)  # only the point queue and the clock
    arm._points, arm._t0_ns, arm.scale = [], 5_000_000_000, 1.0
    arm.now = lambda: 1.25

    def message(sec, nanosec, x):
        return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=sec,
                                                                             nanosec=nanosec)),
                               point=SimpleNamespace(x=x, y=0.0, z=0.0))

    arm._on_point(message(7, 500_000_000, 1.0))  # 2.5 s after the start
    arm._on_point(message(0, 0, 2.0))  # unstamped: on arrival
    (t1, p1), (t2, p2) = arm.take_points()
    assert (t1, p1[0], t2, p2[0]) == (2.5, 1.0, 1.25, 2.0)
    assert arm.take_points() == []
