"""A model-based baseline: sampling-based MPC (cross-entropy method) on the learned model.

At every control period the controller searches the pressure command to hold, scoring candidates
by rolling the learned model forward ``horizon`` control periods with that command held (the
arm settles within about a second, so a constant command over a short horizon suffices for
reaching a fixed goal). Candidates are projected onto the safe set before they are scored, so
whatever the search does, the command is safe.

The model runs alongside the plant open loop, fed the same commands, and the goal given to the
model is shifted by the current plant-minus-model position offset: the usual offset-free
correction of MPC with a model that has no state estimator. On the learned environment itself the
offset stays zero; on the simulated arm or a real arm it absorbs the model's error.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp

from pipeline.arm.safety import SafeSet, project
from pipeline.rl.envs.plants import Plant, hold


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


def mpc_controller(
    env: Any,
    env_params: Any,
    model: Plant,
    model_params: Any,
    settings: CEMSettings = DEFAULT_SETTINGS,
):
    """The MPC as a :data:`pipeline.evaluation.rollouts.Controller` for ``env`` (any plant).

    Its carry is ``(model_carry, model_position [3], last_command [3])``: the learned model run
    open loop on the commands the controller sends; build the first one with
    :func:`initial_carry`.
    """
    steps = env.steps_per_action

    def act(key, obs, state, carry):
        model_carry, model_position, previous = carry
        offset = state.position - model_position
        command = plan(key, model, model_params, model_carry, state.goal - offset, previous,
                       env_params.safe_set, steps, settings)
        action = env.action_for(command, state.last_pressure, env_params)
        if env.incremental_actions:  # rate-limited: the model holds what will be sent
            command = project(env.command(action, state.last_pressure, env_params),
                              env_params.safe_set)
        model_carry, path = hold(model, model_params, model_carry, command, steps)
        return (model_carry, path[-1], command), action

    return act


def initial_carry(model_carry: Any, model_position: chex.Array, preload: chex.Array):
    """The MPC's carry at the start of an episode: the model settled where it starts."""
    return model_carry, jnp.asarray(model_position, jnp.float32), jnp.asarray(preload, jnp.float32)
