"""The policy's action units ([-1, 1]) and the environment's ``Box`` action space."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def action_bounds(env: Any, env_params: Any) -> tuple[np.ndarray, np.ndarray]:
    """The environment's Box action bounds as float32 numpy arrays of the action shape."""
    space = env.action_space(env_params)
    shape = tuple(space.shape)
    low = np.broadcast_to(np.asarray(space.low, np.float32), shape)
    high = np.broadcast_to(np.asarray(space.high, np.float32), shape)
    return low, high


def to_env_action(action: jax.Array, low: jax.Array, high: jax.Array) -> jax.Array:
    """Policy action in [-1, 1] units (clipped) -> the environment's Box."""
    return low + (jnp.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (high - low)
