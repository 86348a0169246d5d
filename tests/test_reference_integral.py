"""Integral action while tracking (env.reference_integral_gain): the observed reference moves by
a share of the measured error each control period, by hand, in the environment and in the keys."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipeline import keys
from pipeline.arm import references as R
from pipeline.rl.envs.observation import observe, update_reference_shift
from pipeline.schemas import ConfigError
from pipeline.validation import validate_config
from tests.test_track_task import ACTIONS, episode, toy

GOAL = np.array([0.032, 0.353, 0.202])


def settings(gain, limit_mm=5.0):
    return SimpleNamespace(reference_integral_gain=jnp.float32(gain),
                           reference_shift_max_mm=jnp.float32(limit_mm))


def test_the_shift_by_hand():
    measured = GOAL - np.array([0.001, 0.0, -0.002])  # 1 mm short in x, 2 mm past in z
    first = update_reference_shift(jnp.zeros(3), measured, GOAL, settings(0.2))
    np.testing.assert_allclose(first, [0.0002, 0.0, -0.0004], atol=1e-9)
    second = update_reference_shift(first, measured, GOAL, settings(0.2))
    np.testing.assert_allclose(second, [0.0004, 0.0, -0.0008], atol=1e-9)
    # an error the other way takes it back
    back = update_reference_shift(second, GOAL + np.array([0.002, 0.0, -0.004]), GOAL,
                                  settings(0.2))
    np.testing.assert_allclose(back, [0.0, 0.0, 0.0], atol=1e-9)
    # at most reference_shift_max_mm in all, along the same direction: 0.2 x 10 mm -> 0.5 mm
    bounded = update_reference_shift(jnp.zeros(3), GOAL - np.array([0.006, 0.0, 0.008]), GOAL,
                                     settings(0.2, limit_mm=0.5))
    np.testing.assert_allclose(bounded, [0.0003, 0.0, 0.0004], atol=1e-9)
    # gain 0: never moves, exactly
    assert not np.any(update_reference_shift(jnp.zeros(3), measured, GOAL, settings(0.0)))


def test_the_shift_has_a_finite_gradient_at_zero():
    grad = jax.grad(lambda measured: update_reference_shift(
        jnp.zeros(3), measured, jnp.asarray(GOAL, jnp.float32), settings(0.2)).sum())(
        jnp.asarray(GOAL, jnp.float32))  # the error, and the shift, exactly 0
    np.testing.assert_allclose(grad, [-0.2, -0.2, -0.2], rtol=1e-6)


def test_the_policy_observes_the_goal_and_preview_moved_by_the_shift():
    params = SimpleNamespace(obs_mean=jnp.array([0.03, 0.35, 0.2]),
                             obs_scale=jnp.array([0.01, 0.01, 0.02]), error_scale_m=0.005)
    measured = jnp.array([0.031, 0.352, 0.203])
    goal = jnp.array([0.033, 0.352, 0.201])
    preview = jnp.array([[0.034, 0.352, 0.202], [0.035, 0.352, 0.203]])
    shift = jnp.array([0.001, 0.0, -0.0005])
    obs = observe(measured, goal, jnp.zeros(3), params, include_error=True,
                  include_last_action=False, preview=preview, reference_shift=shift)
    # goal (0.034, 0.352, 0.2005), preview (0.035 .., 0.2015), (0.036 .., 0.2025)
    np.testing.assert_allclose(obs[3:6], [0.4, 0.2, 0.025], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(obs[6:9], [0.6, 0.0, -0.5], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(obs[9:], [0.8, 0.0, -0.3, 1.0, 0.0, -0.1], rtol=1e-5, atol=1e-6)
    unmoved = observe(measured, goal, jnp.zeros(3), params, include_error=True,
                      include_last_action=False, preview=preview)
    np.testing.assert_array_equal(obs[:3], unmoved[:3])  # the position is what it is


def test_the_environment_moves_the_observed_reference_and_rewards_the_reference():
    gain = 0.5
    env, params = toy("track", preview=2, static_share=0.0, goal_tolerance_m=1.0,
                      reference_integral_gain=gain)
    steps = episode(env, params, ACTIONS)
    reference = steps[0][1].reference
    shift = np.zeros(3)
    for period, (obs, state, reward, _) in enumerate(steps):
        if period:
            previous_goal = np.asarray(steps[period - 1][1].goal)
            # no observation noise: measured is the position
            shift = shift + gain * (previous_goal - np.asarray(state.position))
            length = np.linalg.norm(shift)
            shift = shift * min(1.0, 0.005 / length)
            # the reward is the distance to the reference itself
            np.testing.assert_allclose(
                reward, -1000.0 * np.linalg.norm(state.position - previous_goal), rtol=1e-5)
        np.testing.assert_allclose(state.reference_shift, shift, atol=1e-7)
        np.testing.assert_allclose(obs[6:9], (state.goal + shift - state.position) / 0.005,
                                   rtol=1e-4, atol=1e-4)
        ahead = R.positions(reference, jnp.array([period + 2, period + 3]) / 2.0)
        np.testing.assert_allclose(obs[-6:], ((ahead + shift - state.position) / 0.005)
                                   .reshape(-1), rtol=1e-4, atol=1e-4)
    assert np.linalg.norm(shift) > 1e-4  # it moved


def test_at_gain_zero_the_environment_tracks_as_before():
    env, params = toy("track", preview=2, static_share=0.0)
    _, moved = toy("track", preview=2, static_share=0.0, reference_integral_gain=0.5)
    for (obs, state, _, _), (obs2, state2, _, _) in zip(episode(env, params, ACTIONS),
                                                      episode(env, moved, ACTIONS)):
        assert not np.any(state.reference_shift)
        np.testing.assert_array_equal(obs[:3], obs2[:3])  # the same poses ...
        np.testing.assert_array_equal(state.position, state2.position)
    assert not np.allclose(obs[3:], obs2[3:])  # ... but a moved reference observed


def test_reaching_keeps_no_shift():
    env, params = toy(reference_integral_gain=0.5)
    for _, state, _, _ in episode(env, params, ACTIONS):
        assert not np.any(state.reference_shift)


def test_keys_name_the_gain_only_where_it_acts(make_cfg):
    tracked = make_cfg("experiment=tracking")
    assert keys.key("train_ppo", tracked) == keys.key(
        "train_ppo", make_cfg("experiment=tracking", "env.reference_shift_max_mm=3"))
    acting = make_cfg("experiment=tracking", "env.reference_integral_gain=0.2")
    assert keys.key("train_ppo", acting) != keys.key("train_ppo", tracked)
    assert keys.key("train_ppo", acting) != keys.key(
        "train_ppo", make_cfg("experiment=tracking", "env.reference_integral_gain=0.2",
                              "env.reference_shift_max_mm=3"))
    base = make_cfg()
    assert keys.key("train_ppo", base) == keys.key(
        "train_ppo", make_cfg("env.reference_integral_gain=0.2"))  # reaching: unused


@pytest.mark.parametrize("override, words", [
    ("env.reference_integral_gain=1.5", "env.reference_integral_gain=1.5 must lie in \\[0, 1\\]"),
    ("env.reference_integral_gain=-0.1", "env.reference_integral_gain=-0.1 must lie in"),
    ("env.reference_shift_max_mm=0", "env.reference_shift_max_mm=0.0 must be a finite number"),
])
def test_bad_integral_settings_are_refused_by_name(make_cfg, override, words):
    with pytest.raises(ConfigError, match=words):
        validate_config(make_cfg("experiment=tracking", override))
