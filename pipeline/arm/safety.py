"""The safe set of pressure commands and the projection every command passes through.

Safe set: ``p_min <= p_j <= p_max`` for every valve j and ``sum_j p_j <= sum_max`` (kPa).
Exploration, policies and the hardware path all call :func:`project`; the hardware path then
checks the projected command once more in float64 with :func:`pipeline.arm.limits.assert_safe`
before it leaves the process, so a bug upstream can stop a command but never send one outside the
limits.
"""

from __future__ import annotations

from typing import Any

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pipeline.arm.limits import validate_limits

# Bisection on the multiplier of the sum constraint: 40 halvings of a bracket of at most a few
# tens of kPa resolve it far below float32 precision.
_BISECTION_STEPS = 40
# The sum is projected a hair inside sum_max (relative _SUM_MARGIN plus 1e-6 kPa): float rounding
# in a reordered sum can then never push a projected command over the real limit.
_SUM_MARGIN = 1e-6
_INPUT_BOUND = 1e6  # kPa; inputs beyond are clipped to it before the projection


@struct.dataclass
class SafeSet:
    """Pressure limits in kPa, a pytree so it can live in environment parameters."""

    p_min: chex.Array
    p_max: chex.Array
    sum_max: chex.Array

    @classmethod
    def from_limits(cls, limits: Any, n_valves: int = 3) -> SafeSet:
        """Build from a config node with p_min, p_max, sum_max (and preload), checking it.

        The float32 bounds are rounded toward the inside of the set (6.9 kPa becomes the largest
        float32 not above 6.9), so a command at a float32 bound is within the float64 limits.
        """
        validate_limits(limits, n_valves)
        return cls(
            p_min=jnp.full((n_valves,), _float32_inside(limits.p_min, upward=True)),
            p_max=jnp.full((n_valves,), _float32_inside(limits.p_max, upward=False)),
            sum_max=jnp.asarray(_float32_inside(limits.sum_max, upward=False)),
        )


def _float32_inside(value: float, upward: bool) -> np.float32:
    """The float32 nearest ``value`` on the inside: not below it (upward) or not above it."""
    rounded = np.float32(value)
    if upward and float(rounded) < float(value):
        rounded = np.nextafter(rounded, np.float32(np.inf))
    if not upward and float(rounded) > float(value):
        rounded = np.nextafter(rounded, np.float32(-np.inf))
    return rounded


def on_boundary(pressures: Any, safe: SafeSet, tolerance_kpa: float = 0.01) -> np.ndarray:
    """``[...]`` bool: whether each command ``pressures [..., n_valves]`` kPa lies on the safe
    set's boundary, a valve within ``tolerance_kpa`` of ``p_min`` or ``p_max`` or the valves' sum
    within it of ``sum_max``: the arm gets all that its rating allows in some direction (the
    projection puts a command that asks for more there). NaN (no command) is not on it."""
    pressures = np.asarray(pressures, np.float64)
    p_min, p_max = np.asarray(safe.p_min, np.float64), np.asarray(safe.p_max, np.float64)
    on_box = ((pressures <= p_min + tolerance_kpa) | (pressures >= p_max - tolerance_kpa)).any(-1)
    on_sum = pressures.sum(-1) >= float(safe.sum_max) - tolerance_kpa
    return on_box | on_sum


def project(pressures: chex.Array, safe: SafeSet) -> chex.Array:
    """Euclidean projection of ``pressures [..., n_valves]`` onto the safe set.

    Clip to the box; where the sum is still too large, subtract the smallest common offset
    ``lam >= 0`` such that ``sum_j clip(p_j - lam, p_min, p_max) <= sum_max`` (the KKT solution of
    the projection onto box ∩ half-space), found by bisection. The bracket's upper end is always
    feasible, so the result is inside the set for any input, NaN and infinities included (NaN maps to p_min).
    """
    pressures = jnp.asarray(pressures, jnp.float32)
    chex.assert_axis_dimension(pressures, -1, safe.p_min.shape[-1])
    # Bound the input so the bisection bracket stays exact in float32; NaN means "no pressure".
    pressures = jnp.where(jnp.isnan(pressures), safe.p_min, pressures)
    pressures = jnp.clip(pressures, -_INPUT_BOUND, _INPUT_BOUND)
    target = safe.sum_max - _SUM_MARGIN * jnp.abs(safe.sum_max) - 1e-6

    def clipped(lam):
        return jnp.clip(pressures - lam[..., None], safe.p_min, safe.p_max)

    def bisect(_, bracket):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        feasible = clipped(mid).sum(-1) <= target
        return jnp.where(feasible, lo, mid), jnp.where(feasible, mid, hi)

    lo = jnp.zeros(pressures.shape[:-1], pressures.dtype)
    hi = jnp.maximum(jnp.max(pressures - safe.p_min, axis=-1), 0.0) + 1.0
    _, hi = jax.lax.fori_loop(0, _BISECTION_STEPS, bisect, (lo, hi))
    box = clipped(jnp.zeros_like(lo))
    return jnp.where((box.sum(-1) <= target)[..., None], box, clipped(hi))
