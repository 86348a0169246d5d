"""Where an ensemble of forward models disagrees: the command sequences worth driving the arm
with to learn the most (uncertainty-targeted exploration, as ensemble-disagreement exploration
does), scored without touching the arm."""

from __future__ import annotations

from collections.abc import Sequence

import chex
import jax
import jax.numpy as jnp
import numpy as np

from pipeline.dynamics.model import DynamicsParams, predict_sequence


def held_at_model_rate(commands: np.ndarray, steps_per_command: int) -> np.ndarray:
    """Commands ``[..., N, valves]`` at the control rate as pressures at the model rate, each
    held ``steps_per_command`` model steps: ``[..., N * steps_per_command, valves]``."""
    if steps_per_command < 1:
        raise ValueError(f"steps_per_command must be >= 1, got {steps_per_command}")
    return np.repeat(np.asarray(commands, np.float32), int(steps_per_command), axis=-2)


def disagreement_m2(members: Sequence[DynamicsParams], pressures: np.ndarray,
                    initial_pose: np.ndarray) -> np.ndarray:
    """Per candidate, the ensemble's disagreement over its open-loop predictions [m²].

    ``pressures [C, T, 3]`` kPa at the model rate, ``initial_pose [3]`` m (where every
    candidate starts). For member predictions ``x_m[c, t]`` with mean ``x̄[c, t]``, returns
    ``mean_t mean_m |x_m[c, t] - x̄[c, t]|²``: ``[C]``. Needs at least two members.
    """
    if len(members) < 2:
        raise ValueError(f"disagreement needs at least two models, got {len(members)}")
    pressures = jnp.asarray(pressures, jnp.float32)
    chex.assert_rank(pressures, 3)
    pose = jnp.asarray(initial_pose, jnp.float32)
    predictions = jnp.stack([
        jax.vmap(predict_sequence, in_axes=(None, 0, None))(member, pressures, pose)
        for member in members])  # [M, C, T, 3]
    spread = jnp.sum(jnp.square(predictions - predictions.mean(axis=0)), axis=-1)  # [M, C, T]
    return np.asarray(spread.mean(axis=(0, 2)), np.float64)


def most_disputed(scores: np.ndarray, count: int) -> np.ndarray:
    """Indices of the ``count`` highest ``scores``, highest first (ties: the lower index)."""
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    return order[: int(count)]
