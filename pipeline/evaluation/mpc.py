"""A model-based baseline: sampling-based MPC (cross-entropy method) on the learned model.

At every control period the controller searches the pressure command to send, scoring candidates
by rolling the learned model forward ``horizon`` control periods: the mean distance, at the end of
each of those periods, to that period's goal. Reaching, every period's goal is the same and the
candidate is one command held over the horizon (the arm settles within about a second, so a
constant command over a short horizon suffices for a fixed goal); following a reference
(``env.task=track``), the goals are the reference over the horizon (the current goal and the
points after it, as a policy's preview shows them) and, with ``per_period``, a candidate is one
command per period of the horizon, of which the first is sent. Candidates are projected onto the
safe set before they are scored, so whatever the search does, the command is safe.

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
from pipeline.rl.envs import task
from pipeline.rl.envs.plants import Plant, hold


class CEMSettings(NamedTuple):
    horizon: int = 2  # control periods a candidate is scored over
    num_samples: int = 64
    num_iterations: int = 3
    num_elites: int = 8
    initial_std_kpa: float = 2.0
    per_period: bool = False  # a command per period of the horizon; False: one held throughout


DEFAULT_SETTINGS = CEMSettings()


def plan(
    key: chex.PRNGKey,
    model: Plant,
    model_params: Any,
    carry: Any,
    goals: chex.Array,
    start: chex.Array,
    safe: SafeSet,
    steps_per_action: int,
    settings: CEMSettings = DEFAULT_SETTINGS,
) -> chex.Array:
    """The plan ``[blocks, 3]`` kPa (:func:`blocks`: one command held, or one per period of the
    horizon with ``settings.per_period``; its first row is the command to send now), searched
    from ``start`` (``[3]`` or ``[blocks, 3]`` kPa).

    ``goals``: ``[horizon, 3]`` m, the goal at the end of each period of the horizon, or ``[3]``
    m, one goal for all of them. Cost of a candidate: the mean distance to the periods' goals at
    their ends.
    """
    horizon = settings.horizon
    goals = jnp.broadcast_to(goals, (horizon, 3))
    count = blocks(settings)

    def cost(commands):  # [blocks, 3] kPa
        def period(model_carry, command):
            model_carry, path = hold(model, model_params, model_carry, command, steps_per_action)
            return model_carry, path[-1]

        _, ends = jax.lax.scan(period, carry, jnp.broadcast_to(commands, (horizon, 3)))
        return jnp.linalg.norm(ends - goals, axis=-1).mean()

    def iteration(search, iteration_key):
        mean, std = search
        noise = jax.random.normal(iteration_key, (settings.num_samples, count, 3))
        samples = project(mean + std * noise, safe).at[0].set(project(mean, safe))  # keep it
        costs = jax.vmap(cost)(samples)
        elites = samples[jnp.argsort(costs)[: settings.num_elites]]
        return (elites.mean(axis=0), elites.std(axis=0) + 0.05), elites[0]

    search = (jnp.broadcast_to(start, (count, 3)), jnp.full((count, 3), settings.initial_std_kpa))
    _, best = jax.lax.scan(iteration, search, jax.random.split(key, settings.num_iterations))
    return project(best[-1], safe)


def blocks(settings: CEMSettings) -> int:
    """The commands of a plan: one per period of the horizon with ``per_period``, else one."""
    return int(settings.horizon) if settings.per_period else 1


def mpc_controller(
    env: Any,
    env_params: Any,
    model: Plant,
    model_params: Any,
    settings: CEMSettings = DEFAULT_SETTINGS,
):
    """The MPC as a :data:`pipeline.evaluation.rollouts.Controller` for ``env`` (any plant).

    Its carry is ``(model_carry, model_position [3], plan [blocks, 3])``: the learned model run
    open loop on the commands the controller sends, and where the next search starts (the last
    command sent; planning per period, the rest of the last plan, its last command repeated);
    build the first one with :func:`initial_carry`.
    """
    steps = env.steps_per_action

    def act(key, obs, state, carry):
        model_carry, model_position, previous = carry
        offset = state.position - model_position
        planned = plan(key, model, model_params, model_carry, horizon_goals(env, state, settings)
                       - offset, previous, env_params.safe_set, steps, settings)
        command = planned[0]
        action = env.action_for(command, state.last_pressure, env_params)
        if env.incremental_actions:  # rate-limited: the model holds what will be sent
            command = project(env.command(action, state.last_pressure, env_params),
                              env_params.safe_set)
        model_carry, path = hold(model, model_params, model_carry, command, steps)
        following = jnp.concatenate([planned[1:], planned[-1:]]) if len(planned) > 1 else \
            command[None]
        return (model_carry, path[-1], following), action

    return act


def horizon_goals(env: Any, state: Any, settings: CEMSettings) -> chex.Array:
    """``[horizon, 3]`` m: the goal at the end of each period of the horizon from ``state``: the
    current goal, then, following a reference (``env.tracking``), the reference at the ends of
    the periods after it (:func:`pipeline.rl.envs.task.preview`); reaching, the current goal
    throughout."""
    if not env.tracking:
        return jnp.broadcast_to(state.goal, (settings.horizon, 3))
    ahead = task.preview(state.reference, state.time, env.control_hz, settings.horizon - 1)
    return jnp.concatenate([state.goal[None], ahead])


def initial_carry(model_carry: Any, model_position: chex.Array, preload: chex.Array,
                  settings: CEMSettings = DEFAULT_SETTINGS):
    """The MPC's carry at the start of an episode: the model settled where it starts, the plan
    holding the preload."""
    return (model_carry, jnp.asarray(model_position, jnp.float32),
            jnp.broadcast_to(jnp.asarray(preload, jnp.float32), (blocks(settings), 3)))
