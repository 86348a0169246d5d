"""Minibatches of a rollout for PPO's epochs, ``[M, ...]`` leaves scanned over M.

A feed-forward policy learns from single steps shuffled over time and environments; a recurrent
one from whole sequences, minibatched over environments and started from the hidden state the
rollout started with.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp


def step_minibatches(key: jax.Array, data: Any, num_minibatches: int) -> tuple[jax.Array, Any]:
    """``data`` (``[T, B, ...]`` leaves) shuffled over all T * B steps into ``num_minibatches``:
    ``-> (hidden [M, N, 1] zeros, data [M, N, ...])`` with ``N = T * B / M``; each minibatch
    is then seen by the network as one time step of N environments."""
    num_steps, num_envs = jax.tree.leaves(data)[0].shape[:2]
    size = num_steps * num_envs
    permutation = jax.random.permutation(key, size)
    data = jax.tree.map(
        lambda x: jnp.take(x.reshape(size, *x.shape[2:]), permutation, axis=0)
        .reshape(num_minibatches, -1, *x.shape[2:]), data)
    return jnp.zeros((num_minibatches, size // num_minibatches, 1)), data


def sequence_minibatches(key: jax.Array, data: Any, rollout_hidden: jax.Array,
                         num_minibatches: int) -> tuple[jax.Array, Any]:
    """``data`` (``[T, B, ...]`` leaves) as whole sequences of environments shuffled into
    ``num_minibatches``: ``-> (hidden [M, B / M, H], data [M, T, B / M, ...])``, ``hidden``
    the rollout's starting state of each environment (``rollout_hidden [B, H]``)."""
    num_steps, num_envs = jax.tree.leaves(data)[0].shape[:2]
    permutation = jax.random.permutation(key, num_envs)
    data = jax.tree.map(lambda x: jnp.take(x, permutation, axis=1), data)
    data = jax.tree.map(
        lambda x: jnp.swapaxes(x.reshape(num_steps, num_minibatches, -1, *x.shape[2:]), 0, 1),
        data)
    hidden = jnp.take(rollout_hidden, permutation, axis=0).reshape(
        num_minibatches, -1, rollout_hidden.shape[-1])
    return hidden, data
