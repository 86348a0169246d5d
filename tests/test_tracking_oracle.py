"""The tracking oracle on a plant whose answer is known by hand: a static map of the command."""

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from experiments.tracking_oracle import START_KPA, optimal_commands
from pipeline.arm.safety import SafeSet
from pipeline.rl.envs.plants import Plant

MM_PER_KPA = 1.0  # the plant sits at 1 mm per kPa along each axis


class _Env(NamedTuple):
    plant: Plant
    steps_per_action: int


class _Params(NamedTuple):
    plant: Any
    safe_set: SafeSet


def _static_map_plant() -> Plant:
    """Position = command x 1 mm/kPa, immediately (no memory beyond the last command)."""

    def step(params, carry, pressure):
        position = pressure * MM_PER_KPA / 1000.0
        return position, position

    return Plant(lambda params, pose: pose, step, 10.0, "static map")


def test_oracle_follows_a_reachable_reference_and_stops_at_the_limit():
    env = _Env(_static_map_plant(), 5)
    params = _Params(None, SafeSet(jnp.full(3, -3.0), jnp.full(3, 7.0), jnp.asarray(13.0)))
    preload = jnp.array([2.0, 2.0, 2.0])
    steps, settle = 6, 2
    # commands 1..6 kPa on the first valve, 3 on the others: all inside the safe set except the
    # last two periods, which ask for 7.5 and 8 kPa on the first valve (0.5 and 1 mm beyond 7)
    wanted = np.stack([np.linspace(1.0, 8.0, steps + 1), np.full(steps + 1, 3.0),
                       np.full(steps + 1, 3.0)], axis=-1)
    wanted[:, 0] = [1.0, 2.0, 3.0, 4.0, 5.0, 7.5, 8.0]
    targets = jnp.asarray(wanted[None] / 1000.0, jnp.float32)  # [1, T + 1, 3] m
    carries = jnp.zeros((1, 3))
    commands, positions, held = optimal_commands(env, params, carries, preload, targets, settle,
                                                 2000, 0.05)
    # the preload held: 2 mm on every axis in every period
    np.testing.assert_allclose(np.asarray(held[0]) * 1000.0, np.full((steps, 3), 2.0), atol=1e-5)
    # the positions after periods 2 ... 6 are scored, as the evaluation scores them: the commands
    # of periods 2 ... 6 follow (3, 4, 5 kPa), then stop at the limit
    found = np.asarray(commands[0])
    np.testing.assert_allclose(found[settle - 1:, 0], [3.0, 4.0, 5.0, 7.0, 7.0], atol=0.02)
    np.testing.assert_allclose(found[settle - 1:, 1:], 3.0, atol=0.02)
    np.testing.assert_allclose(np.asarray(positions[0]) * 1000.0, found, atol=1e-4)
    # the first period ends before the settling time, unscored: left where the search started
    np.testing.assert_allclose(found[0], 2.0 + START_KPA, atol=1e-6)
