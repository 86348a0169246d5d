"""The reaching environment: gymnax API under jit and vmap, spaces, safety, episode ends, keys."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from omegaconf import OmegaConf

from pipeline.arm.safety import SafeSet
from pipeline.dynamics import model as dynamics
from pipeline.rl.envs import (
    SoftArmReachEnv,
    default_linear_lag_params,
    hold,
    learned_plant,
    linear_lag_plant,
    make_env_params,
    sim_plant,
)
from pipeline.rl.envs.factory import sim_plant_params, sim_rest_pose
from pipeline.schemas import EnvConfig, GoalMode
from tests.conftest import compose_config

LIMITS = OmegaConf.create({"p_min": 0.0, "p_max": 7.0, "sum_max": 13.0, "preload": 2.0})
REST_POSE = jnp.array([0.032, 0.353, 0.202])
NUM_ENVS = 8
ENV_FIELDS = {f.name for f in dataclasses.fields(EnvConfig)}


def toy_env(**overrides):
    """Linear-lag plant at 10 Hz, 2 Hz control; goals a few mm around the rest pose."""
    env = SoftArmReachEnv(linear_lag_plant(10.0), control_hz=2.0, settle_seconds=2.0,
                          include_last_action=overrides.pop("include_last_action", False),
                          include_error=overrides.pop("include_error", False),
                          include_error_integral=overrides.pop("include_error_integral", False))
    goals = REST_POSE + jnp.array([[0.005, 0.0, 0.0], [0.0, 0.0, -0.005], [-0.004, 0.0, 0.003]])
    settings = {"safe_set": SafeSet.from_limits(LIMITS), "preload": 2.0, "rest_pose": REST_POSE,
                "goal_set": goals, "max_steps": 5, "reset_bank_size": 4}
    settings.update(overrides)
    params = make_env_params(env, default_linear_lag_params(), EnvConfig(**{k: settings.pop(k) for k in list(settings) if k in ENV_FIELDS}),
                             key=jax.random.PRNGKey(0), **settings)
    return env, params


def batched(env, params, num=NUM_ENVS, seed=0):
    keys = jax.random.split(jax.random.PRNGKey(seed), num)
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    obs, state = reset(keys, params)
    return reset, step, obs, state


def test_reset_and_step_under_jit_and_vmap():
    env, params = toy_env()
    _, step, obs, state = batched(env, params)
    assert obs.shape == (NUM_ENVS, env.obs_dim) == (NUM_ENVS, 6)
    assert env.observation_space(params).shape == (6,)
    assert env.action_space(params).shape == (3,)
    assert np.all(np.asarray(env.action_space(params).low) == -1.0)
    keys = jax.random.split(jax.random.PRNGKey(1), NUM_ENVS)
    obs, state, reward, terminated, truncated, info = step(keys, state, jnp.zeros((NUM_ENVS, 3)),
                                                           params)
    assert obs.shape == (NUM_ENVS, 6) and obs.dtype == jnp.float32
    for value in (reward, terminated, truncated, info["distance_m"]):
        assert value.shape == (NUM_ENVS,)
    assert info["final_observation"].shape == (NUM_ENVS, 6)
    assert np.all(np.asarray(reward) <= 0)
    np.testing.assert_allclose(-np.asarray(reward), 1000 * np.asarray(info["distance_m"]),
                               rtol=1e-5)  # reward in mm


def test_start_is_the_settled_preload_pose_and_goal_is_from_the_goal_set():
    env, params = toy_env()
    _, state = env.reset(jax.random.PRNGKey(3), params)
    np.testing.assert_allclose(state.position, REST_POSE, atol=1e-6)  # toy: preload is its rest
    np.testing.assert_allclose(state.last_pressure, 2.0)
    assert int(state.time) == 0
    assert np.min(np.linalg.norm(np.asarray(params.goal_set) - np.asarray(state.goal), axis=1)
                  ) < 1e-7


def test_perturb_goals_are_spread_around_the_initial_pose():
    env, params = toy_env(goal_mode="perturb", goal_perturbation_m=0.01, goal_set=None)
    _, _, _, state = batched(env, params, num=512)
    offsets = np.asarray(state.goal - state.position)
    assert abs(offsets.mean()) < 2e-3
    np.testing.assert_allclose(offsets.std(axis=0), 0.01, rtol=0.15)


def test_actions_are_mapped_to_the_valve_range_and_projected_into_the_safe_set():
    env, params = toy_env()
    _, step, _, state = batched(env, params)
    actions = jax.random.uniform(jax.random.PRNGKey(2), (NUM_ENVS, 3), minval=-3.0, maxval=3.0)
    actions = actions.at[0].set(jnp.ones(3))  # 7+7+7 kPa: must be pulled under the 13 kPa sum
    actions = actions.at[1].set(-jnp.ones(3))
    keys = jax.random.split(jax.random.PRNGKey(4), NUM_ENVS)
    *_, info = step(keys, state, actions, params)
    pressure = np.asarray(info["pressure"])
    assert np.all(pressure >= 0.0) and np.all(pressure <= 7.0)
    assert np.all(pressure.sum(axis=1) <= 13.0)
    np.testing.assert_allclose(pressure[0], 13.0 / 3, atol=1e-3)
    np.testing.assert_allclose(pressure[1], 0.0, atol=1e-6)


def test_action_noise_cannot_leave_the_safe_set():
    env, params = toy_env(action_noise_std_kpa=5.0)
    _, step, _, state = batched(env, params, num=64)
    keys = jax.random.split(jax.random.PRNGKey(5), 64)
    *_, info = step(keys, state, jnp.ones((64, 3)), params)
    pressure = np.asarray(info["pressure"])
    assert pressure.min() >= 0.0 and pressure.max() <= 7.0
    assert pressure.sum(axis=1).max() <= 13.0
    assert pressure.std(axis=0).min() > 0.1  # the noise does act


def test_termination_within_tolerance_is_not_truncation():
    env, params = toy_env(goal_tolerance_m=0.05)  # every goal is within 5 cm
    _, state = env.reset(jax.random.PRNGKey(0), params)
    _, state, _, terminated, truncated, _ = env.step(
        jax.random.PRNGKey(1), state, env.pressure_to_action(params.preload, params), params)
    assert bool(terminated) and not bool(truncated)
    assert int(state.time) == 0  # auto-reset


def test_truncation_at_the_step_limit_is_not_termination():
    env, params = toy_env(goal_tolerance_m=1e-9, max_steps=5)
    _, state = env.reset(jax.random.PRNGKey(0), params)
    action = jnp.zeros(3)
    flags = []
    for i in range(5):
        obs, state, _, terminated, truncated, info = env.step(
            jax.random.PRNGKey(10 + i), state, action, params)
        flags.append((bool(terminated), bool(truncated)))
    assert flags == [(False, False)] * 4 + [(False, True)]
    assert int(state.time) == 0  # reset after truncation
    # the final observation of the truncated episode is reported for bootstrapping
    assert not np.allclose(info["final_observation"], obs)


def test_hold_periods_end_an_episode_after_that_many_periods_at_the_goal_in_a_row():
    """hold_periods=3: within, away (the count starts again), then within three times."""
    env, params = toy_env(hold_periods=3, goal_tolerance_m=0.001)
    _, state = env.reset(jax.random.PRNGKey(0), params)
    at_preload = env.pressure_to_action(params.preload, params)  # the toy rests at the preload
    step = jax.jit(env.step_env)  # no auto-reset: the counter is seen after every period
    here, far = state.position, state.position + jnp.array([0.0, 0.0, 0.01])
    counts, ends = [], []
    for i, goal in enumerate([here, far, here, here, here]):
        _, state, _, terminated, _ = step(jax.random.PRNGKey(i), state.replace(goal=goal),
                                          at_preload, params)
        counts.append(int(state.periods_within))
        ends.append(bool(terminated))
    assert counts == [1, 0, 1, 2, 3]
    assert ends == [False, False, False, False, True]
    # the same compiled step with hold_periods=1 ends at the first arrival, as without the setting
    _, _, _, terminated, _ = step(jax.random.PRNGKey(9), state.replace(
        goal=here, periods_within=jnp.zeros((), jnp.int32)), at_preload,
        params.replace(hold_periods=jnp.asarray(1, jnp.int32)))
    assert bool(terminated)
    assert step._cache_size() == 1  # one program for every hold_periods
    with pytest.raises(ValueError, match="hold_periods"):
        toy_env(hold_periods=0)


def test_hold_bonus_is_paid_for_every_period_at_the_goal():
    env, params = toy_env(hold_periods=5, hold_bonus_mm=2.5, goal_tolerance_m=0.001)
    _, state = env.reset(jax.random.PRNGKey(0), params)
    at_preload = env.pressure_to_action(params.preload, params)
    offset = jnp.array([0.0004, 0.0, 0.0])  # 0.4 mm: within
    _, _, reward, _, info = env.step_env(jax.random.PRNGKey(1), state.replace(
        goal=state.position + offset), at_preload, params)
    assert float(info["distance_m"]) == pytest.approx(0.0004, abs=1e-6)
    assert float(reward) == pytest.approx(-0.4 + 2.5, abs=1e-3)
    _, _, reward, _, info = env.step_env(jax.random.PRNGKey(1), state.replace(
        goal=state.position + 5 * offset), at_preload, params)  # 2 mm: outside, no bonus
    assert float(reward) == pytest.approx(-2.0, abs=1e-3)


def test_zero_order_hold_steps_the_plant_model_hz_over_control_hz_times():
    env, params = toy_env()
    assert env.steps_per_action == 5
    _, state = env.reset(jax.random.PRNGKey(0), params)
    pressure = jnp.array([5.0, 1.0, 1.0])
    _, state_after, *_ = env.step_env(jax.random.PRNGKey(1), state,
                                      env.pressure_to_action(pressure, params), params)
    _, expected = hold(env.plant, params.plant, state.plant_carry, pressure, 5)
    np.testing.assert_allclose(state_after.position, expected[-1], atol=1e-7)
    with pytest.raises(ValueError, match="integer multiple"):
        SoftArmReachEnv(linear_lag_plant(10.0), control_hz=3.0)


def test_keys_are_split_noise_draws_are_independent():
    env, params = toy_env(obs_noise_std_m=1e-3, action_noise_std_kpa=0.5)
    _, state = env.reset(jax.random.PRNGKey(0), params)
    step = jax.jit(env.step)
    a = step(jax.random.PRNGKey(1), state, jnp.zeros(3), params)
    b = step(jax.random.PRNGKey(1), state, jnp.zeros(3), params)
    c = step(jax.random.PRNGKey(2), state, jnp.zeros(3), params)
    np.testing.assert_array_equal(a[0], b[0])  # same key: reproducible
    assert not np.allclose(a[0], c[0])  # another key: other noise
    # observation noise and action noise are separate draws: the noisy position is not the
    # noise-free one displaced by a multiple of the action noise of the same numbers
    obs_noise = np.asarray(a[0][:3]) * np.asarray(params.obs_scale) + np.asarray(
        params.obs_mean) - np.asarray(a[1].position)
    assert np.linalg.norm(obs_noise) > 0
    pressures_noise = np.asarray(a[-1]["pressure"]) - 3.5
    assert not np.allclose(obs_noise / np.linalg.norm(obs_noise),
                           pressures_noise / np.linalg.norm(pressures_noise), atol=1e-3)


def test_last_action_in_the_observation():
    env, params = toy_env(include_last_action=True)
    obs, _ = env.reset(jax.random.PRNGKey(0), params)
    assert obs.shape == (9,)
    np.testing.assert_allclose(obs[6:], env.pressure_to_action(params.preload, params))


def test_scaled_error_in_the_observation():
    """The error block is (goal - position) / error_scale, in that order before the action."""
    env, params = toy_env(include_error=True, include_last_action=True, error_scale_m=0.002)
    obs, state = env.reset(jax.random.PRNGKey(3), params)
    assert obs.shape == (12,) == env.observation_space(params).shape
    error_mm = 1000.0 * np.asarray(state.goal - state.position)
    assert np.linalg.norm(error_mm) > 1.0  # the goals are mm away from the rest pose
    np.testing.assert_allclose(obs[6:9], error_mm / 2.0, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(obs[9:], env.pressure_to_action(params.preload, params))


def test_accumulated_error_in_the_observation_by_hand():
    """I_0 = 0, I_t = 0.75 I_(t-1) + 0.25 (goal - position_t) / 2 mm, between error and action."""
    env, params = toy_env(include_error=True, include_error_integral=True,
                          include_last_action=True, error_scale_m=0.002, error_integral_decay=0.75)
    obs, state = env.reset(jax.random.PRNGKey(3), params)
    assert obs.shape == (15,) == env.observation_space(params).shape
    np.testing.assert_array_equal(obs[9:12], np.zeros(3))
    expected = np.zeros(3)
    for action in ([1.0, -1.0, 0.0], [0.0, 0.5, -0.5]):
        obs, state, _, _, _ = env.step_env(jax.random.PRNGKey(1), state, jnp.array(action),
                                           params)
        error_units = 1000.0 * np.asarray(state.goal - state.position) / 2.0
        expected = 0.75 * expected + 0.25 * error_units
        np.testing.assert_allclose(obs[6:9], error_units, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(obs[9:12], expected, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(state.error_integral, expected, rtol=1e-4, atol=1e-5)
    assert np.abs(expected).max() > 0.1  # the goal is millimetres away: it accumulated
    # without the option the observation is what it was, the same numbers
    plain_env, plain_params = toy_env(include_error=True, include_last_action=True,
                                      error_scale_m=0.002)
    plain_obs, _ = plain_env.reset(jax.random.PRNGKey(3), plain_params)
    reset_obs, _ = env.reset(jax.random.PRNGKey(3), params)
    np.testing.assert_array_equal(plain_obs, np.concatenate([reset_obs[:9], reset_obs[12:]]))


def test_one_compiled_env_serves_a_batch_of_models():
    """vmap over EnvParams: two plants with different gains in one call."""
    env, params = toy_env()
    plant = default_linear_lag_params()
    stronger = make_env_params(
        env, plant.replace(gain=2 * plant.gain), EnvConfig(max_steps=5, reset_bank_size=4),
        key=jax.random.PRNGKey(0), safe_set=params.safe_set, preload=2.0, rest_pose=REST_POSE,
        goal_set=params.goal_set)
    both = jax.tree.map(lambda a, b: jnp.stack([a, b]), params, stronger)
    _, state = jax.vmap(env.reset, in_axes=(None, 0))(jax.random.PRNGKey(0), both)
    action = jnp.array([1.0, -1.0, -1.0])
    out = jax.vmap(env.step, in_axes=(None, 0, None, 0))(jax.random.PRNGKey(1), state, action,
                                                          both)
    moved = np.asarray(out[1].position - state.position)
    np.testing.assert_allclose(moved[1], 2 * moved[0], rtol=1e-4, atol=1e-7)


def test_learned_model_plant_runs_in_the_env():
    config = dynamics.DynamicsConfig(hidden=8)
    network = dynamics.init_network(jax.random.PRNGKey(0), config)
    ones, zeros = jnp.ones(3), jnp.zeros(3)
    normalizer = dynamics.Normalizer(2.0 * ones, ones, REST_POSE, 0.01 * ones, zeros,
                                     0.01 * ones)
    model = dynamics.DynamicsParams(network, normalizer, config)
    env = SoftArmReachEnv(learned_plant(10.0), 2.0, settle_seconds=1.0)
    params = make_env_params(env, model, EnvConfig(goal_mode=GoalMode.perturb, reset_bank_size=2),
                             key=jax.random.PRNGKey(0), safe_set=SafeSet.from_limits(LIMITS),
                             preload=2.0, rest_pose=REST_POSE)
    _, step, _, state = batched(env, params, num=4)
    out = step(jax.random.split(jax.random.PRNGKey(1), 4), state, jnp.zeros((4, 3)), params)
    assert np.all(np.isfinite(np.asarray(out[0])))


def test_simulated_arm_plant_reaches_by_feedback_and_rests_at_the_rest_pose(tmp_path):
    cfg = compose_config(tmp_path, "env=sim")
    plant_params = sim_plant_params(cfg.robot)
    env = SoftArmReachEnv(sim_plant(100.0, 10), 2.0, settle_seconds=1.0)
    rest = sim_rest_pose(plant_params)
    carry, position = env.settle(plant_params, rest + jnp.array([0.001, 0.0, 0.0]),
                                 plant_params.preload)
    np.testing.assert_allclose(position, rest + jnp.array([0.001, 0.0, 0.0]), atol=2e-5)
    # chamber 0 (at 90 degrees, +z) pressurised bends the arm towards -z
    _, positions = hold(env.plant, plant_params, carry, jnp.array([6.0, 2.0, 2.0]), 10)
    assert float(positions[-1, 2] - position[2]) < -0.005


def test_gymnax_observations_scaled_by_the_space_bounds():
    import gymnax

    from pipeline.rl.envs.factory import BoundsScaledObservation

    raw_env, params = gymnax.make("Pendulum-v1")
    env = BoundsScaledObservation(raw_env)
    np.testing.assert_allclose(env.observation_space(params).high, [1.0, 1.0, 1.0])
    key = jax.random.PRNGKey(3)
    raw_obs, raw_state = raw_env.reset(key, params)
    obs, state = env.reset(key, params)
    # Pendulum-v1: (cos, sin, angular velocity in [-8, 8]) -> velocity / 8
    np.testing.assert_allclose(obs, raw_obs / jnp.array([1.0, 1.0, 8.0]), rtol=1e-6)
    action = jnp.array([1.5])
    raw = raw_env.step(key, raw_state.replace(time=199), action, params)
    scaled = jax.jit(env.step)(key, state.replace(time=199), action, params)
    assert bool(scaled[4])  # truncated at 200 steps: the observation is the reset one
    np.testing.assert_allclose(scaled[0], raw[0] / jnp.array([1.0, 1.0, 8.0]), rtol=1e-6)
    np.testing.assert_allclose(scaled[5]["final_observation"],
                               raw[5]["final_observation"] / jnp.array([1.0, 1.0, 8.0]),
                               rtol=1e-6)
    np.testing.assert_allclose(scaled[2], raw[2])
