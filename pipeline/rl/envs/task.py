"""The tracking task's references inside the environment (``env.task=track``).

In ``track`` each episode follows a :class:`~pipeline.arm.references.Reference` held in
``EnvState.reference``: the goal of control period ``k`` (from ``k / control_hz`` to ``(k + 1) /
control_hz`` s after the reset) is the reference at the period's end, ``(k + 1) / control_hz``,
the position the period is rewarded at. A training episode's reference is a random shape around
the goal a reaching episode would get (:func:`pipeline.arm.references.draw`, ranges in
``EnvParams``), or that goal itself with ``EnvParams.static_share``.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from pipeline.arm import references

TASKS = ("reach", "track")
MM_PER_M = 1000.0


def check_task(name: str, preview: int) -> None:
    """A ValueError unless ``name`` is a task and ``preview >= 0`` (nonzero only to track)."""
    if str(name) not in TASKS or int(preview) < 0 or (int(preview) and str(name) != "track"):
        raise ValueError(f"task must be one of {TASKS} and preview >= 0 (only with task=track), "
                         f"got task={name!r}, preview={preview}")


def draw_reference(key: jax.Array, goal: jax.Array, params: Any) -> references.Reference:
    """A training episode's reference around ``goal [3]`` m, drawn with the ranges of ``params``
    (``reference_size_{min,max}_mm`` mm, ``reference_period_{min,max}_s`` s, ``static_share``)."""
    ranges = references.DrawRanges(
        size_m=jnp.stack([params.reference_size_min_mm, params.reference_size_max_mm]) / MM_PER_M,
        period_s=jnp.stack([params.reference_period_min_s, params.reference_period_max_s]),
        static_share=params.static_share)
    return references.draw(key, goal, ranges)


def period_goal(reference: references.Reference, period: jax.Array, control_hz: float
                ) -> jax.Array:
    """``[3]`` m: the goal of control period ``period`` (0 after a reset): the reference at the
    period's end, ``(period + 1) / control_hz`` s."""
    return references.position(reference, (period + 1).astype(jnp.float32) / control_hz)


def preview(reference: references.Reference, period: jax.Array, control_hz: float, count: int
            ) -> jax.Array:
    """``[count, 3]`` m: the goals of the ``count`` control periods after ``period``, one period
    apart (the reference at ``(period + 1 + j) / control_hz`` s, ``j = 1 .. count``)."""
    ahead = period.astype(jnp.float32) + 1.0 + jnp.arange(1, count + 1, dtype=jnp.float32)
    return references.positions(reference, ahead / control_hz)


def goal_path(reference: references.Reference, periods: int, control_hz: float) -> jax.Array:
    """``[periods, 3]`` m: the goal of each control period ``0 .. periods - 1`` of an episode."""
    return references.positions(
        reference, jnp.arange(1, periods + 1, dtype=jnp.float32) / control_hz)
