"""The tracking task: the environment's moving goal and preview, its evaluation and metrics."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.arm import references as R
from pipeline.arm.safety import SafeSet
from pipeline.chain import cross_model_folds
from pipeline.evaluation.closed_loop import ClosedLoopSettings
from pipeline.evaluation.tracking import TrackingSettings, run_tracking, tracking_metrics
from pipeline.rl.envs import (
    SoftArmReachEnv,
    default_linear_lag_params,
    linear_lag_plant,
    make_env_params,
    task,
)
from pipeline.schemas import ConfigError, EnvConfig, EvaluationConfig
from pipeline.stages._environment import config_environment
from pipeline.stages.evaluate import tracking_settings
from pipeline.validation import validate_config

LIMITS = OmegaConf.create({"p_min": 0.0, "p_max": 7.0, "sum_max": 13.0, "preload": 2.0})
REST_POSE = jnp.array([0.032, 0.353, 0.202])
GOALS = REST_POSE + jnp.array([[0.005, 0.0, 0.0], [0.0, 0.0, -0.005], [-0.004, 0.0, 0.003]])


def toy(task_name="reach", preview=0, **settings):
    env = SoftArmReachEnv(linear_lag_plant(10.0), 2.0, settle_seconds=2.0, include_error=True,
                          task=task_name, preview=preview)
    config = EnvConfig(task=task_name, preview=preview, max_steps=5, reset_bank_size=4,
                       **settings)
    params = make_env_params(env, default_linear_lag_params(), config, key=jax.random.PRNGKey(0),
                             safe_set=SafeSet.from_limits(LIMITS), preload=2.0,
                             rest_pose=REST_POSE, goal_set=GOALS)
    return env, params


def episode(env, params, actions, seed=0):
    obs, state = jax.jit(env.reset)(jax.random.PRNGKey(seed), params)
    out = [(obs, state, None, None)]
    step = jax.jit(env.step_env)
    for number, action in enumerate(actions):
        obs, state, reward, done, _ = step(jax.random.PRNGKey(100 + number), state,
                                           jnp.asarray(action, jnp.float32), params)
        out.append((obs, state, reward, done))
    return out


ACTIONS = [[0.5, -0.2, 0.1], [-0.3, 0.4, 0.0], [0.2, 0.2, -0.6]]


def test_reaching_does_not_see_the_tracking_settings():
    env, params = toy()
    _, other = toy(static_share=0.9, reference_size_max_mm=9.0, reference_period_min_s=3.0)
    for (obs, state, reward, _), (obs2, state2, reward2, _) in zip(
            episode(env, params, ACTIONS), episode(env, other, ACTIONS)):
        np.testing.assert_array_equal(obs, obs2)
        np.testing.assert_array_equal(state.position, state2.position)
        np.testing.assert_array_equal(state.goal, state2.goal)
        assert state.reference is None and (reward is None or reward == reward2)
    assert env.obs_dim == 9


def test_the_default_configs_artifact_keys_ignore_the_tracking_settings(make_cfg):
    base = make_cfg()
    changed = make_cfg("env.static_share=0.5", "env.reference_size_max_mm=3",
                       "evaluation.tracking_seconds=12")
    for stage in ("train_ppo", "evaluate"):
        assert keys.key(stage, base) == keys.key(stage, changed)
    tracked = make_cfg("experiment=tracking")
    assert keys.key("train_ppo", tracked) != keys.key("train_ppo", base)
    assert keys.key("fit_model", tracked) == keys.key("fit_model", base)  # same model


def test_a_replayed_csv_keys_the_evaluation_by_its_content(make_cfg, tmp_path):
    path = tmp_path / "walk.csv"
    path.write_text("t,x,y,z\n0,30,353,200\n1,31,353,200\n")
    cfg = make_cfg("experiment=tracking",
                   f"+evaluation.references.walk={{kind:replay,file:{path},slow_down:2}}")
    spec = keys.evaluate_spec(cfg)[0]["evaluation"]["references"]["walk"]
    assert "file" not in spec and spec["slow_down"] == 2 and len(spec["file_sha256"]) == 64
    first = keys.key("evaluate", cfg)
    path.write_text("t,x,y,z\n0,30,353,200\n1,32,353,200\n")
    assert keys.key("evaluate", cfg) != first
    assert keys.key("train_ppo", cfg) == keys.key("train_ppo", make_cfg("experiment=tracking"))


def test_each_period_follows_the_reference_at_its_end_with_a_preview():
    env, params = toy("track", preview=2, static_share=0.0, goal_tolerance_m=1.0)
    assert env.obs_dim == 9 + 6
    steps = episode(env, params, ACTIONS)
    reference = steps[0][1].reference
    assert float(jnp.abs(reference.omega)) > 0  # a moving shape around a goal of the set
    for period, (obs, state, reward, done) in enumerate(steps):
        # the goal in force during period k is the reference at (k + 1) / 2 s
        expected = R.position(reference, (period + 1) / 2.0)
        np.testing.assert_allclose(state.goal, expected, atol=1e-7)
        # preview: the next two periods' goals relative to the position, in the error's scale
        ahead = R.positions(reference, jnp.array([period + 2, period + 3]) / 2.0)
        np.testing.assert_allclose(obs[-6:], ((ahead - state.position) / 0.005).reshape(-1),
                                   rtol=1e-5, atol=1e-4)
        if period:
            previous_goal = steps[period - 1][1].goal
            np.testing.assert_allclose(
                reward, -1000.0 * np.linalg.norm(state.position - previous_goal), rtol=1e-5)
            assert not done  # within the (1 m) tolerance, yet no end on arrival


def test_a_static_share_of_one_tracks_the_reaching_goal():
    env, params = toy("track", static_share=1.0)
    reach_env, reach_params = toy()
    for key in range(4):
        _, tracked = jax.jit(env.reset)(jax.random.PRNGKey(key), params)
        _, reached = jax.jit(reach_env.reset)(jax.random.PRNGKey(key), reach_params)
        np.testing.assert_array_equal(tracked.goal, reached.goal)
        np.testing.assert_array_equal(tracked.position, reached.position)


def test_preview_only_to_track():
    with pytest.raises(ValueError, match="preview"):
        SoftArmReachEnv(linear_lag_plant(10.0), 2.0, preview=2)
    assert task.goal_path(R.static(jnp.ones(3)), 3, 2.0).shape == (3, 3)


@pytest.mark.parametrize("overrides, words", [
    (["env.preview=2"], "env.preview=2 observes a moving reference: it needs env.task=track"),
    (["experiment=tracking", "env.static_share=1.5"], "env.static_share=1.5 must lie in"),
    (["experiment=tracking", "env.reference_size_min_mm=8"], "env.reference_size_min_mm=8.0"),
])
def test_bad_tracking_settings_are_refused_by_name(make_cfg, overrides, words):
    with pytest.raises(ConfigError, match=words):
        validate_config(make_cfg(*overrides))


def test_tracking_metrics_by_hand():
    times = np.arange(21) / 2.0  # 10 s at 2 Hz
    reference = np.stack([0.005 * np.cos(2 * np.pi * times / 10), np.zeros(21),
                          0.005 * np.sin(2 * np.pi * times / 10)], axis=-1)[None]
    offset = reference + np.array([0.0, 0.002, 0.0])  # 2 mm off, all along
    table = tracking_metrics(np.concatenate([offset, reference + np.array([0, 0.0005, 0])]),
                             np.concatenate([reference, reference]), 2.0, settle_seconds=2.0)
    np.testing.assert_allclose(table["rmse_mm"], [2.0, 0.5], rtol=1e-9)
    np.testing.assert_allclose(table["max_mm"], [2.0, 0.5], rtol=1e-9)
    np.testing.assert_allclose(table["within_1mm"], [0.0, 1.0])
    np.testing.assert_allclose(table["lag_s"], [0.0, 0.0], atol=1e-9)
    # a constant gap is all steady offset: its length and its signed axes
    np.testing.assert_allclose(table["offset_mm"], [2.0, 0.5], rtol=1e-9)
    np.testing.assert_allclose(table[["offset_x_mm", "offset_y_mm", "offset_z_mm"]],
                               [[0.0, 2.0, 0.0], [0.0, 0.5, 0.0]], atol=1e-9)
    # half the scored ticks 1 mm below in x, half 3 mm above: offset 1 mm, RMSE sqrt(5) mm
    swing = reference.copy()
    swing[0, 5::2, 0] -= 0.001  # the scored ticks 5 .. 20 (after 2.5 s), 8 of each
    swing[0, 6::2, 0] += 0.003
    half = tracking_metrics(swing, reference, 2.0, settle_seconds=2.5)
    assert half["offset_x_mm"][0] == pytest.approx(1.0, abs=1e-9)
    assert half["offset_mm"][0] == pytest.approx(1.0, abs=1e-9)
    assert half["rmse_mm"][0] == pytest.approx(np.sqrt(5.0), rel=1e-9)
    # a path one second behind: positions[k] = reference[k - 2]
    long_times = np.arange(61) / 2.0
    circle = np.stack([0.005 * np.cos(2 * np.pi * long_times / 20), np.zeros(61),
                       0.005 * np.sin(2 * np.pi * long_times / 20)], axis=-1)
    behind = np.concatenate([np.repeat(circle[:1], 2, axis=0), circle[:-2]])
    lagged = tracking_metrics(behind[None], circle[None], 2.0, settle_seconds=5.0)
    assert lagged["lag_s"][0] == pytest.approx(1.0, abs=1e-6)
    chord = 2 * 5.0 * np.sin(np.pi * 1.0 / 20)  # mm: the circle's chord over 1 s of a 20 s lap
    assert lagged["rmse_mm"][0] == pytest.approx(chord, rel=1e-6)
    assert np.isnan(lagged["at_limits"][0])  # no commands given


def test_tracking_metrics_share_of_commands_on_the_limits():
    times = np.arange(11) / 2.0  # 5 s at 2 Hz: ticks 0 .. 10, commands of periods 0 .. 9
    path = np.zeros((1, 11, 3))
    commands = np.full((1, 10, 3), 2.0)
    commands[0, 3] = [5.0, 4.0, 4.0]  # the sum at 13 kPa
    commands[0, 6] = [7.0, 2.0, 2.0]  # a valve at p_max
    commands[0, 8:] = [0.0, 3.0, 3.0]  # a valve at p_min (periods 8, 9)
    safe = SafeSet(p_min=np.zeros(3), p_max=np.full(3, 7.0), sum_max=np.asarray(13.0))
    table = tracking_metrics(path, path + times[None, :, None] * 0.0, 2.0, settle_seconds=2.0,
                             commands=commands, safe=safe)
    # scored ticks 4 .. 10: the commands of periods 3 .. 9, 4 of the 7 on a limit
    assert table["at_limits"][0] == pytest.approx(4 / 7)
    with pytest.raises(ValueError, match=r"commands must be \[E, T, n_valves\]"):
        tracking_metrics(path, path, 2.0, settle_seconds=2.0, commands=commands[:, :5],
                         safe=safe)


@pytest.mark.slow  # among the longest of the suite: runs with `make test-all`
def test_run_tracking_on_the_simulated_arm_scores_the_preload(make_cfg):
    cfg = make_cfg("env=sim", "env.task=track", "env.preview=1", "env.num_goals=64",
                   "env.reset_bank_size=4")
    env, _, params = config_environment(cfg)
    settings = ClosedLoopSettings(
        evaluation=EvaluationConfig(num_episodes=4, baselines=["preload"]), max_steps=4,
        model_hz=float(cfg.dataset.model_hz), limits=cfg.robot.limits,
        env=OmegaConf.to_object(cfg.env))
    shapes = {"circle": R.ShapeSettings("circle", None, 2.0, period_s=10.0)}
    with pytest.raises(ConfigError, match=r"evaluation\.references circle refused"):
        run_tracking(settings, TrackingSettings(shapes, 6.0, 2.0, 0.001), {}, env, params)
    results = run_tracking(settings, TrackingSettings(shapes, 6.0, 2.0, 50.0), {}, env, params)
    table = results["tables"]["tracking_episodes"]
    assert len(table) == 4 and set(table["controller"]) == {"preload"}
    # the preload holds the arm where it rests: the error is the distance from the rest pose
    path = results["paths"][("learned", "preload", "circle", 0)]
    target = results["reference_paths"]["circle"]
    error = np.linalg.norm(path - target, axis=-1)[:, 4:] * 1000.0
    np.testing.assert_allclose(table["rmse_mm"], np.sqrt((error ** 2).mean(axis=1)), rtol=1e-6)
    np.testing.assert_allclose(path, np.broadcast_to(path[:, :1], path.shape), atol=2e-4)
    # the episodes' phases are spread over a lap: a quarter lap apart
    np.testing.assert_allclose(np.linalg.norm(target[0, 0] - target[2, 0]) * 1000, 4.0,
                               rtol=1e-4)


TINY_TRACKING = ["experiment=[quick,tracking]", "robot.num_runs=2", "exploration.num_steps=40",
                 "agent.num_seeds=1", "agent.total_timesteps=4096", "agent.num_evals=1",
                 "evaluation.num_episodes=4", "evaluation.consecutive_episodes=2",
                 "model.num_steps=20", "model.eval_every=10", "model.checkpoint_every=10",
                 "dataset.window=32", "dataset.train_fraction=0.5", "env.max_steps=8",
                 "evaluation.tracking_seconds=8", "evaluation.tracking_settle_seconds=2",
                 "evaluation.reachable_tolerance_mm=50", "evaluation.mpc_samples=8",
                 "evaluation.mpc_iterations=1"]


@pytest.mark.slow
def test_experiment_tracking_trains_and_evaluates_both_policy_types(make_cfg):
    from pipeline.__main__ import run

    cfg = make_cfg(*TINY_TRACKING)
    assert cfg.env.task == "track" and cfg.env.preview == 3
    artifact = run(cfg)["evaluate"]
    import pandas as pd

    summary = pd.read_parquet(artifact.file("tracking.parquet"))
    # the reaching policies of the same settings, fed the moving goal, as a baseline
    assert set(summary["controller"]) == {"apg", "apg_rnn", "preload", "mpc",
                                          "apg (reaching)", "apg_rnn (reaching)"}
    assert set(summary["reference"]) == {"circle", "figure_eight"}
    assert set(summary["plant"]) == {"learned", "plant"}
    assert np.isfinite(summary["median_rmse_mm"]).all()
    episodes = pd.read_parquet(artifact.file("tracking_episodes.parquet"))
    assert len(episodes) == 2 * 6 * 2 * 4  # plants x controllers x references x episodes
    markdown = artifact.file("report.md").read_text()
    assert "## Tracking" in markdown and "tracking.png" in markdown
    assert artifact.file("figures/tracking.png").stat().st_size > 10_000
    assert "tracking/plant/apg_rnn/circle" in artifact.manifest["summary"]


def test_evaluation_references_over_their_defaults_and_unknown_settings(make_cfg):
    cfg = make_cfg("experiment=tracking",
                   "+evaluation.references.fast={kind:figure_eight,period_s:10}")
    shapes = tracking_settings(cfg).references
    assert shapes["circle"] == R.ShapeSettings("circle", None, 5.0, period_s=20.0)
    assert shapes["fast"].kind == "figure_eight" and shapes["fast"].period_s == 10
    assert shapes["fast"].size_mm == 5.0 and shapes["fast"].plane == "xz"
    bad = make_cfg("experiment=tracking", "+evaluation.references.odd={shape:circle}")
    with pytest.raises(ConfigError, match=r"evaluation\.references\.odd: unknown setting\(s\) "
                                          r"\['shape'\]"):
        tracking_settings(bad)


def test_the_recorded_arm_tracks_with_absolute_actions_and_the_mpc_over_the_preview(
        make_cfg, sorolex_dir):
    cfg = make_cfg("experiment=real_arm_tracking", f"robot.data_dir={sorolex_dir}")
    validate_config(cfg)
    reaching = make_cfg("experiment=real_arm", f"robot.data_dir={sorolex_dir}")
    # real_arm's models, ensemble, randomization (less its command delay) and plants; the task,
    # the action mode, the trainer (analytic policy gradients, with integral action on the
    # tracking error) and no price
    assert cfg.env.task.value == "track" and cfg.env.action_mode.value == "absolute"
    assert reaching.env.action_mode.value == "incremental"
    assert cfg.env.ensemble_seeds == reaching.env.ensemble_seeds
    assert cfg.env.randomization.max_delay_s == 0 < reaching.env.randomization.max_delay_s
    assert ({**cfg.env.randomization, "max_delay_s": None}
            == {**reaching.env.randomization, "max_delay_s": None})
    assert cfg.agent.trainer.value == "apg" and reaching.agent.trainer.value == "ppo"
    assert cfg.env.reference_integral_gain == 0.2 and cfg.env.command_change_cost_mm_per_kpa == 0
    assert list(cfg.evaluation.policies) == ["apg", "apg_rnn"] and cfg.control.policy == "apg_rnn"
    assert keys.key("fit_model", cfg) == keys.key("fit_model", reaching)
    assert list(cfg.evaluation.twins) == ["sim_sorolex"] and cfg.evaluation.reaching
    # the cross-model groups train 8 seeds each (their tracking figures within about 0.02 mm of
    # those at 20), the deployed policy's training 20, at the same steps
    assert cfg.agent.num_seeds == 20
    for train, _ in cross_model_folds(cfg).values():
        assert train.agent.num_seeds == 8
        assert train.agent.recurrent_total_timesteps == cfg.agent.recurrent_total_timesteps
    # the MPC plans over what the policies see ahead: the period's goal and the preview
    tracking = tracking_settings(cfg)
    # the circle, the figure-eight and the paths the arm went through, four times slower
    assert set(tracking.references) == {"circle", "figure_eight", "walk"}
    assert tracking.references["walk"] == R.ReplaySettings(slow_down=4.0)
    assert tracking.mpc_horizon is None
    env = SoftArmReachEnv(linear_lag_plant(10.0), 2.0, task="track", preview=int(cfg.env.preview))
    assert tracking.mpc_settings(cfg.evaluation, env).horizon == 4
