"""stage=control on the in-process simulated arm: the loop, its records and its safe stops."""

from __future__ import annotations

import copy
import dataclasses

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from pipeline.arm.safety import SafeSet
from pipeline.control.goals import GoalError, goal_schedule, workspace_problem
from pipeline.control.loop import ControlLoop, LoopSettings, SimArm
from pipeline.control.records import GOAL_COLUMNS, PeriodRecorder
from pipeline.control.results import goal_metrics
from pipeline.control.session import ControlInterrupted
from pipeline.data.schemas import CMD_COLUMNS
from pipeline.infra.artifacts import ArtifactStore
from pipeline.keys import key
from pipeline.rl.envs.learned import EnvState, with_hold_map
from pipeline.rl.envs.observation import observe
from pipeline.ros2.gate import CommandGate
from pipeline.schemas import ControlConfig
from pipeline.stages.control import control, load_deployment
from tests.conftest import compose_config
from tests.control_fixtures import SMALL, goals_mm, write_policy

LIMITS = {"p_min": 0.0, "p_max": 7.0, "sum_max": 13.0}


def assert_within_limits(commands: np.ndarray) -> None:
    commands = np.asarray(commands, np.float64)
    assert np.isfinite(commands).all()
    assert commands.min() >= LIMITS["p_min"] and commands.max() <= LIMITS["p_max"]
    assert commands.sum(axis=1).max() <= LIMITS["sum_max"]


# ---- the observation: one function for the env and the arm ------------------------------------
def test_observation_by_hand_and_identical_in_the_env():
    class Params:
        obs_mean = np.array([0.03, 0.35, 0.20], np.float32)
        obs_scale = np.array([0.01, 0.001, 0.01], np.float32)
        error_scale_m = np.float32(0.005)
        safe_set = SafeSet(np.zeros(3, np.float32), np.full(3, 7.0, np.float32), np.float32(13))

    measured = np.array([0.04, 0.351, 0.19], np.float32)
    goal = np.array([0.035, 0.35, 0.21], np.float32)
    last = np.array([0.0, 3.5, 7.0], np.float32)
    obs = observe(measured, goal, last, Params, include_error=True, include_last_action=True)
    np.testing.assert_allclose(obs, [1.0, 1.0, -1.0, 0.5, 0.0, 1.0, -1.0, -0.2, 4.0, -1, 0, 1],
                               atol=1e-4)

    from pipeline.rl.envs.learned import SoftArmReachEnv
    from pipeline.rl.envs.plants import linear_lag_plant

    env = SoftArmReachEnv(linear_lag_plant(4.0), 2.0, include_error=True,
                          include_last_action=True)
    params = type("P", (), {**{k: getattr(Params, k) for k in
                               ("obs_mean", "obs_scale", "error_scale_m", "safe_set")},
                            "obs_noise_std_m": np.float32(0.0)})
    state = EnvState(None, measured, goal, last, np.int32(0))
    import jax

    np.testing.assert_array_equal(env.observe(jax.random.key(0), state, None, params), obs)


# ---- goals ----------------------------------------------------------------------------------------
WORKSPACE = np.array([[0.020, 0.350, 0.190], [0.045, 0.354, 0.215]])


def test_a_goal_outside_the_workspace_is_refused_saying_by_how_much():
    assert workspace_problem(np.array([0.03, 0.352, 0.2]), WORKSPACE, 2.0) is None
    problem = workspace_problem(np.array([0.060, 0.352, 0.185]), WORKSPACE, 2.0)
    assert "x by 13.0 mm" in problem and "z by 3.0 mm" in problem and "y by" not in problem
    assert "x [20.0, 45.0]" in problem and "z [190.0, 215.0]" in problem


def test_goal_schedules(tmp_path):
    def control_cfg(**values):
        return ControlConfig(**{"hold_s": 2.0, "workspace_margin_mm": 2.0, **values})

    schedule = goal_schedule(control_cfg(goals=[[30, 352, 200], [40, 353, 210]]), 2.0, WORKSPACE)
    assert schedule.end == 8 and schedule.goal(0)[0] == 0 and schedule.goal(4)[0] == 1
    np.testing.assert_allclose(schedule.goal(7)[1], [0.040, 0.353, 0.210])
    with pytest.raises(GoalError, match=r"control.goals: refused: goal \[80.0, 352.0, 200.0\]"):
        goal_schedule(control_cfg(goals=[[30, 352, 200], [80, 352, 200]]), 2.0, WORKSPACE)
    with pytest.raises(GoalError, match="exactly one of"):
        goal_schedule(control_cfg(goals=[[30, 352, 200]], goal_topic="/goal"), 2.0, WORKSPACE)

    csv = tmp_path / "waypoints.csv"
    csv.write_text("t,x,y,z\n0,30,352,200\n1.5,35,352,205\n")
    schedule = goal_schedule(control_cfg(goals_csv=str(csv)), 2.0, WORKSPACE)
    assert schedule.starts.tolist() == [0, 3] and schedule.end == 7
    csv.write_text("t,x,y\n0,30,352\n")
    with pytest.raises(GoalError, match=r"missing column\(s\) \['z'\]"):
        goal_schedule(control_cfg(goals_csv=str(csv)), 2.0, WORKSPACE)


def test_goal_metrics_by_hand():
    # one goal, 4 periods of 0.5 s: distances 4, 2, 0.5 (past the goal by 0.5), 0.8, 0.8 mm
    x = np.array([-4.0, -2.0, 0.5, 0.8, 0.8]) / 1e3
    periods = pd.DataFrame({"period": range(5), "t": np.arange(5) * 0.5, "x": x, "y": 0.0,
                            "z": 0.0, "goal_index": [0, 0, 0, 0, -1], "goal_x": 0.0,
                            "goal_y": 0.0, "goal_z": 0.0,
                            **{c: [1.0, 2.0, 2.0, 4.0, np.nan] for c in CMD_COLUMNS}})
    (row,) = goal_metrics(periods, 0.5).to_dict("records")
    assert row["final_distance_mm"] == pytest.approx(0.8)
    assert row["time_to_1mm_s"] == 1.0 and row["time_to_3mm_s"] == 0.5
    assert row["overshoot_mm"] == pytest.approx(0.8)
    assert row["steady_state_error_mm"] == pytest.approx(0.8)
    assert row["smoothness_kpa"] == pytest.approx(1.0)
    # from the arrival at tick 2: 0.5, 0.8, 0.8 mm, all within 1 mm, held
    assert row["within_1mm_after_arrival"] == 1.0 and row["held_1.5mm"] == 1.0
    assert row["max_after_arrival_mm"] == pytest.approx(0.8)


# ---- the stage on the simulated arm ---------------------------------------------------------------
@pytest.fixture(scope="module")
def policies(tmp_path_factory):
    """Configs of a feed-forward and a recurrent policy artifact (random networks), by name."""
    out = tmp_path_factory.mktemp("control") / "outputs"
    cfgs = {}
    for name in ("ppo_ff", "ppo_rnn"):
        cfg = compose_config(out, *SMALL, f"control.policy={name}", "stage=control")
        _, train_params = write_policy(cfg)
        cfg.control.goals = goals_mm(train_params)
        cfg.control.hold_s = 2.0
        cfgs[name] = cfg
    return cfgs


@pytest.fixture(scope="module")
def deployment(policies):
    cfg = policies["ppo_rnn"]
    return load_deployment(cfg, ArtifactStore(cfg.paths.artifact_dir))


@pytest.mark.parametrize("policy", ["ppo_ff", "ppo_rnn"])
def test_control_on_the_simulated_arm_records_every_period_and_ends_at_the_preload(policies,
                                                                                    policy):
    cfg = policies[policy]
    artifact = control(cfg)
    assert artifact.key == key("control", cfg)
    periods = pd.read_parquet(artifact.file("periods.parquet"))
    goals = pd.read_parquet(artifact.file("goals.parquet"))
    commanded = periods[periods["goal_index"] >= 0]
    assert len(commanded) == 12 and periods["goal_index"].iloc[-1] == -1  # 3 goals x 4 periods
    assert commanded["goal_index"].tolist() == [0] * 4 + [1] * 4 + [2] * 4
    np.testing.assert_allclose(commanded["t"], np.arange(12) * 0.5)
    assert_within_limits(commanded[CMD_COLUMNS].to_numpy())
    assert (commanded["pose_age_s"] < 0.03).all()  # the latest frame: within 3 frames
    # the observation as the env builds it: position, goal, error / 5 mm, last command in [-1, 1]
    obs = commanded.filter(like="obs_").to_numpy()
    assert obs.shape[1] == 12
    error = commanded[["goal_x", "goal_y", "goal_z"]].to_numpy() - commanded[["x", "y", "z"]]
    np.testing.assert_allclose(obs[:, 6:9], error / 0.005, rtol=1e-4, atol=1e-3)
    sent = commanded[CMD_COLUMNS].to_numpy()
    last = np.vstack([[2.0, 2.0, 2.0], sent[:-1]])
    np.testing.assert_allclose(obs[:, 9:], 2 * last / 7.0 - 1, atol=1e-5)
    assert len(goals) == 3 and np.isfinite(goals["final_distance_mm"]).all()
    summary = artifact.manifest["summary"]
    assert summary["seed"] == 1  # the better held-out median of the two
    assert "interrupted" not in summary
    assert artifact.file("report.html").is_file()
    assert {p.name for p in artifact.file("figures").iterdir()} == {
        "distance.png", "path_xz.png", "pressures.png"}
    assert not list((artifact.path.parents[2] / "recovery").glob("*/*"))


def test_an_incremental_policy_changes_the_last_command_on_the_arm(tmp_path):
    # the arm applies the environment's action mapping: last command + 0.5 kPa x action, projected
    cfg = compose_config(tmp_path, *SMALL, "env.action_mode=incremental",
                         "env.action_step_kpa=0.5", "control.policy=ppo_ff", "stage=control")
    _, train_params = write_policy(cfg)
    cfg.control.goals = goals_mm(train_params, 2)
    cfg.control.hold_s = 2.0
    periods = pd.read_parquet(control(cfg).file("periods.parquet"))
    commanded = periods[periods["goal_index"] >= 0]
    sent = commanded[CMD_COLUMNS].to_numpy()
    actions = np.clip(commanded.filter(like="action_").to_numpy(), -1.0, 1.0)
    last = np.vstack([[2.0, 2.0, 2.0], sent[:-1]])
    assert_within_limits(sent)
    inside = (sent > LIMITS["p_min"] + 1e-6) & (sent < LIMITS["p_max"] - 1e-6)
    np.testing.assert_allclose(sent[inside], (last + 0.5 * actions)[inside], atol=1e-5)
    assert np.abs(sent - last).max() <= 0.5 + 1e-6
    assert np.abs(sent - last).max() > 1e-3  # it moved


def test_the_arm_accumulates_the_error_as_the_environment_does(tmp_path):
    # zero at a goal's first period, then 0.5 x the last + 0.5 x (goal - measured) / error scale
    cfg = compose_config(tmp_path, *SMALL, "env.include_error_integral=true",
                         "env.error_integral_decay=0.5", "control.policy=ppo_ff",
                         "stage=control")
    _, train_params = write_policy(cfg)
    cfg.control.goals = goals_mm(train_params, 1)
    cfg.control.hold_s = 3.0
    periods = pd.read_parquet(control(cfg).file("periods.parquet"))
    commanded = periods[periods["goal_index"] >= 0]
    error = commanded.filter(like="obs_").to_numpy()[:, 6:9]  # (goal - measured) / scale
    measured = (commanded[GOAL_COLUMNS].to_numpy() - commanded[["x", "y", "z"]].to_numpy())
    np.testing.assert_allclose(error, measured / float(train_params.error_scale_m), rtol=1e-4,
                               atol=1e-4)
    integral = commanded.filter(like="obs_").to_numpy()[:, 9:12]
    expected = [np.zeros(3)]
    for row in error[1:]:
        expected.append(0.5 * expected[-1] + 0.5 * row)
    assert len(expected) >= 4
    np.testing.assert_allclose(integral, np.array(expected), rtol=1e-4, atol=1e-4)
    assert np.abs(integral).max() > 1e-3


def _loop(cfg, deployment, arm_factory, tmp_path):
    robot, control_settings = OmegaConf.to_object(cfg.robot), OmegaConf.to_object(cfg.control)
    schedule = goal_schedule(control_settings, deployment.control_hz, deployment.workspace_m)
    gate = CommandGate(robot.limits, 3)
    arm = arm_factory(SimArm(robot, 0, gate))
    recorder = PeriodRecorder(tmp_path / "chunks", deployment.env.obs_dim, {}, {})
    # robot=sim has no watchdog setting; the loop takes one where the robot has one
    settings = dataclasses.replace(LoopSettings.of(robot, control_settings), watchdog_s=0.2)
    return ControlLoop(deployment, schedule, gate, arm, recorder, settings).run(), arm


def test_loop_settings_take_the_watchdog_and_missed_periods_of_a_ros2_robot_only():
    from pipeline.schemas import Ros2RobotConfig, SimRobotConfig

    control_settings = ControlConfig(max_pose_jump_mm=15.0, workspace_margin_mm=1.0,
                                     flush_every_s=3.0)
    ros = LoopSettings.of(Ros2RobotConfig(control_hz=4.0, watchdog_s=0.3, max_missed_periods=1),
                          control_settings)
    assert ros == LoopSettings(control_hz=4.0, watchdog_s=0.3, max_missed_periods=1,
                               max_pose_jump_mm=15.0, workspace_margin_mm=1.0, flush_every_s=3.0)
    sim = LoopSettings.of(SimRobotConfig(control_hz=2.0), control_settings)
    assert sim.watchdog_s is None and sim.max_missed_periods == 2 and sim.control_hz == 2.0


class Faulty:
    """The simulated arm with a fault from arm time ``at`` on: ``kind`` jump | silent | error."""

    def __init__(self, arm, kind, at=1.2):
        self.arm, self.kind, self.at = arm, kind, at
        self.commands = arm.commands

    def __getattr__(self, name):
        return getattr(self.arm, name)

    def take_frames(self):
        frames = self.arm.take_frames()
        if self.arm.now() < self.at:
            return frames
        if self.kind == "silent":
            return []
        if self.kind == "error":
            raise OSError("the mocap driver went away")
        return [(s, r, xyz + np.array([0.03, 0.0, 0.0])) for s, r, xyz in frames]


@pytest.mark.parametrize(("kind", "reason"), [
    ("jump", "ControlFault: pose jump of 30.0 mm"),
    ("silent", "mocap watchdog: the latest pose is"),
    ("error", "OSError: the mocap driver went away")])
def test_faults_stop_at_the_preload(policies, deployment, tmp_path, kind, reason):
    outcome, arm = _loop(policies["ppo_rnn"], deployment, lambda a: Faulty(a, kind), tmp_path)
    assert outcome.reason.startswith(reason), outcome.reason
    commands = np.asarray(arm.commands)
    assert 2 <= len(commands) <= 4  # stopped at the period after the fault (1.2 s)
    np.testing.assert_array_equal(commands[-1], [2.0, 2.0, 2.0])
    assert_within_limits(commands)
    chunks = pd.concat(pd.read_parquet(p) for p in sorted((tmp_path / "chunks").glob("periods-*")))
    assert len(chunks) == len(commands) - 1  # every command but the preload is recorded


def test_a_stop_signal_ends_the_session_at_the_preload(policies, deployment, tmp_path):
    class Signals:
        received = None

    signals = Signals()

    def with_signal(arm):
        arm.signals = signals
        original = arm.publish

        def publish(pressures):
            if len(arm.commands) == 3:
                signals.received = "SIGTERM"
            return original(pressures)

        arm.publish = publish
        return arm

    outcome, arm = _loop(policies["ppo_rnn"], deployment, with_signal, tmp_path)
    assert outcome.reason == "SIGTERM received"
    assert len(arm.commands) == 5
    np.testing.assert_array_equal(arm.commands[-1], [2.0, 2.0, 2.0])


def test_a_non_finite_policy_output_stops_with_a_clear_error(make_cfg):
    cfg = make_cfg(*SMALL, "stage=control")
    _, train_params = write_policy(cfg, scale=np.nan)
    cfg.control.goals = goals_mm(train_params)
    with pytest.raises(ControlInterrupted, match="non-finite policy output at period 0"):
        control(cfg)
    assert ArtifactStore(cfg.paths.artifact_dir).find("control", key("control", cfg)) is None


def test_live_goals_take_effect_at_the_next_period_and_bad_ones_are_refused(policies,
                                                                            deployment, tmp_path):
    cfg = policies["ppo_rnn"].copy()
    cfg.control.goals = []
    cfg.control.goal_topic = "/goal"
    cfg.control.duration_s = 3.0
    inside = np.asarray(cfg_goals := policies["ppo_rnn"].control.goals, np.float64) / 1e3

    class Live:
        def __init__(self, arm):
            self.arm, self.commands, self.sent = arm, arm.commands, []

        def __getattr__(self, name):
            return getattr(self.arm, name)

        def take_goals(self):
            now = self.arm.now()
            due = [(0.9, inside[0]), (1.0, np.array([0.5, 0.35, 0.2])), (2.0, inside[1])]
            out = [g for t, g in due if t <= now and t not in self.sent]
            self.sent += [t for t, _ in due if t <= now and t not in self.sent]
            return out

    outcome, arm = _loop(cfg, deployment, Live, tmp_path)
    assert outcome.reason is None and outcome.periods == 6, outcome
    chunks = pd.concat(pd.read_parquet(p) for p in sorted((tmp_path / "chunks").glob("periods-*")))
    commanded = chunks[chunks["goal_index"] >= 0]
    assert commanded["period"].tolist() == [2, 3, 4, 5]  # periods 0, 1 held the preload
    assert commanded["goal_index"].tolist() == [0, 0, 1, 1]  # the far goal was refused
    np.testing.assert_allclose(commanded[["goal_x", "goal_y", "goal_z"]].to_numpy()[-1],
                               np.asarray(cfg_goals[1]) / 1e3)
    np.testing.assert_array_equal(np.asarray(arm.commands)[[0, 1, -1]], [[2.0] * 3] * 3)


def test_the_arm_keeps_the_last_command_within_the_deadband(policies):
    """env.deadband_m of the session (not of the training) reaches the deployed step: a pose
    measured 0.9 mm from the goal sends the last command again, 1.1 mm away the policy's; a
    reference (control.trajectory) moves on, so there it is off."""
    cfg = copy.deepcopy(policies["ppo_ff"])
    cfg.env.deadband_m, cfg.env.hold_gain = 0.001, 0.0
    deployment = load_deployment(cfg, ArtifactStore(cfg.paths.artifact_dir))
    assert float(deployment.env_params.deadband_m) == pytest.approx(0.001)
    goal = np.asarray(deployment.env_params.goal_set[0], np.float64)
    last = np.array([2.5, 3.0, 1.0])
    preview = np.zeros((0, 3))
    for offset_mm, held in ((0.9, True), (1.1, False)):
        measured = goal + np.array([offset_mm, 0.0, 0.0]) / 1e3
        _, _, _, pressure = deployment.act(deployment.hidden, True, measured, goal, preview, last)
        assert np.allclose(pressure, last, atol=1e-5) == held
    cfg.control.trajectory = "circle"
    assert float(load_deployment(cfg, ArtifactStore(cfg.paths.artifact_dir))
                 .env_params.deadband_m) == 0.0


def test_the_arm_is_held_by_integral_action_through_its_models_static_map(policies):
    """With a hold gain the deployed step, within env.deadband_m of the goal, moves the last
    command by the gain times the model's hold map applied to the error (the evaluate stage's
    function, on the session's settings); beyond it, the policy's."""
    cfg = copy.deepcopy(policies["ppo_ff"])
    cfg.env.deadband_m, cfg.env.hold_gain = 0.002, 0.5
    deployment = load_deployment(cfg, ArtifactStore(cfg.paths.artifact_dir))
    params = deployment.env_params
    assert float(params.hold_gain) == pytest.approx(0.5)
    np.testing.assert_allclose(params.hold_map, with_hold_map(deployment.env, params.replace(
        hold_map=jnp.zeros((3, 3)))).hold_map)  # the model's own
    goal = np.asarray(params.goal_set[0], np.float64)
    last = np.array([2.5, 3.0, 1.0])
    preview = np.zeros((0, 3))
    error = np.array([-1.5, 0.0, 0.5]) / 1e3  # goal - measured, 1.58 mm
    _, _, _, pressure = deployment.act(deployment.hidden, True, goal - error, goal, preview,
                                       last)
    correction = np.asarray(params.hold_map) @ error
    assert np.abs(correction).max() > 0.05
    np.testing.assert_allclose(pressure, last + 0.5 * correction, atol=1e-4)
    far = goal - np.array([2.5, 0.0, 0.0]) / 1e3
    policy = deployment.act(deployment.hidden, True, far, goal, preview, last)[3]
    cfg.env.hold_gain = 0.0
    cfg.env.deadband_m = 0.0
    alone = load_deployment(cfg, ArtifactStore(cfg.paths.artifact_dir))
    np.testing.assert_allclose(policy, alone.act(alone.hidden, True, far, goal, preview, last)[3])


def test_control_is_routed_alone_and_never_by_the_chain(make_cfg):
    from pipeline.chain import CHAIN, STAGES, stages_to_run
    from pipeline.schemas import Stage

    assert Stage.control in STAGES and Stage.control not in CHAIN
    assert stages_to_run(make_cfg("stage=control", "robot=ros2")) == [Stage.control]
    assert stages_to_run(make_cfg("stage=control")) == [Stage.control]
