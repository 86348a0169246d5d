"""The simulated arm: rest pose, steady states, dynamics, motion capture, vmap."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from omegaconf import OmegaConf

from pipeline.arm import sim_arm
from pipeline.schemas import SimRobotConfig

ROBOT = OmegaConf.structured(SimRobotConfig)
PARAMS = sim_arm.SimParams.from_config(ROBOT)
PRELOAD = jnp.full(3, 2.0)
advance = jax.jit(sim_arm.advance, static_argnums=3)


def settle(command, seconds=12.0, state=None):
    state = state or sim_arm.settled_state(PARAMS, PRELOAD, jnp.zeros(3))
    return advance(PARAMS, state, jnp.asarray(command, jnp.float32), int(seconds * 100))


def test_rest_pose_at_preload_is_the_real_arms():
    state = sim_arm.settled_state(PARAMS, PRELOAD, jnp.zeros(3))
    rest = np.asarray(sim_arm.tip_position(PARAMS, state)) * 1e3
    # the real runs rest near (30-34, 353, 200-203) mm
    np.testing.assert_allclose(rest, [32.0, 353.0, 201.5], atol=1.0)
    # holding the preload keeps it there
    np.testing.assert_allclose(np.asarray(sim_arm.tip_position(PARAMS, settle(PRELOAD))) * 1e3,
                               rest, atol=1e-3)


def test_equal_pressures_only_lengthen_the_arm():
    low = np.asarray(sim_arm.tip_position(PARAMS, settle([2.0, 2.0, 2.0], seconds=40)))
    high = np.asarray(sim_arm.tip_position(PARAMS, settle([4.0, 4.0, 4.0], seconds=40)))
    np.testing.assert_allclose(high[[0, 2]], low[[0, 2]], atol=1e-6)
    # 0.5 mm/kPa of mean pressure; rising pressure stops at the play's lower edge (-0.2 kPa):
    # 1.8 kPa more effective pressure -> 0.9 mm lower
    assert high[1] - low[1] == pytest.approx(-1.8 * 0.0005, abs=1e-5)


def test_a_pressure_difference_bends_away_and_lifts_the_tip():
    rest = np.asarray(sim_arm.tip_position(PARAMS, settle(PRELOAD)))
    bent = np.asarray(sim_arm.tip_position(PARAMS, settle([5.0, 0.5, 0.5])))
    lateral = np.hypot(*(bent - rest)[[0, 2]]) * 1e3
    assert 12.0 < lateral < 30.0  # the real arm: ~20 mm for a few kPa of difference
    assert bent[1] > rest[1]  # bending lifts the markers, as on the real arm
    # chamber 0 sits at 90 deg (+z): pressurising it bends the arm toward -z
    assert bent[2] < rest[2] and abs(bent[0] - rest[0]) < 1e-3


def test_step_response_lags_overshoots_a_little_and_settles():
    state = sim_arm.settled_state(PARAMS, PRELOAD, jnp.zeros(3))
    z = []
    for _ in range(300):
        state = advance(PARAMS, state, jnp.array([5.0, 0.5, 0.5]), 1)
        z.append(float(sim_arm.tip_position(PARAMS, state)[2]))
    z = np.array(z) - z[0]
    final = z[-1]
    assert abs(z[4]) < 0.2 * abs(final)  # 50 ms in: the chambers have barely filled
    assert np.abs(z).max() > 1.02 * abs(final)  # under-damped
    assert np.abs(z[150:] - final).max() < 0.05 * abs(final)  # settled after 1.5 s (creep aside)


def test_hysteresis_makes_the_path_depend_on_the_direction():
    up = settle([3.0, 2.0, 2.0], state=settle([4.0, 2.0, 2.0]))
    down = settle([3.0, 2.0, 2.0], state=settle([2.0, 2.0, 2.0]))
    gap = np.linalg.norm(np.asarray(sim_arm.tip_position(PARAMS, up) -
                                    sim_arm.tip_position(PARAMS, down)))
    assert gap > 1e-4


def test_simulated_run_records_noisy_jittered_mocap_with_drops():
    commands = np.tile([[2.0, 2.0, 2.0], [4.0, 1.0, 1.0]], (10, 1))  # 20 commands, 10 s
    frames = sim_arm.frame_command_index(len(commands), 2.0, 100.0)
    assert len(frames) == 1000 and frames[49] == 0 and frames[50] == 1
    out = jax.jit(sim_arm.simulate_run)(PARAMS, jax.random.key(0), commands, frames, PRELOAD)
    t, pos, valid = (np.asarray(out[k]) for k in ("t", "position", "valid"))
    assert np.all(np.diff(t) > 0)
    assert np.median(np.diff(t)) == pytest.approx(0.01, abs=1e-4)
    assert 0.9 < valid.mean() < 1.0
    assert np.isnan(pos[~valid]).all() and np.isfinite(pos[valid]).all()
    noise = pos[valid] - np.asarray(out["true_position"])[valid]
    assert np.std(noise) == pytest.approx(ROBOT.mocap.noise_std_m, rel=0.2)


def test_sessions_differ_in_rest_pose_and_vmap_over_arms():
    commands = jnp.full((4, 3), 2.0)
    frames = sim_arm.frame_command_index(4, 2.0, 100.0)
    simulate = jax.jit(jax.vmap(sim_arm.simulate_run, in_axes=(None, 0, None, None, None)))
    out = simulate(PARAMS, jax.random.split(jax.random.key(1), 8), commands, frames, PRELOAD)
    rest = np.asarray(out["true_position"][:, 0])
    assert rest.shape == (8, 3)
    spread_mm = rest.std(axis=0) * 1e3
    assert 0.5 < spread_mm[0] < 5 and 0.2 < spread_mm[2] < 3  # a few mm between sessions


def test_many_arms_with_different_parameters_under_vmap():
    stiff = jax.tree.map(lambda x: jnp.stack([x, x]), PARAMS)
    stiff = stiff.replace(bend_gain=jnp.array([0.065, 0.03]))
    states = jax.vmap(sim_arm.settled_state, in_axes=(0, None, None))(stiff, PRELOAD, jnp.zeros(3))
    moved = jax.vmap(sim_arm.advance, in_axes=(0, 0, None, None))(
        stiff, states, jnp.array([5.0, 0.5, 0.5]), 500)
    tips = jax.vmap(sim_arm.tip_position)(stiff, moved)
    rest = jax.vmap(sim_arm.tip_position)(stiff, states)
    shift = np.abs(np.asarray(tips - rest)[:, 2])
    assert shift[0] > 1.5 * shift[1]


def _with_spread(spread):
    robot = OmegaConf.merge(ROBOT, {"physics": {"session_std": spread}})
    return sim_arm.SimParams.from_config(robot)


def test_no_session_spread_gives_every_session_the_same_physics():
    commands = jnp.tile(jnp.array([[2.0, 2.0, 2.0], [4.0, 1.0, 1.0]]), (4, 1))
    frames = sim_arm.frame_command_index(len(commands), 2.0, 100.0)
    simulate = jax.jit(jax.vmap(sim_arm.simulate_run, in_axes=(None, 0, None, None, None)))
    keys = jax.random.split(jax.random.key(3), 3)
    assert sim_arm.session_params(PARAMS, keys[0]) is PARAMS  # empty spread: nothing drawn
    outputs = []
    for spread in ({}, {"bend_gain": 0.0, "chamber_angles_deg": 0.0, "natural_freq_hz": 0.0}):
        params = _with_spread(spread).replace(rest_pose_std=jnp.zeros(3))
        true = np.asarray(simulate(params, keys, commands, frames, PRELOAD)["true_position"])
        np.testing.assert_array_equal(true[1], true[0])
        np.testing.assert_array_equal(true[2], true[0])
        outputs.append(true)
    # a zero spread is no spread: another program (the draws times zero), the same arm to float
    # rounding (the suite's older CPU emitters, conftest.py, fuse the two apart by an ulp)
    np.testing.assert_allclose(outputs[1], outputs[0], rtol=1e-6, atol=1e-9)


def test_sessions_draw_their_physics_with_the_configured_spread():
    spread = {"bend_gain": 0.01, "chamber_gains": [0.1, 0.0, 0.05], "chamber_angles_deg": 4.0,
              "natural_freq_hz": 0.1}
    params = _with_spread(spread)
    n = 4000
    drawn = jax.vmap(sim_arm.session_params, in_axes=(None, 0))(
        params, jax.random.split(jax.random.key(0), n))
    tolerance = 4 / np.sqrt(2 * n)  # relative error of a standard deviation, 4 sigma
    bend = np.asarray(drawn.bend_gain)
    assert bend.mean() == pytest.approx(0.065, abs=4 * 0.01 / np.sqrt(n))
    assert bend.std() == pytest.approx(0.01, rel=tolerance)
    gains = np.asarray(drawn.chamber_gains)
    np.testing.assert_allclose(gains.std(0), [0.1, 0.0, 0.05], rtol=tolerance)
    np.testing.assert_array_equal(gains[:, 1], 1.0)
    angles = np.asarray(jax.vmap(sim_arm.physics_value, in_axes=(0, None))(
        drawn, "chamber_angles_deg"))
    turned = (angles - np.array([90.0, 210.0, 330.0]) + 180.0) % 360.0 - 180.0
    np.testing.assert_allclose(turned.std(0), 4.0, rtol=tolerance)
    np.testing.assert_allclose(turned.mean(0), 0.0, atol=4 * 4.0 / np.sqrt(n))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(drawn.chamber_dirs), axis=-1), 1.0,
                               atol=1e-6)
    frequency = np.asarray(drawn.omega) / (2 * np.pi)
    assert frequency.std() == pytest.approx(0.1, rel=tolerance)
    assert abs(np.corrcoef(bend, frequency)[0, 1]) < 4 / np.sqrt(n)  # independent draws
    np.testing.assert_array_equal(np.asarray(drawn.damping_ratio), np.float32(0.3))  # not spread
    # a simulated run reports the physics its session drew, and sessions differ by them
    frames = sim_arm.frame_command_index(4, 2.0, 100.0)
    out = jax.vmap(sim_arm.simulate_run, in_axes=(None, 0, None, None, None))(
        params, jax.random.split(jax.random.key(1), 2), jnp.full((4, 3), 2.0), frames, PRELOAD)
    assert sorted(out["physics"]) == sorted(spread)
    assert out["physics"]["bend_gain"].shape == (2,)
    assert out["physics"]["bend_gain"][0] != out["physics"]["bend_gain"][1]


def test_a_session_spread_of_an_unknown_or_misshaped_parameter_is_refused():
    with pytest.raises(ValueError, match="base_position_m"):
        _with_spread({"base_position_m": 0.001})
    with pytest.raises(ValueError, match="chamber_gains"):
        _with_spread({"chamber_gains": [0.1, 0.1]})
    with pytest.raises(ValueError, match="bend_gain"):
        _with_spread({"bend_gain": -0.01})
