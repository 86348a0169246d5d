"""The simulated arm: rest pose, steady states, dynamics, motion capture, vmap."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from omegaconf import OmegaConf

from pipeline.arm import sim_arm
from pipeline.config import SimRobotConfig

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
