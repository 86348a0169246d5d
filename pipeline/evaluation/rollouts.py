"""Closed-loop rollouts with fixed goals, for evaluation (no auto-reset, goals set per step).

Every controller runs through the environment's own ``step_env`` (action mapping, action noise,
safe-set projection, zero-order hold), on any plant the environment wraps. A rollout of ``T``
control periods returns ``positions [T + 1, 3]`` m (row 0 the start) and the applied
``commands [T, 3]`` kPa; ``goals [T, 3]`` gives the goal in force in each period, so one function
serves single goals and consecutive goals.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import chex
import jax
import jax.numpy as jnp

from pipeline.arm import references
from pipeline.rl.envs.learned import EnvParams, EnvState, SoftArmReachEnv

# A controller: (key, observation [obs_dim], state, controller_carry) -> (carry, action [3])
Controller = Callable[[chex.PRNGKey, chex.Array, EnvState, Any], tuple[Any, chex.Array]]


def rollout(
    env: SoftArmReachEnv,
    params: EnvParams,
    controller: Controller,
    controller_carry: Any,
    key: chex.PRNGKey,
    start_carry: Any,
    start_position: chex.Array,
    goals: chex.Array,
    reference: Any = None,
    deadband: bool = False,
) -> tuple[chex.Array, chex.Array]:
    """Run ``controller`` from a settled start for ``goals.shape[0]`` control periods (the
    episode's randomization, none with zero magnitudes, drawn as at a reset). A tracking
    environment (``env.tracking``) follows ``reference``, by default the goals themselves
    (:func:`pipeline.arm.references.goal_table`: its preview shows the goals to come). With
    ``deadband`` (reaching, as deployed), a period whose measured position lies within
    ``params.deadband_m`` of its goal keeps the last command
    (:meth:`~pipeline.rl.envs.learned.SoftArmReachEnv.deadband_action`)."""
    chex.assert_shape(start_position, (3,))
    chex.assert_rank(goals, 2)
    if env.tracking and reference is None:
        reference = references.goal_table(goals, env.control_hz)
    state = env.start_state(jax.random.fold_in(key, 1), start_carry, start_position, goals[0],
                            params, reference)

    def period(carry, inputs):
        state, controller_carry = carry
        goal, period_key = inputs
        obs_key, act_key, step_key = jax.random.split(period_key, 3)
        state = state.replace(goal=goal)
        measured = env.measure(obs_key, state.position, params)
        obs = env.observe_measured(measured, state, params)
        controller_carry, action = controller(act_key, obs, state, controller_carry)
        if deadband:
            action = env.deadband_action(action, measured, goal, state.last_pressure, params)
        _, state, _, _, info = env.step_env(step_key, state, action, params)
        return (state, controller_carry), (state.position, info["pressure"])

    keys = jax.random.split(key, goals.shape[0])
    _, (positions, commands) = jax.lax.scan(period, (state, controller_carry), (goals, keys))
    return jnp.concatenate([start_position[None], positions]), commands


def policy_controller(network: Any, policy_params: Any) -> Controller:
    """A trained actor-critic acting deterministically (its mean action); carry: hidden state."""
    from pipeline.rl.policy_io import deterministic_action

    def act(key, obs, state, carry):
        hidden, first = carry  # hidden [1, H]; first: True before the first step
        hidden, action = deterministic_action(network, policy_params, hidden, obs[None],
                                              first[None])
        return (hidden, jnp.zeros_like(first)), action[0]

    return act


def preload_controller(env: SoftArmReachEnv, params: EnvParams) -> Controller:
    """Do nothing: hold the preload."""
    return lambda key, obs, state, carry: (
        carry, env.action_for(params.preload, state.last_pressure, params))


def random_controller() -> Controller:
    """Uniformly random actions (the environment projects them onto the safe set)."""
    return lambda key, obs, state, carry: (carry, jax.random.uniform(key, (3,), minval=-1.0,
                                                                      maxval=1.0))
