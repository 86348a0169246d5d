"""Robustness to model error: ensemble environments, randomization around the plant and
incremental actions.

Known answers on the linear-lag toy (``position = offset + G @ lagged``, ``lagged`` a first-order
lag of the received pressure with factor 1/2 per plant step, five plant steps per period), the
defaults unchanged to float rounding, the config and keys, and a shrunk train_ppo in an ensemble.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from omegaconf import OmegaConf

from pipeline import chain, keys
from pipeline.__main__ import run
from pipeline.arm.safety import SafeSet, project
from pipeline.dynamics import model as dynamics
from pipeline.rl.envs import (
    SoftArmReachEnv,
    default_linear_lag_params,
    ensemble_plant,
    hold,
    learned_plant,
    linear_lag_plant,
    make_env_params,
    randomization,
    stack_members,
)
from pipeline.rl.envs import observation as observation_module
from pipeline.schemas import ConfigError, EnvConfig
from pipeline.validation import validate_config

LIMITS = OmegaConf.create({"p_min": 0.0, "p_max": 7.0, "sum_max": 13.0, "preload": 2.0})
REST_POSE = jnp.array([0.032, 0.353, 0.202])
GOALS = REST_POSE + jnp.array([[0.005, 0.0, 0.0], [0.0, 0.0, -0.005], [-0.004, 0.0, 0.003]])
PRELOAD = jnp.full(3, 2.0)
ENV_FIELDS = {f.name for f in dataclasses.fields(EnvConfig)}


def toy(plant=None, plant_params=None, **overrides):
    """Linear lag at 10 Hz, 2 Hz control (5 plant steps per period)."""
    env = SoftArmReachEnv(plant or linear_lag_plant(10.0), control_hz=2.0, settle_seconds=2.0,
                          include_last_action=True, include_error=True)
    settings = {"safe_set": SafeSet.from_limits(LIMITS), "preload": 2.0, "rest_pose": REST_POSE,
                "goal_set": GOALS, "max_steps": 5, "reset_bank_size": 4}
    settings.update(overrides)
    params = make_env_params(env, plant_params or default_linear_lag_params(),
                             EnvConfig(**{k: settings.pop(k) for k in list(settings) if k in ENV_FIELDS}),
                             key=jax.random.PRNGKey(0), **settings)
    return env, params


@functools.partial(jax.jit, static_argnums=(0, 4))
def hold_command(env, params, state, pressure, periods=1):
    """Step ``periods`` control periods commanding ``pressure [3]`` kPa; the last state (one
    compiled program: the env's steps scanned, period ``k`` with ``PRNGKey(50 + k)``)."""
    action = env.pressure_to_action(jnp.asarray(pressure, jnp.float32), params)
    keys = jax.vmap(jax.random.PRNGKey)(50 + jnp.arange(periods))

    def one_period(state, key):
        return env.step_env(key, state, action, params)[1], None

    return jax.lax.scan(one_period, state, keys)[0]


# ---- defaults ---------------------------------------------------------------------------------
def nominal_reset(env, key, params):
    """The reset as it was before randomization existed (a reference written out)."""
    index_key, perturb_key, obs_key = jax.random.split(key, 3)
    bank, goal_index = jax.random.randint(index_key, (2,), 0, jnp.array(
        [params.reset_positions.shape[0], params.goal_set.shape[0]]))
    position = params.reset_positions[bank]
    perturbed = position + params.goal_perturbation_m * jax.random.normal(perturb_key, (3,))
    goal = jnp.where(params.goal_from_data, params.goal_set[goal_index], perturbed)
    carry = jax.tree.map(lambda leaf: leaf[bank], params.reset_carries)
    return carry, position, goal, obs_key


def nominal_step(env, key, carry, position, goal, last, action, params):
    """The step as it was before randomization existed: noise, projection, zero-order hold."""
    noise_key, obs_key = jax.random.split(key)
    pressure = env.pressure_command(action, params) + params.action_noise_std_kpa * jax.random.normal(
        noise_key, (3,))
    pressure = project(pressure, params.safe_set)
    carry, positions = hold(env.plant, params.plant, carry, pressure, env.steps_per_action)
    return carry, positions[-1], pressure, obs_key


def nominal_obs(key, position, goal, last, params):
    measured = position + params.obs_noise_std_m * jax.random.normal(key, (3,))
    return observation_module.observe(measured, goal, last, params, include_error=True,
                                      include_last_action=True)


def random_lstm(seed=0, hidden=8):
    config = dynamics.DynamicsConfig(hidden=hidden, step_size=True, step_decays=(1.0, 3.0))
    ones, zeros = jnp.ones(3), jnp.zeros(3)
    normalizer = dynamics.Normalizer(2.0 * ones, ones, REST_POSE, 0.01 * ones, zeros,
                                     0.01 * ones)
    return dynamics.DynamicsParams(dynamics.init_network(jax.random.PRNGKey(seed), config),
                                   normalizer, config)


@pytest.mark.parametrize("kind", ["linear_lag", "lstm"])
def test_default_env_is_the_nominal_plant_to_float_rounding(kind):
    plant, plant_params = None, None
    if kind == "lstm":
        plant, plant_params = learned_plant(10.0), random_lstm()
    env, params = toy(plant, plant_params, rest_pose_std=0.001, obs_noise_std_m=1e-4,
                      action_noise_std_kpa=0.3, reset_bank_size=8)
    reset, step = jax.jit(env.reset_env), jax.jit(env.step_env)
    # the reference compiled too (XLA's fusions may differ from op-by-op rounding by an ulp; the
    # suite's older CPU emitters, conftest.py, fuse the two programs apart by a few): any draw
    # of the randomization would move them by orders of magnitude more
    reference_reset = jax.jit(functools.partial(nominal_reset, env))
    reference_step = jax.jit(functools.partial(nominal_step, env))
    reference_obs = jax.jit(nominal_obs)
    def same(actual, expected):
        np.testing.assert_allclose(actual, expected, rtol=1e-6, atol=1e-6)

    for episode in range(3):
        key = jax.random.PRNGKey(episode)
        obs, state = reset(key, params)
        carry, position, goal, obs_key = reference_reset(key, params)
        same(obs, reference_obs(obs_key, position, goal, PRELOAD,
                                                         params))
        same(state.position, position)
        last = PRELOAD
        for t in range(6):
            step_key = jax.random.PRNGKey(100 * episode + t)
            action = jax.random.uniform(jax.random.PRNGKey(7 + t), (3,), minval=-1, maxval=1)
            obs, state, reward, _, info = step(step_key, state, action, params)
            carry, position, last, obs_key = reference_step(step_key, carry, position, goal,
                                                            last, action, params)
            same(state.position, position)
            same(info["pressure"], last)
            same(reward, -1000.0 * jnp.linalg.norm(goal - position))
            same(obs, reference_obs(obs_key, position, goal, last,
                                                             params))
            for a, b in zip(jax.tree.leaves(state.plant_carry), jax.tree.leaves(carry)):
                same(a, b)


def test_default_randomization_draws_the_nominal_plant():
    env, params = toy()
    _, state = jax.vmap(env.reset_env, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(0), 64), params)
    perturbation = state.perturbation
    assert np.all(np.asarray(perturbation.gain) == 1.0)
    assert np.all(np.asarray(perturbation.offset) == 0.0)
    assert np.all(np.asarray(perturbation.delay) == 0)
    assert np.all(np.asarray(perturbation.rest_offset) == 0.0)
    assert np.all(np.asarray(perturbation.drift) == 0.0)
    assert np.all(np.asarray(perturbation.saturation) == 0.0)


# ---- randomization: known answers -------------------------------------------------------------
def settled_state(env, params):
    """An episode from bank entry 0 (the toy rests exactly at REST_POSE at the preload)."""
    _, state = env.reset_env(jax.random.PRNGKey(0), params)
    return state


def test_gain_and_offset_shift_the_settled_position_by_the_plant_gain():
    env, params = toy()
    gain_matrix = default_linear_lag_params().gain
    state = settled_state(env, params)
    command = jnp.array([4.0, 2.5, 3.0])  # inside the safe set, also after gain and offset
    gain, offset = jnp.array([1.1, 0.8, 1.0]), jnp.array([0.3, -0.2, 0.5])
    nominal = hold_command(env, params, state, command, periods=12)
    perturbed_state = state.replace(perturbation=state.perturbation.replace(gain=gain,
                                                                              offset=offset))
    perturbed = hold_command(env, params, perturbed_state, command, periods=12)
    # 60 plant steps of a 1/2 lag: settled to float precision
    np.testing.assert_allclose(nominal.position, state.position + gain_matrix @ (command - 2.0),
                               atol=1e-7)
    np.testing.assert_allclose(perturbed.position - nominal.position,
                               gain_matrix @ ((gain - 1.0) * command + offset), atol=1e-7)
    # the policy sees the command it sent, the plant got the perturbed one
    np.testing.assert_allclose(perturbed.last_pressure, command, atol=1e-6)
    np.testing.assert_allclose(perturbed.perturbation.received, gain * command + offset,
                               atol=1e-6)


def test_perturbed_commands_stay_inside_the_safe_set():
    env, params = toy(randomization_params=randomization(gain_std=0.5, offset_std_kpa=3.0))
    _, state = jax.vmap(env.reset_env, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(0), 256), params)
    step = jax.vmap(env.step_env, in_axes=(0, 0, 0, None))
    actions = jnp.ones((256, 3)).at[:128].set(-1.0)
    _, state, *_ = step(jax.random.split(jax.random.PRNGKey(1), 256), state, actions, params)
    received = np.asarray(state.perturbation.received)
    assert received.min() >= 0.0 and received.max() <= 7.0
    assert received.sum(axis=1).max() <= 13.0
    assert received[128:].std(axis=0).min() > 0.1  # the randomization does act


@pytest.mark.parametrize("delay", [0, 1, 2, 3, 4, 5])
def test_a_delay_of_d_steps_holds_the_previous_command_for_d_steps(delay):
    env, params = toy()
    gain_matrix = default_linear_lag_params().gain
    state = settled_state(env, params)
    state = state.replace(perturbation=state.perturbation.replace(delay=jnp.int32(delay)))
    command = jnp.array([5.0, 1.0, 3.0])
    after = hold_command(env, params, state, command)
    # the preload for d steps (the lag stays settled), the command for 5 - d: a lag of
    # (command - preload) (1 - 2^-(5 - d))
    expected = state.position + gain_matrix @ ((command - 2.0) * (1.0 - 0.5 ** (5 - delay)))
    np.testing.assert_allclose(after.position, expected, atol=1e-7)
    np.testing.assert_allclose(after.perturbation.received, command, atol=1e-6)


def test_delays_are_drawn_uniformly_up_to_one_period():
    env, params = toy(randomization_params=randomization(max_delay_steps=99))
    _, state = jax.vmap(env.reset_env, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(0), 3000), params)
    counts = np.bincount(np.asarray(state.perturbation.delay), minlength=6)
    assert len(counts) == 6  # capped at steps_per_action = 5
    np.testing.assert_allclose(counts / 3000, 1 / 6, atol=0.03)


def test_rest_offset_and_drift_shift_the_position():
    env, params = toy()
    state = settled_state(env, params)
    rest, drift = jnp.array([0.002, -0.001, 0.0005]), jnp.array([1e-4, 0.0, -2e-4])
    shifted = state.replace(perturbation=state.perturbation.replace(rest_offset=rest,
                                                                      drift=drift))
    nominal = hold_command(env, params, state, PRELOAD, periods=4)
    after = hold_command(env, params, shifted, PRELOAD, periods=4)
    np.testing.assert_allclose(after.position - nominal.position, rest + drift * 4 / 2.0,
                               atol=1e-7)  # 4 periods at 2 Hz: 2 s; float32 at 0.35 m: 3e-8


def test_saturating_chambers_get_the_command_pulled_toward_the_preload():
    env, params = toy()
    gain_matrix = default_linear_lag_params().gain
    state = settled_state(env, params)
    command = jnp.array([5.0, 1.0, 3.0])
    saturated = state.replace(perturbation=state.perturbation.replace(saturation=jnp.float32(0.5)))
    after = hold_command(env, params, saturated, command, periods=12)
    # 2 + tanh(0.5 (p - 2)) / 0.5: 2 + tanh(1.5) / 0.5, 2 - tanh(0.5) / 0.5, 2 + tanh(0.5) / 0.5
    received = np.array([3.810296, 1.075766, 2.924234])
    np.testing.assert_allclose(after.perturbation.received, received, atol=1e-5)
    np.testing.assert_allclose(after.position, state.position + gain_matrix @ (received - 2.0),
                               atol=1e-6)
    np.testing.assert_allclose(after.last_pressure, command, atol=1e-6)  # what the policy sent
    # none (0): the command as sent (test_default_env_is_the_nominal_plant_to_float_rounding)
    nominal = hold_command(env, params, state, command, periods=1)
    np.testing.assert_allclose(nominal.perturbation.received, command, atol=1e-6)


def test_saturation_is_drawn_uniformly_up_to_its_bound():
    env, params = toy(randomization_params=randomization(saturation_max_per_kpa=1.5))
    _, state = jax.vmap(env.reset_env, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(0), 4000), params)
    drawn = np.asarray(state.perturbation.saturation)
    assert drawn.min() >= 0.0 and drawn.max() <= 1.5
    np.testing.assert_allclose(drawn.mean(), 0.75, atol=0.03)  # U(0, 1.5): std 0.43 / sqrt(4000)
    np.testing.assert_allclose(np.histogram(drawn, bins=3, range=(0, 1.5))[0] / 4000, 1 / 3,
                               atol=0.03)
    # the randomization's other draws are as without it
    _, plain = jax.vmap(env.reset_env, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(0), 4000), toy()[1])
    np.testing.assert_array_equal(state.position, plain.position)
    with pytest.raises(ValueError, match="saturation_max_per_kpa must be finite and >= 0"):
        randomization(saturation_max_per_kpa=-0.1)


def test_randomization_draws_have_their_magnitudes():
    spread = randomization(gain_std=0.1, offset_std_kpa=0.4, rest_offset_std_m=0.002,
                           drift_std_m_per_s=1e-4)
    env, params = toy(randomization_params=spread)
    _, state = jax.vmap(env.reset_env, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(0), 4000), params)
    perturbation = jax.tree.map(np.asarray, state.perturbation)
    np.testing.assert_allclose(perturbation.gain.mean(axis=0), 1.0, atol=0.01)
    np.testing.assert_allclose(perturbation.gain.std(axis=0), 0.1, rtol=0.06)
    np.testing.assert_allclose(perturbation.offset.std(axis=0), 0.4, rtol=0.06)
    np.testing.assert_allclose(perturbation.drift.std(axis=0), 1e-4, rtol=0.06)
    # the start is the bank's pose shifted by the rest offset (the toy's bank: all at REST_POSE)
    np.testing.assert_allclose(np.asarray(state.position) - np.asarray(REST_POSE),
                               perturbation.rest_offset, atol=1e-7)
    np.testing.assert_allclose(perturbation.rest_offset.std(axis=0), 0.002, rtol=0.06)
    # one key per draw: the draws are not the same numbers scaled
    assert abs(np.corrcoef(perturbation.gain[:, 0], perturbation.offset[:, 0])[0, 1]) < 0.1


# ---- ensembles --------------------------------------------------------------------------------
def two_gains():
    """Two linear plants, the second with twice the first's gain."""
    plant = default_linear_lag_params()
    return [plant, plant.replace(gain=2.0 * plant.gain)]


@pytest.mark.parametrize("selection", ["gather", "all"])
def test_even_and_odd_bank_entries_follow_members_zero_and_one(selection):
    members = two_gains()
    env, params = toy(ensemble_plant(linear_lag_plant(10.0), selection), stack_members(members))
    np.testing.assert_array_equal(params.reset_carries.member, [0, 1, 0, 1])
    gain_matrix = members[0].gain
    command = jnp.array([5.0, 1.0, 3.0])

    @jax.jit
    @jax.vmap
    def moved(entry):  # one compiled program for the four bank entries
        carry = jax.tree.map(lambda leaf: leaf[entry], params.reset_carries)
        state = env.start_state(jax.random.PRNGKey(entry), carry,
                                params.reset_positions[entry], GOALS[0], params)
        return hold_command(env, params, state, command, periods=12).position - state.position

    expected = [(1 + entry % 2) * gain_matrix @ (command - 2.0) for entry in range(4)]
    np.testing.assert_allclose(moved(jnp.arange(4)), np.stack(expected), atol=1e-7)


def test_members_are_drawn_about_uniformly():
    env, params = toy(ensemble_plant(linear_lag_plant(10.0)), stack_members(two_gains()))
    _, state = jax.vmap(env.reset_env, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(0), 4000), params)
    assert abs(float(np.mean(state.plant_carry.member)) - 0.5) < 0.03


def test_an_ensemble_member_steps_exactly_as_the_model_alone():
    """Both selections agree with the member run on its own (LSTMs with step features)."""
    models = [random_lstm(0), random_lstm(1), random_lstm(2)]
    pressures = jax.random.uniform(jax.random.PRNGKey(3), (7, 3), minval=0.0, maxval=4.0)
    alone = learned_plant(10.0)
    for selection in ("gather", "all"):
        plant = ensemble_plant(alone, selection)
        stacked = stack_members(models)
        for index, model in enumerate(models):
            carry = plant.init_carry(stacked.replace(member=jnp.int32(index)), REST_POSE)
            reference = alone.init_carry(model, REST_POSE)
            for pressure in pressures:
                carry, position = plant.step(stacked, carry, pressure)
                reference, expected = alone.step(model, reference, pressure)
                np.testing.assert_allclose(position, expected, rtol=1e-6, atol=1e-7)
            assert int(carry.member) == index


def test_members_of_different_architectures_are_refused():
    with pytest.raises(ValueError, match="one structure"):
        stack_members([random_lstm(0, hidden=8), random_lstm(0, hidden=4)])


# ---- config and keys --------------------------------------------------------------------------
def test_every_env_setting_is_in_the_keys_with_its_value(make_cfg):
    cfg = make_cfg("experiment=quick")
    spec, inputs = keys.train_ppo_spec(cfg)
    assert spec["spec_version"] == keys.SPEC_VERSIONS["train_ppo"]
    assert spec["env"]["ensemble_seeds"] == 1 and set(spec["env"]["randomization"])
    assert "models" not in spec["env"]  # where further models lie is not part of the key
    assert set(inputs) == {"fit_model"}
    assert chain.ensemble_configs(cfg) == [] and keys.ensemble_entries(cfg) == {}
    # zero magnitudes spelled out are the default
    zero = make_cfg("experiment=quick", "env.randomization.gain_std=0.0", "env.ensemble_seeds=1")
    assert keys.key("train_ppo", zero) == keys.key("train_ppo", cfg)


def test_ensemble_and_randomization_are_part_of_the_train_ppo_key(make_cfg):
    base = make_cfg("experiment=quick")
    ensemble = make_cfg("experiment=quick", "env.ensemble_seeds=3")
    _, inputs = keys.train_ppo_spec(ensemble)
    seeds = [member.model.seed for member in chain.ensemble_configs(ensemble)]
    assert seeds == [1, 2] and base.model.seed == 0
    assert inputs["fit_model/seed+1"] == keys.key("fit_model", make_cfg("experiment=quick",
                                                                        "model.seed=1"))
    assert inputs["fit_model/seed+2"] == keys.key("fit_model", make_cfg("experiment=quick",
                                                                        "model.seed=2"))
    assert keys.key("fit_model", ensemble) == keys.key("fit_model", base)
    assert keys.key("train_ppo", ensemble) != keys.key("train_ppo", base)
    randomized = make_cfg("experiment=quick", "env.randomization.max_delay_s=0.2")
    spec, _ = keys.train_ppo_spec(randomized)
    assert {k: v for k, v in spec["env"]["randomization"].items() if v} == {"max_delay_s": 0.2}
    assert keys.key("train_ppo", randomized) != keys.key("train_ppo", base)
    other = make_cfg("experiment=quick", "env.models=[/somewhere/fit_model/abc123def456]")
    assert keys.ensemble_entries(other) == {
        "fit_model/abc123def456": "/somewhere/fit_model/abc123def456"}
    assert keys.train_ppo_spec(other)[1]["fit_model/abc123def456"] == "abc123def456"


@pytest.mark.parametrize("overrides, message", [
    (["env=sim", "env.ensemble_seeds=2"], "needs env=learned"),
    (["env.ensemble_seeds=0"], "must be >= 1"),
    (["env.randomization.max_delay_s=0.6"], "at most one control period"),
    (["env.randomization.gain_std=-0.1"], "must be finite and >= 0"),
    (["env=gymnax", "env.randomization.gain_std=0.1"], "no plant"),
    (["env.action_mode=incremental", "env.action_step_kpa=0"], "action_step_kpa=0.0 must be"),
])
def test_unusable_robustness_settings_are_refused(make_cfg, overrides, message):
    with pytest.raises(ConfigError, match=message):
        validate_config(make_cfg(*overrides))


def test_robustness_settings_compose_and_validate(make_cfg):
    cfg = make_cfg("env.ensemble_seeds=3", "env.models=[a,b]", "env.randomization.gain_std=0.05",
                   "env.randomization.offset_std_kpa=0.2", "env.randomization.max_delay_s=0.5",
                   "env.randomization.rest_offset_std_m=0.001",
                   "env.randomization.drift_std_m_per_s=1e-5")
    validate_config(cfg)
    validate_config(make_cfg("env=sim", "env.randomization.rest_offset_std_m=0.001"))
    assert OmegaConf.to_container(cfg.env.randomization)["max_delay_s"] == 0.5


# ---- the stage --------------------------------------------------------------------------------
SHRUNK = ["experiment=quick", "robot.num_runs=2", "exploration.num_steps=30",
          "model.num_steps=20", "model.eval_every=10", "model.checkpoint_every=10",
          "dataset.window=16", "dataset.train_fraction=0.5", "agent.num_seeds=1",
          "agent.num_envs=16", "agent.num_steps=8", "agent.total_timesteps=256",
          "agent.num_evals=1", "agent.eval_envs=4", "env.reset_bank_size=3",
          "env.goal_every=4", "stage=train_ppo"]


@pytest.mark.slow  # a minute; the members, the bank and the draws are checked one by one above
def test_train_ppo_in_an_ensemble_of_two_model_seeds_with_randomization(make_cfg):
    cfg = make_cfg(*SHRUNK, "env.ensemble_seeds=2", "env.randomization.gain_std=0.05",
                   "env.randomization.max_delay_s=0.2")
    results = run(cfg)  # collect, align, both fit_model seeds, train_ppo
    assert list(results) == ["collect", "align", "fit_model", "train_ppo"]
    artifact = results["train_ppo"]
    inputs = artifact.manifest["inputs"]
    assert set(inputs) == {"fit_model", "fit_model/seed+1"}
    fitted = sorted(p.name for p in (artifact.path.parent.parent / "fit_model").glob("[!.]*"))
    assert fitted == sorted([inputs["fit_model"], inputs["fit_model/seed+1"]])
    assert inputs["fit_model"] != inputs["fit_model/seed+1"]
    assert artifact.manifest["summary"]["env"] == "SoftArmReach-learned_ensemble"
    assert artifact.file("policy.msgpack").is_file()


# ---------------------------------------------------------------------------------------------
# incremental actions
# ---------------------------------------------------------------------------------------------
def incremental_toy(step_kpa=0.5, **overrides):
    env = SoftArmReachEnv(linear_lag_plant(10.0), control_hz=2.0, settle_seconds=2.0,
                          include_last_action=True, include_error=True,
                          incremental_actions=True)
    settings = {"safe_set": SafeSet.from_limits(LIMITS), "preload": 2.0, "rest_pose": REST_POSE,
                "goal_set": GOALS, "max_steps": 5, "reset_bank_size": 4,
                "action_step_kpa": step_kpa}
    settings.update(overrides)
    return env, make_env_params(env, default_linear_lag_params(),
                                EnvConfig(**{k: settings.pop(k) for k in list(settings) if k in ENV_FIELDS}),
                                key=jax.random.PRNGKey(0), **settings)


def test_incremental_actions_change_the_last_command_by_hand():
    env, params = incremental_toy(step_kpa=0.5)
    _, state = env.reset(jax.random.PRNGKey(1), params)
    np.testing.assert_allclose(state.last_pressure, [2.0, 2.0, 2.0])
    # 2 + 0.5 * [1, -0.5, 0] = [2.5, 1.75, 2.0]; then 2.5 + 0.5 * 1 = 3.0, clipped actions
    _, state, *_ = env.step_env(jax.random.PRNGKey(2), state, jnp.array([1.0, -0.5, 0.0]),
                                params)
    np.testing.assert_allclose(state.last_pressure, [2.5, 1.75, 2.0], atol=1e-6)
    _, state, *_ = env.step_env(jax.random.PRNGKey(3), state, jnp.array([4.0, 0.0, -1.0]),
                                params)
    np.testing.assert_allclose(state.last_pressure, [3.0, 1.75, 1.5], atol=1e-6)
    # action zero holds the command: the position settles where holding 3, 1.75, 1.5 kPa does
    held = state
    for period in range(6):
        _, held, *_ = env.step_env(jax.random.PRNGKey(10 + period), held, jnp.zeros(3), params)
    np.testing.assert_allclose(held.last_pressure, [3.0, 1.75, 1.5], atol=1e-6)
    absolute, absolute_params = toy()
    _, reference = absolute.reset(jax.random.PRNGKey(1), absolute_params)
    reference = hold_command(absolute, absolute_params, reference, [3.0, 1.75, 1.5], periods=8)
    np.testing.assert_allclose(held.position, reference.position, atol=1e-5)


def test_incremental_commands_stay_inside_the_safe_set():
    env, params = incremental_toy(step_kpa=5.0)
    _, state = env.reset(jax.random.PRNGKey(1), params)
    for period in range(4):  # push every valve up: each at most p_max, the sum at most sum_max
        _, state, *_ = env.step_env(jax.random.PRNGKey(period), state, jnp.ones(3), params)
    assert float(state.last_pressure.max()) <= 7.0 + 1e-5
    assert float(state.last_pressure.sum()) <= 13.0 + 1e-4
    for period in range(4):
        _, state, *_ = env.step_env(jax.random.PRNGKey(period), state, -jnp.ones(3), params)
    np.testing.assert_allclose(state.last_pressure, [0.0, 0.0, 0.0], atol=1e-6)


@pytest.mark.parametrize("incremental", [False, True])
def test_action_for_inverts_the_command(incremental):
    env, params = incremental_toy() if incremental else toy()
    last = jnp.array([2.0, 3.0, 1.0])
    target = jnp.array([2.3, 2.8, 1.0])  # within one step of the last command
    action = env.action_for(target, last, params)
    np.testing.assert_allclose(env.command(action, last, params), target, atol=1e-6)
    if incremental:  # farther than one step: the largest step towards it
        far = env.action_for(jnp.array([5.0, 3.0, 0.0]), last, params)
        np.testing.assert_allclose(far, [1.0, 0.0, -1.0], atol=1e-6)


def test_incremental_actions_are_part_of_the_keys_and_reach_the_environment(make_cfg):
    from pipeline.rl.envs.factory import observation_options
    from pipeline.rl.envs.params import setting_values
    from pipeline.stages._environment import env_settings

    base = make_cfg("experiment=quick")
    assert keys.train_ppo_spec(base)[0]["env"]["action_mode"] == "absolute"
    # the incremental step is unused by absolute actions: not part of their key
    spelled = make_cfg("experiment=quick", "env.action_mode=absolute", "env.action_step_kpa=3")
    assert keys.key("train_ppo", spelled) == keys.key("train_ppo", base)
    incremental = make_cfg("experiment=quick", "env.action_mode=incremental")
    wider = make_cfg("experiment=quick", "env.action_mode=incremental", "env.action_step_kpa=2")
    assert len({keys.key("train_ppo", c) for c in (base, incremental, wider)}) == 3
    assert observation_options(env_settings(wider))["incremental_actions"] is True
    assert float(setting_values(env_settings(wider))["action_step_kpa"]) == 2.0
    assert observation_options(env_settings(base))["incremental_actions"] is False


def test_the_command_change_costs_its_price_in_the_reward_by_hand():
    """Incremental steps of 0.5 kPa at cost 2 mm/kPa: action [1, -0.5, 0] changes the command by
    0.5 + 0.25 + 0 = 0.75 kPa, 1.5 mm off the reward; holding it costs nothing."""
    env, params = incremental_toy(step_kpa=0.5, command_change_cost_mm_per_kpa=2.0)
    _, state = env.reset(jax.random.PRNGKey(1), params)
    goal = state.goal
    _, moved, reward, _, info = env.step_env(jax.random.PRNGKey(2), state,
                                             jnp.array([1.0, -0.5, 0.0]), params)
    distance_mm = 1000.0 * float(jnp.linalg.norm(goal - moved.position))
    assert float(reward) == pytest.approx(-distance_mm - 2.0 * 0.75, rel=1e-5)
    assert float(info["distance_m"]) * 1000.0 == pytest.approx(distance_mm, rel=1e-5)
    _, held, reward, _, _ = env.step_env(jax.random.PRNGKey(3), moved, jnp.zeros(3), params)
    assert float(reward) == pytest.approx(
        -1000.0 * float(jnp.linalg.norm(goal - held.position)), rel=1e-5)


def test_a_negative_command_change_cost_is_refused(make_cfg):
    with pytest.raises(ConfigError,
                       match=r"env.command_change_cost_mm_per_kpa=-1.0 must be finite and >= 0"):
        validate_config(make_cfg("env.command_change_cost_mm_per_kpa=-1"))


@pytest.mark.parametrize("overrides, message", [
    (["env.hold_periods=0"], r"env.hold_periods=0 must be an integer >= 1"),
    (["env.hold_periods=41"], r"env.hold_periods=41 must be at most env.max_steps=40"),
    (["env.hold_bonus_mm=-1"], r"env.hold_bonus_mm=-1.0 must be finite and >= 0"),
])
def test_unusable_hold_settings_are_refused(make_cfg, overrides, message):
    with pytest.raises(ConfigError, match=message):
        validate_config(make_cfg(*overrides))


def test_hold_settings_reach_the_env_and_the_key_only_where_set(make_cfg):
    from pipeline.rl.envs.params import setting_values
    from pipeline.stages._environment import env_settings

    base = make_cfg()
    assert keys.key("train_ppo", make_cfg("env.hold_periods=1", "env.hold_bonus_mm=0")) == \
        keys.key("train_ppo", base)  # the defaults spelled out are the defaults
    held = make_cfg("env.hold_periods=5", "env.hold_bonus_mm=2")
    validate_config(held)
    assert keys.train_ppo_spec(held)[0]["env"]["hold_periods"] == 5
    assert keys.key("train_ppo", held) != keys.key("train_ppo", base)
    values = setting_values(env_settings(held))
    assert (int(values["hold_periods"]), float(values["hold_bonus_mm"])) == (5, 2.0)


@pytest.mark.parametrize("decay", ["1.0", "-0.1"])
def test_an_accumulated_error_decay_outside_0_1_is_refused(make_cfg, decay):
    with pytest.raises(ConfigError, match=rf"env.error_integral_decay={float(decay)} must lie in"):
        validate_config(make_cfg(f"env.error_integral_decay={decay}"))


def test_training_evaluations_run_the_whole_horizon_and_score_its_end():
    """A random actor-critic on the toy (episodes of 5 steps): whatever the goal tolerance, every
    episode runs its 5 steps to the same end, and it succeeded exactly where that end is within
    the tolerance (here halfway between the nearest and the farthest end: some of them)."""
    from pipeline.rl.evaluation import evaluate_policy
    from pipeline.rl.networks import ActorCriticFF

    env, params = toy()
    network = ActorCriticFF(action_dim=3, width=8, num_layers=1)
    weights = network.init(jax.random.PRNGKey(0), jnp.zeros((1, 1)),
                           jnp.zeros((1, env.obs_dim)), jnp.zeros((1,), bool))

    def evaluate(tolerance):
        return evaluate_policy(env, params.replace(goal_tolerance_m=jnp.float32(tolerance)),
                               network, weights, jax.random.PRNGKey(3), num_envs=16,
                               num_steps=5, has_distance=True)

    final = np.asarray(evaluate(1e-6)["episode_final_distance_m"])
    tolerance = float(final.min() + final.max()) / 2
    out = evaluate(tolerance)
    assert bool(out["episode_finished"].all())
    np.testing.assert_array_equal(np.asarray(out["episode_final_distance_m"]), final)
    np.testing.assert_array_equal(np.asarray(out["episode_success"]), final <= tolerance)
    assert 0 < float(out["success_rate"]) < 1
    assert float(evaluate(1.0)["success_rate"]) == 1.0  # within a metre of every goal


# ---------------------------------------------------------------------------------------------
# conservative goals
# ---------------------------------------------------------------------------------------------
def test_conservative_goals_keep_the_agreed_ones_and_every_held_out_one():
    """Spreads 0.5, 2, 0.9, 3, 0.1 mm at 1 mm: rows 0, 2 and 4 agree; row 3 is held out and
    stays; row 1 goes."""
    import pandas as pd

    from pipeline.rl.envs.factory import conservative_goals

    goals = pd.DataFrame({"run_id": list("aabbb"), "x": np.arange(5.0), "y": 0.0, "z": 0.0})
    spread = np.array([0.5, 2.0, 0.9, 3.0, 0.1]) * 1e-3
    held_out = np.array([False, False, False, True, False])
    kept = conservative_goals(goals, spread, 1e-3, held_out)
    assert kept["x"].tolist() == [0.0, 2.0, 3.0, 4.0]
    assert conservative_goals(goals, spread, 1e-3)["x"].tolist() == [0.0, 2.0, 4.0]
    with pytest.raises(ConfigError, match=r"goal_agreement_mm=0.05: .* none of the 4 training"):
        conservative_goals(goals, spread, 5e-5, held_out)


def test_prediction_spread_is_the_largest_distance_to_the_first_models_prediction():
    from pipeline.dynamics.scoring import predict_run
    from pipeline.rl.envs.factory import prediction_spread
    from tests.test_dynamics import CONFIGS, make_params, make_runs

    run = make_runs(num_runs=1)[0]
    first, second, third = (make_params(CONFIGS[0], seed) for seed in (0, 1, 2))
    np.testing.assert_array_equal(prediction_spread([first], run), 0.0)
    np.testing.assert_array_equal(prediction_spread([first, first], run), 0.0)
    reference = predict_run(first, run)
    by_hand = np.maximum(np.linalg.norm(predict_run(second, run) - reference, axis=-1),
                         np.linalg.norm(predict_run(third, run) - reference, axis=-1))
    spread = prediction_spread([first, second, third], run)
    assert spread.shape == (len(run),) and spread.max() > 0
    np.testing.assert_allclose(spread, by_hand, rtol=1e-6)


@pytest.mark.parametrize("overrides, message", [
    (["env.goal_agreement_mm=1.0"], "needs one"),
    (["env.ensemble_seeds=3", "env.goal_agreement_mm=0"], "must be finite and > 0"),
])
def test_conservative_goals_need_an_ensemble_and_a_positive_agreement(make_cfg, overrides,
                                                                      message):
    with pytest.raises(ConfigError, match=message):
        validate_config(make_cfg(*overrides))


def test_conservative_goals_are_part_of_the_key(make_cfg):
    base = make_cfg("experiment=quick", "env.ensemble_seeds=2")
    agreed = make_cfg("experiment=quick", "env.ensemble_seeds=2", "env.goal_agreement_mm=1.0")
    validate_config(agreed)
    assert keys.train_ppo_spec(base)[0]["env"]["goal_agreement_mm"] is None
    assert keys.key("train_ppo", agreed) != keys.key("train_ppo", base)


# ---------------------------------------------------------------------------------------------
# goals redrawn within an episode
# ---------------------------------------------------------------------------------------------
def test_a_goal_is_redrawn_every_k_periods_as_at_a_reset_by_hand():
    """k = 2, goal_mode=perturb (1 cm): the goal of periods 1-2 is the reset's; after period 2
    it is the position then plus 1 cm x N(0, 1) drawn from fold_in(step key, 2), and the count
    of periods at the goal starts again; period 3 keeps it."""
    env, params = toy(goal_mode="perturb", goal_redraw_periods=2, hold_periods=5,
                      goal_tolerance_m=1.0)  # every period at the goal: the count shows it
    _, state = env.reset(jax.random.PRNGKey(1), params)
    first_goal = state.goal
    keys = jax.random.split(jax.random.PRNGKey(2), 3)
    _, one, _, _, _ = env.step_env(keys[0], state, jnp.zeros(3), params)
    np.testing.assert_array_equal(one.goal, first_goal)
    assert int(one.periods_within) == 1
    _, two, reward, _, info = env.step_env(keys[1], one, jnp.zeros(3), params)
    # the period's reward is the old goal's distance
    assert float(reward) == pytest.approx(-1000.0 * float(info["distance_m"]), rel=1e-6)
    assert float(info["distance_m"]) == pytest.approx(
        float(jnp.linalg.norm(first_goal - two.position)), rel=1e-6)
    _, perturb_key = jax.random.split(jax.random.fold_in(keys[1], 2))
    expected = two.position + 0.01 * jax.random.normal(perturb_key, (3,))
    np.testing.assert_allclose(two.goal, expected, atol=1e-7)
    assert int(two.periods_within) == 0
    _, three, _, _, _ = env.step_env(keys[2], two, jnp.zeros(3), params)
    np.testing.assert_array_equal(three.goal, two.goal)
    assert int(three.periods_within) == 1


def test_goal_redraws_off_leave_every_step_as_it_was_and_a_negative_period_is_refused():
    """0 (the default) never redraws: over a whole episode the goal stays; from goal_mode=data
    a redrawn goal is one of the goal set's."""
    env, params = toy()
    _, state = env.reset(jax.random.PRNGKey(1), params)
    goal = state.goal
    for step_key in jax.random.split(jax.random.PRNGKey(2), 5):
        _, state, _, _, _ = env.step_env(step_key, state, jnp.ones(3), params)
        np.testing.assert_array_equal(state.goal, goal)
    env, params = toy(goal_redraw_periods=1)
    _, state = env.reset(jax.random.PRNGKey(1), params)
    for step_key in jax.random.split(jax.random.PRNGKey(2), 5):
        _, state, _, _, _ = env.step_env(step_key, state, jnp.ones(3), params)
        assert np.any(np.all(np.isclose(np.asarray(GOALS), np.asarray(state.goal)), axis=1))
    with pytest.raises(ConfigError, match=r"env.goal_redraw_periods=-1 must be >= 0"):
        toy(goal_redraw_periods=-1)


def test_the_ensemble_of_a_cv_model_fits_its_further_seeds_on_all_runs_alone(make_cfg,
                                                                               sorolex_dir):
    """The folds score the recipe once (the first seed's fit); the further members of the
    ensemble train the model on every run and nothing else."""
    cfg = make_cfg("robot=sorolex_csv", f"robot.data_dir={sorolex_dir}", "env.ensemble_seeds=3")
    assert keys.model_protocol(cfg).value == "cv"
    members = chain.ensemble_configs(cfg)
    assert [m.model.seed for m in members] == [1, 2]
    for member in members:
        spec, _ = keys.fit_model_spec(member)
        assert spec["dataset"]["protocol"] == "split"
        assert spec["dataset"]["train_fraction"] == 1.0
    _, inputs = keys.train_ppo_spec(cfg)
    assert inputs["fit_model/seed+1"] == keys.key("fit_model", members[0])
    # the jobs the chain runs are the ones the keys read
    jobs = [job for job in chain.model_jobs(cfg) if job.label]
    assert [keys.key("fit_model", job.cfg) for job in jobs] == [
        inputs["fit_model/seed+1"], inputs["fit_model/seed+2"]]
