"""The deterministic evaluation PPO runs during training: one episode per environment.

On a reaching environment (one whose parameters have a ``goal_tolerance_m``) every episode runs its
whole horizon, as in the evaluate stage: the goal tolerance does not end it, its
``final_distance_m`` is the distance at the last step and it succeeded if that is within the
tolerance. A policy that passes through the goal and leaves it again is not counted as there; it
is what ``pipeline.rl.policy_io.best_seed`` reads to choose the seed that drives an arm. On any
other environment an episode ends where the environment ends it (terminated or truncated).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pipeline.rl.networks import initial_hidden
from pipeline.rl.spaces import action_bounds, to_env_action


def evaluate_policy(env: Any, env_params: Any, network: Any, params: Any, key: jax.Array,
                    num_envs: int, num_steps: int, has_distance: bool,
                    bounds: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, jax.Array]:
    """``num_envs`` episodes of the mean action, ``num_steps`` steps at most each.

    ``bounds``: the action space's ``(low, high)``, read from concrete parameters beforehand
    (:func:`action_bounds`); needed where ``env_params`` are traced and the space depends on them
    (Pendulum's torque limit). Default: read from ``env_params``.

    Returns ``[E]`` per episode: ``episode_return``, ``episode_final_distance_m`` (NaN where the
    env reports no distance), ``episode_success`` (the final distance within the goal tolerance;
    terminated, on an env without one), ``episode_finished``; and their summaries
    ``mean_return``, ``median_final_distance_m``, ``success_rate``.
    """
    if num_envs == 0:  # evaluation switched off (saves compile time in tests)
        empty = jnp.zeros((0,))
        return {"episode_return": empty, "episode_final_distance_m": empty,
                "episode_success": empty.astype(bool),
                "episode_finished": empty.astype(bool), "mean_return": jnp.nan,
                "median_final_distance_m": jnp.nan, "success_rate": jnp.nan}
    low, high = action_bounds(env, env_params) if bounds is None else bounds
    tolerance = getattr(env_params, "goal_tolerance_m", None) if has_distance else None
    if tolerance is not None:  # the whole horizon: reaching the goal does not end an episode
        env_params = env_params.replace(goal_tolerance_m=jnp.full_like(tolerance, -jnp.inf))
    reset_key, episode_key = jax.random.split(key)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(
        jax.random.split(reset_key, num_envs), env_params)

    def step(carry, step_key):
        obs, state, hidden, reset, active, episode_return, record = carry
        hidden, pi, _ = network.apply(params, hidden, obs[None], reset[None])
        action = pi.mode()[0]
        obs, state, reward, terminated, truncated, info = jax.vmap(
            env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(step_key, num_envs), state, to_env_action(action, low, high),
            env_params)
        done = jnp.logical_or(terminated, truncated)
        ending = jnp.logical_and(active, done)
        distance = info["distance_m"] if has_distance else jnp.full(num_envs, jnp.nan)
        episode_return = episode_return + jnp.where(active, reward, 0.0)
        record = {
            "final_distance_m": jnp.where(active, distance, record["final_distance_m"]),
            "success": jnp.where(ending, terminated, record["success"]),
        }
        active = jnp.logical_and(active, ~done)
        return (obs, state, hidden, done, active, episode_return, record), None

    record = {"final_distance_m": jnp.full(num_envs, jnp.nan),
              "success": jnp.zeros(num_envs, bool)}
    carry = (obs, state, initial_hidden(network, num_envs), jnp.ones(num_envs, bool),
             jnp.ones(num_envs, bool), jnp.zeros(num_envs), record)
    carry, _ = jax.lax.scan(step, carry, jax.random.split(episode_key, num_steps))
    *_, active, episode_return, record = carry
    if tolerance is not None:
        record["success"] = record["final_distance_m"] <= tolerance
    return {
        "episode_return": episode_return,
        "episode_final_distance_m": record["final_distance_m"],
        "episode_success": record["success"],
        "episode_finished": ~active,
        "mean_return": episode_return.mean(),
        "median_final_distance_m": jnp.median(record["final_distance_m"]),
        "success_rate": record["success"].mean(),
    }
