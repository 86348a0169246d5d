"""PPO's losses: generalized advantage estimation and the clipped surrogate objective.

Time indices in a rollout of length T (leading axes ``[T, B]``): ``obs[t]`` is seen,
``action[t]`` taken, ``reward[t]``, ``terminated[t]``, ``truncated[t]`` come back.
"""

from __future__ import annotations

from typing import Any

import chex
import jax
import jax.numpy as jnp


def compute_gae(
    rewards: jax.Array,
    values: jax.Array,
    terminated: jax.Array,
    truncated: jax.Array,
    bootstrap_values: jax.Array,
    last_value: jax.Array,
    gamma: float,
    gae_lambda: float,
) -> tuple[jax.Array, jax.Array]:
    """Generalized advantage estimates and value targets, both ``[T, B]``.

    Args:
      rewards, values, terminated, truncated, bootstrap_values: ``[T, B]`` (see Transition).
      last_value: ``[B]``, V of the observation after the last step (the next rollout's first).

    The one-step target of step t bootstraps with ``V(obs[t+1])`` inside an episode, with
    ``bootstrap_values[t]`` where the episode was truncated at t, and with 0 where it terminated;
    the advantage recursion ``A_t = delta_t + gamma * lambda * A_{t+1}`` stops at every episode
    end (terminated or truncated).
    """
    chex.assert_equal_shape([rewards, values, terminated, truncated, bootstrap_values])
    chex.assert_rank(rewards, 2)
    chex.assert_shape(last_value, rewards.shape[1:])
    next_values = jnp.concatenate([values[1:], last_value[None]], axis=0)
    done = jnp.logical_or(terminated, truncated)
    next_values = jnp.where(done, bootstrap_values, next_values)
    next_values = jnp.where(terminated, 0.0, next_values)
    deltas = rewards + gamma * next_values - values
    continues = 1.0 - done.astype(rewards.dtype)

    def backward(advantage_next, step):
        delta, cont = step
        advantage = delta + gamma * gae_lambda * cont * advantage_next
        return advantage, advantage

    _, advantages = jax.lax.scan(backward, jnp.zeros_like(last_value), (deltas, continues),
                                 reverse=True)
    return advantages, advantages + values


def ppo_loss(params: Any, network: Any, hidden: jax.Array, batch: Any, advantage: jax.Array,
             target: jax.Array, config: Any) -> tuple[jax.Array, dict[str, jax.Array]]:
    """The clipped PPO objective on one minibatch: ``-> (total loss, diagnostics)``.

    Args:
      params: network variables; ``network`` applies them as ``(hidden, obs [T, B, D], reset
        [T, B]) -> (hidden, pi, value [T, B])``.
      hidden: ``[B, H]`` the recurrent state before ``batch`` (zeros of width 1 for an MLP).
      batch: a ``Transition`` with ``[T, B]`` leaves (``[1, N]`` for shuffled single steps).
      advantage, target: ``[T, B]`` GAE advantages and value targets.
      config: the agent config (clip_eps, clip_value, vf_coef, ent_coef).

    The advantages are standardized per minibatch; the value loss is clipped around the
    rollout's values where ``config.clip_value``.
    """
    _, pi, value = network.apply(params, hidden, batch.obs, batch.reset)
    log_prob = pi.log_prob(batch.action)
    if config.clip_value:
        value_clipped = batch.value + jnp.clip(value - batch.value, -config.clip_eps,
                                               config.clip_eps)
        value_loss = 0.5 * jnp.maximum(
            jnp.square(value - target), jnp.square(value_clipped - target)).mean()
    else:
        value_loss = 0.5 * jnp.square(value - target).mean()
    log_ratio = log_prob - batch.log_prob
    ratio = jnp.exp(log_ratio)
    advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
    actor_loss = -jnp.minimum(
        ratio * advantage,
        jnp.clip(ratio, 1.0 - config.clip_eps, 1.0 + config.clip_eps) * advantage,
    ).mean()
    entropy = pi.entropy().mean()
    total = actor_loss + config.vf_coef * value_loss - config.ent_coef * entropy
    aux = {
        "value_loss": value_loss,
        "actor_loss": actor_loss,
        "entropy": entropy,
        "approx_kl": ((ratio - 1.0) - log_ratio).mean(),
        "clip_fraction": (jnp.abs(ratio - 1.0) > config.clip_eps).mean(),
    }
    return total, aux
