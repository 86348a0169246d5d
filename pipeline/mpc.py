"""A model-based baseline: sampling-based MPC (cross-entropy method) on the learned model.

At every control period the controller searches the pressure command to hold, scoring candidates
by rolling the learned model forward ``horizon`` control periods with that command held (the
arm settles within about a second, so a constant command over a short horizon suffices for
reaching a fixed goal). Candidates are projected onto the safe set before they are scored, so
whatever the search does, the command is safe.

On a plant other than the model (the simulated arm, a real arm) the model runs alongside the plant
open loop, fed the same commands, and the goal given to the model is shifted by the current
plant-minus-model position offset: the usual offset-free correction of MPC with a model that has
no state estimator.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp

from pipeline.envs.plants import Plant, hold
from pipeline.safety import SafeSet, project


class CEMSettings(NamedTuple):
    horizon: int = 2  # control periods the candidate command is held for
    num_samples: int = 64
    num_iterations: int = 3
    num_elites: int = 8
    initial_std_kpa: float = 2.0


DEFAULT_SETTINGS = CEMSettings()


def plan(
    key: chex.PRNGKey,
    model: Plant,
    model_params: Any,
    carry: Any,
    goal: chex.Array,
    start: chex.Array,
    safe: SafeSet,
    steps_per_action: int,
    settings: CEMSettings = DEFAULT_SETTINGS,
) -> chex.Array:
    """The command ``[3]`` kPa to hold now, searched from ``start [3]`` kPa.

    Cost of a candidate: the mean distance to ``goal [3]`` m at the end of each of the
    ``horizon`` control periods it is held for.
    """
    chex.assert_shape(goal, (3,))

    def cost(command):
        _, positions = hold(model, model_params, carry, command,
                            steps_per_action * settings.horizon)
        ends = positions[steps_per_action - 1::steps_per_action]
        return jnp.linalg.norm(ends - goal, axis=-1).mean()

    def iteration(search, iteration_key):
        mean, std = search
        samples = mean + std * jax.random.normal(iteration_key, (settings.num_samples, 3))
        samples = project(samples.at[0].set(mean), safe)  # keep the current mean in the race
        costs = jax.vmap(cost)(samples)
        elites = samples[jnp.argsort(costs)[: settings.num_elites]]
        return (elites.mean(axis=0), elites.std(axis=0) + 0.05), elites[0]

    search = (start, jnp.full(3, settings.initial_std_kpa))
    _, best = jax.lax.scan(iteration, search, jax.random.split(key, settings.num_iterations))
    return project(best[-1], safe)


def rollout(
    key: chex.PRNGKey,
    plant: Plant,
    plant_params: Any,
    plant_carry: Any,
    model: Plant,
    model_params: Any,
    model_carry: Any,
    start_position: chex.Array,
    model_start_position: chex.Array,
    goals: chex.Array,
    preload: chex.Array,
    safe: SafeSet,
    steps_per_action: int,
    settings: CEMSettings = DEFAULT_SETTINGS,
) -> tuple[chex.Array, chex.Array]:
    """Closed loop of the MPC on ``plant`` for ``T`` control periods.

    Args:
      goals: ``[T, 3]`` m, the goal in force in each control period.
      start_position, model_start_position: ``[3]`` m, where plant and model start.

    Returns:
      positions ``[T + 1, 3]`` (m, on the plant; row 0 the start) and commands ``[T, 3]`` kPa.
    """
    chex.assert_rank(goals, 2)

    def control_period(carry, inputs):
        plant_carry, model_carry, plant_position, model_position, previous = carry
        period_key, goal = inputs
        offset = plant_position - model_position
        command = plan(period_key, model, model_params, model_carry, goal - offset, previous,
                       safe, steps_per_action, settings)
        plant_carry, plant_path = hold(plant, plant_params, plant_carry, command,
                                       steps_per_action)
        model_carry, model_path = hold(model, model_params, model_carry, command,
                                       steps_per_action)
        carry = (plant_carry, model_carry, plant_path[-1], model_path[-1], command)
        return carry, (plant_path[-1], command)

    keys = jax.random.split(key, goals.shape[0])
    start = (plant_carry, model_carry, start_position, model_start_position,
             jnp.asarray(preload, jnp.float32))
    _, (positions, commands) = jax.lax.scan(control_period, start, (keys, goals))
    return jnp.concatenate([start_position[None], positions]), commands
