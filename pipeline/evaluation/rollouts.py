"""Closed-loop rollouts with fixed goals, for evaluation (no auto-reset, goals set per step).

Every controller runs through the environment's own ``step_env`` (action mapping, action noise,
safe-set projection, zero-order hold), on any plant the environment wraps. A rollout of ``T``
control periods returns ``positions [T + 1, 3]`` m (row 0 the start) and the applied
``commands [T, 3]`` kPa; ``goals [T, 3]`` gives the goal in force in each period, so one function
serves single goals and consecutive goals.

:func:`rollout_together` runs several controllers at once on one environment: their episodes
share each period's plant step, so a program that rolls out every controller holds the plant
once; :func:`rollout` is its one episode of one controller.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np

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
    ``params.deadband_m`` of its goal sends the hold's command
    (:meth:`~pipeline.rl.envs.learned.SoftArmReachEnv.deadband_action`)."""
    chex.assert_shape(start_position, (3,))
    chex.assert_rank(goals, 2)

    def batch(tree, axes=1):  # leading axes of size 1: one seed (and one episode)
        return jax.tree.map(lambda leaf: jnp.asarray(leaf)[(None,) * axes], tree)

    [(positions, commands)] = rollout_together(
        env, params, (Kind(lambda _params, _env_params: controller, deadband),),
        [jnp.zeros((1,))], [batch(controller_carry, 2)], batch(key), batch(start_carry),
        batch(start_position), batch(goals), None if reference is None else batch(reference))
    return positions[0, 0], commands[0, 0]


class Kind(NamedTuple):
    """A kind of controller rolled out by :func:`rollout_together`: ``make(params, env_params)``
    builds one seed's controller from its parameters; ``deadband``: it acts as deployed
    (:meth:`~pipeline.rl.envs.learned.SoftArmReachEnv.deadband_action`)."""

    make: Callable[[Any, EnvParams], Controller]
    deadband: bool = False


def rollout_together(
    env: SoftArmReachEnv,
    params: EnvParams,
    kinds: Sequence[Kind],
    kind_params: Sequence[Any],
    kind_carries: Sequence[Any],
    keys: chex.Array,
    start_carries: Any,
    start_positions: chex.Array,
    goals: chex.Array,
    reference: Any = None,
) -> list[tuple[chex.Array, chex.Array]]:
    """Every seed of every kind of controller on the same ``E`` episodes, in one scan whose
    periods step the plant once for all of them.

    ``kind_params[k]``: kind ``k``'s parameters, leaves ``[S_k, ...]``; ``kind_carries[k]``: its
    controller carries, leaves ``[S_k, E, ...]``. Each episode's ``keys [E]``, ``start_carries``
    (leaves ``[E, ...]``), ``start_positions [E, 3]`` m, ``goals [E, T, 3]`` m and ``reference``
    (a tracking env's, leaves ``[E, ...]``; None: the goals) are the same for every seed and
    kind. Inside, the state has a row per seed of each kind (``R = sum S_k``), kinds in order.
    Returns, per kind, ``positions [S_k, E, T + 1, 3]`` m and ``commands [S_k, E, T, 3]`` kPa:
    what :func:`rollout` gives for each seed and episode, to float rounding.
    """
    chex.assert_rank(goals, 3)
    seeds = [int(jax.tree.leaves(param)[0].shape[0]) for param in kind_params]
    rows, steps = sum(seeds), goals.shape[1]
    if env.tracking and reference is None:
        reference = jax.vmap(references.goal_table, in_axes=(0, None))(goals, env.control_hz)

    def start(key, carry, position, goal_path, reference):
        return env.start_state(jax.random.fold_in(key, 1), carry, position, goal_path[0], params,
                               reference)

    states = jax.vmap(start)(keys, start_carries, start_positions, goals, reference)  # [E]
    holds = jax.vmap(env.initial_hold)(goals[:, 0])  # [E], the hold's memory (deadband kinds)
    states, holds = jax.tree.map(lambda leaf: jnp.broadcast_to(leaf, (rows, *leaf.shape)),
                                 (states, holds))
    bounds = np.cumsum([0, *seeds])
    deadband = np.repeat(np.array([kind.deadband for kind in kinds], bool), seeds)  # [R]

    def over_rows(function, axes):
        """``function`` over every row and episode. ``axes``, per argument: ``"episode"`` (the
        same in every row, ``[E, ...]``), ``"row"`` (``[R, E, ...]``) or None (``params``)."""
        each = jax.vmap(function, in_axes=tuple(None if a is None else 0 for a in axes))
        return jax.vmap(each, in_axes=tuple(0 if a == "row" else None for a in axes))

    def act(kind, kind_param, carry, act_keys, obs, state):
        def one_seed(seed_params, seed_carry, seed_obs, seed_state):
            controller = kind.make(seed_params, params)
            return jax.vmap(controller)(act_keys, seed_obs, seed_state, seed_carry)

        return jax.vmap(one_seed)(kind_param, carry, obs, state)

    def period(carry, inputs):
        states, holds, controller_carries = carry
        goal, period_keys = inputs  # [E, 3], [E]
        obs_keys, act_keys, step_keys = jnp.moveaxis(
            jax.vmap(lambda k: jax.random.split(k, 3))(period_keys), 1, 0)
        states = states.replace(goal=jnp.broadcast_to(goal, (rows, *goal.shape)))
        measured = over_rows(env.measure, ("episode", "row", None))(obs_keys, states.position,
                                                                    params)
        obs = over_rows(env.observe_measured, ("row", "row", None))(measured, states, params)
        carries, actions = [], []
        for number, kind in enumerate(kinds):
            part = slice(int(bounds[number]), int(bounds[number + 1]))
            kind_carry, action = act(kind, kind_params[number], controller_carries[number],
                                     act_keys, obs[part],
                                     jax.tree.map(lambda leaf, p=part: leaf[p], states))
            carries.append(kind_carry)
            actions.append(action)
        action = jnp.concatenate(actions)  # [R, E, 3]
        if deadband.any():
            holds, held = over_rows(env.deadband_action, ("row",) * 5 + (None,))(
                holds, action, measured, states.goal, states.last_pressure, params)
            action = jnp.where(deadband[:, None, None], held, action)
        _, states, _, _, info = over_rows(env.step_env, ("episode", "row", "row", None))(
            step_keys, states, action, params)
        return (states, holds, carries), (states.position, info["pressure"])

    period_keys = jax.vmap(lambda key: jax.random.split(key, steps))(keys)  # [E, T]
    _, (positions, commands) = jax.lax.scan(
        period, (states, holds, list(kind_carries)),
        (jnp.moveaxis(goals, 1, 0), jnp.moveaxis(period_keys, 1, 0)))
    positions = jnp.concatenate(  # [R, E, T + 1, 3]
        [jnp.broadcast_to(start_positions, (rows, *start_positions.shape))[:, :, None],
         jnp.moveaxis(positions, 0, 2)], axis=2)
    commands = jnp.moveaxis(commands, 0, 2)  # [R, E, T, 3]
    return [(positions[bounds[k]:bounds[k + 1]], commands[bounds[k]:bounds[k + 1]])
            for k in range(len(kinds))]


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
