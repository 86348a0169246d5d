"""The deadband and the hold of deployment (``env.deadband_m``, ``env.hold_gain``,
``env.hold_backoff``): within it of the goal the last command stays (gain 0) or moves by integral
action through the static map of the policy's model, its gain backed off after each correction
that overshot, in evaluate's reaching episodes and on the arm, never in training.

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
from pipeline.rl.envs import default_linear_lag_params
from pipeline.rl.envs.learned import damped_inverse, static_gain, with_hold_map
from pipeline.schemas import ConfigError
from pipeline.validation import validate_config
from tests.test_robust_env import GOALS, toy


def deployed(env, action, measured, goal, last, params):
    """The action deployment sends in the first period at ``goal`` (the hold's memory fresh)."""
    return env.deadband_action(env.initial_hold(goal), action, measured, goal, last, params)[1]


@pytest.mark.parametrize("incremental", [False, True])
def test_within_the_deadband_the_action_commands_the_last_pressure_again(incremental):
    env, params = toy(deadband_m=0.001)
    env.incremental_actions = incremental
    goal, last = GOALS[0], jnp.array([1.5, 3.0, 4.25])
    action = jnp.array([0.9, -0.8, 0.3])
    near = goal + jnp.array([0.0006, 0.0, -0.0007])  # 0.92 mm away
    far = goal + jnp.array([0.0008, 0.0, -0.0007])  # 1.06 mm away
    held = deployed(env, action, near, goal, last, params)
    np.testing.assert_allclose(env.command(held, last, params), last, atol=1e-6)
    if incremental:
        np.testing.assert_array_equal(held, jnp.zeros(3))
    else:  # [-1, 1] on [0, 7] kPa: 2 p / 7 - 1
        np.testing.assert_allclose(held, [2 * 1.5 / 7 - 1, 2 * 3.0 / 7 - 1, 2 * 4.25 / 7 - 1],
                                   rtol=1e-6)
    np.testing.assert_array_equal(deployed(env, action, far, goal, last, params), action)
    # off (0): the policy's action even exactly at the goal
    _, off = toy(deadband_m=0.0)
    np.testing.assert_array_equal(deployed(env, action, goal, goal, last, off), action)


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


def test_the_deadband_and_the_hold_are_deployment_only_in_the_keys(make_cfg):
    """Training never meets them: the train_ppo key is the same off, with a deadband and with
    a hold; evaluate and control (goals) run anew with each; off, the keys of before (the
    settings left out)."""
    off = make_cfg("experiment=quick", "env.deadband_m=0", "env.hold_gain=0")
    deadband = make_cfg("experiment=quick", "env.deadband_m=0.001", "env.hold_gain=0")
    hold = make_cfg("experiment=quick", "env.deadband_m=0.002", "env.hold_gain=0.1")
    assert len({keys.key("train_ppo", cfg) for cfg in (off, deadband, hold)}) == 1
    assert len({keys.key("evaluate", cfg) for cfg in (off, deadband, hold)}) == 3
    assert len({keys.key("control", cfg) for cfg in (off, deadband, hold)}) == 3
    envs = [keys.evaluate_spec(cfg)[0]["env"] for cfg in (off, deadband, hold)]
    assert "deadband_m" not in envs[0] and "hold_gain" not in envs[0]
    assert envs[1]["deadband_m"] == 0.001 and "hold_gain" not in envs[1]
    assert envs[2]["deadband_m"] == 0.002 and envs[2]["hold_gain"] == 0.1
    assert keys.control_spec(hold)[0]["hold_gain"] == 0.1
    assert "hold_gain" not in keys.control_spec(deadband)[0]
    validate_config(hold)  # beyond the goal tolerance: the hold acts there, it does not freeze


@pytest.mark.parametrize("value", ["-0.0005", "0.002"])
def test_a_deadband_beyond_the_goal_tolerance_is_refused(make_cfg, value):
    cfg = make_cfg("experiment=quick", f"env.deadband_m={value}", "env.hold_gain=0")
    with pytest.raises(ConfigError, match=r"env.deadband_m=.* must lie in \[0, "
                                          r"env.goal_tolerance_m=0.001\] m"):
        validate_config(cfg)


# ---- the hold: integral action through the static map ----------------------------------------
DIAGONAL_GAIN = jnp.diag(jnp.array([0.002, 0.001, 0.004]))  # m/kPa: valve i moves axis i
# (GᵀG + λI)⁻¹Gᵀ of it with λ = (0.1 · 0.004)² = 1.6e-7: g / (g² + 1.6e-7) on the diagonal
DIAGONAL_INVERSE = np.diag([0.002 / 4.16e-6, 0.001 / 1.16e-6, 0.004 / 1.616e-5])  # kPa/m


def _diagonal_toy(**overrides):
    params = default_linear_lag_params()
    return toy(plant_params=params.replace(gain=DIAGONAL_GAIN), **overrides)


def test_the_static_map_of_a_linear_plant_is_its_gain_and_the_hold_map_its_damped_inverse():
    env, params = _diagonal_toy(deadband_m=0.002, hold_gain=0.5)
    gain = static_gain(env, params.plant, params.reset_initial_poses[0], params.preload,
                       params.safe_set)
    np.testing.assert_allclose(gain, DIAGONAL_GAIN, atol=1e-6)
    np.testing.assert_allclose(damped_inverse(DIAGONAL_GAIN), DIAGONAL_INVERSE, rtol=1e-5)
    np.testing.assert_allclose(with_hold_map(env, params).hold_map, DIAGONAL_INVERSE,
                               rtol=1e-3, atol=0.05)
    np.testing.assert_array_equal(params.hold_map, np.zeros((3, 3)))  # training: none
    # the toy arm (two sideways axes and a weak lengthening): its own gain found again
    env, default = toy(deadband_m=0.002, hold_gain=0.5)
    np.testing.assert_allclose(
        static_gain(env, default.plant, default.reset_initial_poses[0], default.preload,
                    default.safe_set), default.plant.gain, atol=1e-6)
    # off (either setting 0): no map is made
    for off in ({"deadband_m": 0.0, "hold_gain": 0.5}, {"deadband_m": 0.001, "hold_gain": 0.0}):
        env, params = _diagonal_toy(**off)
        np.testing.assert_array_equal(with_hold_map(env, params).hold_map, np.zeros((3, 3)))


@pytest.mark.parametrize("incremental", [False, True])
def test_within_the_hold_the_command_moves_by_the_gain_times_the_mapped_error(incremental):
    env, params = _diagonal_toy(deadband_m=0.002, hold_gain=0.5, action_step_kpa=1.0)
    params = with_hold_map(env, params)
    env.incremental_actions = incremental
    goal, last = GOALS[0], jnp.array([1.5, 3.0, 4.25])
    action = jnp.array([0.9, -0.8, 0.3])
    near = goal - jnp.array([0.0006, 0.0, -0.0007])  # 0.92 mm away: goal - measured (0.6, 0, -0.7)
    held = deployed(env, action, near, goal, last, params)
    # 0.5 * (480.77 * 0.0006, 0, 247.52 * -0.0007) kPa = 0.5 * (1.2 / 4.16, 0, -2.8 / 16.16)
    np.testing.assert_allclose(env.command(held, last, params) - last,
                               [0.5 * 1.2 / 4.16, 0.0, -0.5 * 2.8 / 16.16], atol=2e-4)
    far = goal - jnp.array([0.0018, 0.0, -0.0012])  # 2.16 mm away: the policy's action
    np.testing.assert_array_equal(deployed(env, action, far, goal, last, params), action)


def _stopping_short(env, params, beside, periods):
    """``distance_mm(params, deadband=True)``: the distances [mm] to ``GOALS[1]``, ``[periods +
    1]``, of a rollout whose controller commands the steady state at ``beside [3]`` m (the toy's
    ``position = offset + G @ pressure``) every period, with the hold or without it."""
    carry = jax.tree.map(lambda leaf: leaf[0], params.reset_carries)
    offset, gain = carry.offset, params.plant.gain
    goals = jnp.broadcast_to(GOALS[1], (periods, 3))

    def short(key, obs, state, count):
        seek = jnp.linalg.lstsq(gain, beside - offset)[0]
        return count + 1, env.action_for(seek, state.last_pressure, params)

    run = jax.jit(lambda p, deadband: rollouts.rollout(
        env, p, short, jnp.zeros((), jnp.int32), jax.random.PRNGKey(2), carry,
        params.reset_positions[0], goals, deadband=deadband), static_argnums=1)
    return lambda p, deadband=True: 1000 * np.linalg.norm(
        np.asarray(run(p, deadband)[0]) - np.asarray(GOALS[1]), axis=1)


def test_the_hold_closes_the_last_millimetres_a_policy_stops_short_of():
    """A controller that commands the steady state 1.5 mm beside the goal and then the same
    command forever: on its own it ends 1.5 mm away; deployed with the hold (2 mm, gain 0.5) on
    the linear toy, whose map the hold knows exactly, the error halves every period to below
    0.05 mm."""
    env, params = toy(deadband_m=0.002, hold_gain=0.5, goal_tolerance_m=0.001, max_steps=16)
    params = with_hold_map(env, params)
    distance_mm = _stopping_short(env, params, GOALS[1] + jnp.array([0.0015, 0.0, 0.0]), 16)
    alone, held = distance_mm(params, deadband=False), distance_mm(params)
    assert abs(alone[-1] - 1.5) < 0.05
    assert held[-1] < 0.05
    assert np.all(np.diff(held[4:]) <= 1e-3)  # once within the hold, never further away


@pytest.mark.parametrize(("overrides", "words"), [
    (["env.hold_gain=1.5"], r"env.hold_gain=1.5 must lie in \[0, 1\]"),
    (["env.hold_gain=-0.1"], r"env.hold_gain=-0.1 must lie in \[0, 1\]"),
    (["env.hold_gain=0.1", "env.deadband_m=0.02"], r"env.deadband_m=0.02 must lie in \[0, 0.01\]"),
])
def test_a_hold_out_of_its_range_is_refused(make_cfg, overrides, words):
    with pytest.raises(ConfigError, match=words):
        validate_config(make_cfg("experiment=quick", *overrides))


# ---- the hold's backoff: its gain halves after each correction that overshot -------------------
def _memory(env, goal, error_mm, scale=1.0):
    """The hold's memory after a period at ``goal`` that held with ``goal - measured`` =
    ``error_mm``."""
    return env.initial_hold(goal).replace(scale=jnp.float32(scale), held=jnp.array(True),
                                          error=jnp.array(error_mm, jnp.float32) / 1000)


def test_a_correction_that_overshot_halves_the_gain_until_the_goal_changes():
    """Known answers on the diagonal toy (the exact hold map, gain 0.5, backoff 0.5): the last
    period held at an error of (0.6, 0, -0.7) mm (0.92 mm); now (-0.9, 0, 0.6) mm, past the goal
    (their dot product is -0.96 mm²) and further from it (1.08 mm), so the command moves by
    0.5 · 0.5 · map @ error."""
    env, params = _diagonal_toy(deadband_m=0.002, hold_gain=0.5, hold_backoff=0.5)
    params = params.replace(hold_map=jnp.asarray(DIAGONAL_INVERSE, jnp.float32))
    goal, last, action = GOALS[0], jnp.array([1.5, 3.0, 4.25]), jnp.array([0.9, -0.8, 0.3])
    memory = _memory(env, goal, [0.6, 0.0, -0.7])

    def scale(memory, error_mm, p=params):
        measured = goal - jnp.array(error_mm) / 1000
        return float(env.deadband_action(memory, action, measured, goal, last, p)[0].scale)

    past = goal - jnp.array([-0.0009, 0.0, 0.0006])
    hold, held = env.deadband_action(memory, action, past, goal, last, params)
    # 0.25 · (480.77 · -0.0009, 0, 247.52 · 0.0006) kPa = 0.25 · (-1.8 / 4.16, 0, 2.4 / 16.16)
    np.testing.assert_allclose(env.command(held, last, params) - last,
                               [0.25 * -1.8 / 4.16, 0.0, 0.25 * 2.4 / 16.16], atol=2e-6)
    assert float(hold.scale) == 0.5 and bool(hold.held)
    np.testing.assert_allclose(hold.error, [-0.0009, 0.0, 0.0006], atol=1e-8)
    # the scale it had is kept, and halved again at the next overshoot (1.08 -> 1.2 mm across)
    assert scale(hold, [1.2, 0.0, 0.0]) == 0.25
    # the gain stays where the error did not turn past the goal (+0.96 mm²), where it turned and
    # shrank (0.92 -> 0.72 mm: converging), where it turned and grew within a quarter of the
    # radius (0.2 -> 0.4 mm) and where the arm left the radius on its own side (creep)
    assert scale(memory, [0.9, 0.0, -0.6]) == 1.0
    assert scale(memory, [-0.6, 0.0, 0.4]) == 1.0
    assert scale(_memory(env, goal, [0.2, 0.0, 0.0]), [-0.4, 0.0, 0.0]) == 1.0
    assert scale(_memory(env, goal, [1.5, 0.0, -1.2]), [1.8, 0.0, -1.2]) == 1.0
    # a swing across the goal out of the radius counts (1.5 -> 2.16 mm), and the policy acts
    far = goal - jnp.array([0.0018, 0.0, -0.0012])
    hold, sent = env.deadband_action(_memory(env, goal, [-1.2, 0.0, 0.9]), action, far, goal,
                                     last, params)
    assert float(hold.scale) == 0.5 and not bool(hold.held)
    np.testing.assert_array_equal(sent, action)
    # a new goal starts afresh, whatever the memory of the last one
    assert scale(_memory(env, GOALS[1], [0.6, 0.0, -0.7], scale=0.125), [-0.9, 0.0, 0.6]) == 1.0
    # backoff 1: a fixed gain
    assert scale(memory, [-0.9, 0.0, 0.6], params.replace(hold_backoff=jnp.float32(1.0))) == 1.0


def test_where_the_arm_is_steeper_than_the_map_the_backed_off_hold_settles():
    """The hold's map says the arm 20 times less steep than it is (a valve near the preload on
    the recorded arm): at gain 0.5 a fixed hold swings the arm across the goal and out of its
    2 mm radius, back to a controller that stops 1.5 mm short, over and over; backed off, it
    settles within 0.05 mm and stays."""
    env, params = _diagonal_toy(deadband_m=0.002, hold_gain=0.5, goal_tolerance_m=0.001,
                                max_steps=40, hold_backoff=0.5)
    params = params.replace(hold_map=20 * jnp.asarray(DIAGONAL_INVERSE, jnp.float32))
    distance_mm = _stopping_short(env, params, GOALS[1] + jnp.array([0.0, 0.0, 0.0015]), 40)
    backed_off = distance_mm(params)
    fixed = distance_mm(params.replace(hold_backoff=jnp.float32(1.0)))
    assert backed_off[-10:].max() < 0.05
    assert fixed[-10:].max() > 1.5


def test_the_backoff_is_deployment_only_and_checked(make_cfg):
    base = make_cfg("experiment=quick", "env.deadband_m=0.002", "env.hold_gain=0.1",
                    "env.hold_backoff=1")
    backed = make_cfg("experiment=quick", "env.deadband_m=0.002", "env.hold_gain=0.1",
                      "env.hold_backoff=0.5")
    assert keys.key("train_ppo", base) == keys.key("train_ppo", backed)
    assert keys.key("evaluate", base) != keys.key("evaluate", backed)
    assert "hold_backoff" not in keys.evaluate_spec(base)[0]["env"]  # fixed: the key as before
    assert keys.control_spec(backed)[0]["hold_backoff"] == 0.5
    assert "hold_backoff" not in keys.control_spec(base)[0]
    for value in ("0", "1.5"):
        with pytest.raises(ConfigError, match=rf"env.hold_backoff={float(value)} must lie in "
                                              r"\(0, 1\]"):
            validate_config(make_cfg("experiment=quick", f"env.hold_backoff={value}"))
