"""The deadband of deployment (``env.deadband_m``): within it of the goal the last command stays,
in evaluate's reaching episodes and on the arm, never in training.

Known answers on the linear-lag toy of ``tests/test_robust_env.py`` (five plant steps per
period, three recorded goals 5 mm from the rest pose).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipeline import keys
from pipeline.evaluation import rollouts
from pipeline.schemas import ConfigError
from pipeline.validation import validate_config
from tests.test_robust_env import GOALS, toy


@pytest.mark.parametrize("incremental", [False, True])
def test_within_the_deadband_the_action_commands_the_last_pressure_again(incremental):
    env, params = toy(deadband_m=0.001)
    env.incremental_actions = incremental
    goal, last = GOALS[0], jnp.array([1.5, 3.0, 4.25])
    action = jnp.array([0.9, -0.8, 0.3])
    near = goal + jnp.array([0.0006, 0.0, -0.0007])  # 0.92 mm away
    far = goal + jnp.array([0.0008, 0.0, -0.0007])  # 1.06 mm away
    held = env.deadband_action(action, near, goal, last, params)
    np.testing.assert_allclose(env.command(held, last, params), last, atol=1e-6)
    if incremental:
        np.testing.assert_array_equal(held, jnp.zeros(3))
    else:  # [-1, 1] on [0, 7] kPa: 2 p / 7 - 1
        np.testing.assert_allclose(held, [2 * 1.5 / 7 - 1, 2 * 3.0 / 7 - 1, 2 * 4.25 / 7 - 1],
                                   rtol=1e-6)
    np.testing.assert_array_equal(env.deadband_action(action, far, goal, last, params), action)
    # off (0): the policy's action even exactly at the goal
    _, off = toy(deadband_m=0.0)
    np.testing.assert_array_equal(env.deadband_action(action, goal, goal, last, off), action)


def _seek_then_push(env, params, gain, offset):
    """A controller that commands the pressure whose steady state is the goal (the toy's
    ``position = offset + G @ pressure``) for its first 4 periods, then pushes every valve to its
    maximum; carry: the periods it has acted."""

    def act(key, obs, state, periods):
        seek = jnp.linalg.solve(gain, state.goal - offset)
        action = jnp.where(periods < 4, env.action_for(seek, state.last_pressure, params),
                           jnp.ones(3))
        return periods + 1, action

    return act


@pytest.mark.parametrize("deadband", [False, True])
def test_a_rollout_as_deployed_keeps_the_command_that_reached_the_goal(deadband):
    """The goal is reached within 0.5 mm by the end of period 3 (``tests/test_hold_training.py``);
    from period 4 the controller pushes away. As deployed (deadband 1 mm) every command from
    period 4 on is period 3's and the arm stays at the goal; without the deadband, or with it
    at 0, the push moves the arm off by millimetres."""
    env, params = toy(deadband_m=0.001, goal_tolerance_m=0.001)
    carry = jax.tree.map(lambda leaf: leaf[0], params.reset_carries)
    offset, gain = carry.offset, params.plant.gain
    goals = jnp.broadcast_to(GOALS[1], (8, 3))
    controller = _seek_then_push(env, params, gain, offset)
    run = jax.jit(lambda p: rollouts.rollout(
        env, p, controller, jnp.zeros((), jnp.int32), jax.random.PRNGKey(2), carry,
        params.reset_positions[0], goals, deadband=deadband))
    positions, commands = run(params)
    distance_mm = 1000 * np.linalg.norm(np.asarray(positions) - np.asarray(GOALS[1]), axis=1)
    assert distance_mm[4] < 0.5  # arrived: the pose measured at the start of period 4
    if deadband:
        np.testing.assert_allclose(commands[4:], np.broadcast_to(commands[3], (4, 3)), atol=1e-5)
        assert distance_mm[4:].max() < 0.5
    else:
        assert np.abs(np.asarray(commands[4]) - np.asarray(commands[3])).max() > 0.5
        assert distance_mm[-1] > 2.0
    # the deadband at 0 is the rollout without it, to the bit
    off_positions, off_commands = run(params.replace(deadband_m=jnp.float32(0.0)))
    if not deadband:
        np.testing.assert_array_equal(off_positions, positions)
        np.testing.assert_array_equal(off_commands, commands)


def test_the_deadband_is_deployment_only_in_the_keys(make_cfg):
    """Training never meets it: the train_ppo key is the same with and without; evaluate and
    control (goals) run anew with it; at 0 the keys of before (the setting left out)."""
    base, on = make_cfg("experiment=quick"), make_cfg("experiment=quick", "env.deadband_m=0.001")
    assert keys.key("train_ppo", on) == keys.key("train_ppo", base)
    assert "deadband_m" not in keys.evaluate_spec(base)[0]["env"]
    assert keys.evaluate_spec(on)[0]["env"]["deadband_m"] == 0.001
    assert keys.key("evaluate", on) != keys.key("evaluate", base)
    assert keys.key("control", on) != keys.key("control", base)


@pytest.mark.parametrize("value", ["-0.0005", "0.002"])
def test_a_deadband_beyond_the_goal_tolerance_is_refused(make_cfg, value):
    cfg = make_cfg("experiment=quick", f"env.deadband_m={value}")
    with pytest.raises(ConfigError, match=r"env.deadband_m=.* must lie in \[0, "
                                          r"env.goal_tolerance_m=0.001\] m"):
        validate_config(cfg)
