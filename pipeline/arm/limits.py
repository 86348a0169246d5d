"""The float64 checks of pressure limits, in NumPy only: what a command must pass before it leaves
the process (:func:`assert_safe`) and what a limits setting must be (:func:`validate_limits`).

Kept apart from the JAX projection (:mod:`pipeline.arm.safety`) so that the entry point and a
process that only checks commands (the guard between a controller and the valves) do not load JAX
for it.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class UnsafeCommandError(ValueError):
    """A pressure command outside the limits or the arm's rating was stopped before sending."""


def assert_safe(command: np.ndarray, limits: Any, what: str = "robot.limits") -> np.ndarray:
    """Final float64 gate before a command leaves the process; raises
    :class:`UnsafeCommandError` if unsafe. ``what`` names the bounds in the message."""
    p = np.asarray(command, dtype=np.float64)
    if not np.all(np.isfinite(p)):
        raise UnsafeCommandError(f"refusing non-finite pressure command {p.tolist()}")
    p_min, p_max, sum_max = float(limits.p_min), float(limits.p_max), float(limits.sum_max)
    if (p < p_min).any() or (p > p_max).any() or p.sum() > sum_max:
        raise UnsafeCommandError(
            f"refusing pressure command {p.tolist()} kPa outside {what}: "
            f"[{p_min}, {p_max}] per valve, sum <= {sum_max}"
        )
    return p


def validate_limits(limits: Any, n_valves: int = 3) -> None:
    """Reject limit settings whose safe set is empty or excludes the preload."""
    p_min, p_max, sum_max = float(limits.p_min), float(limits.p_max), float(limits.sum_max)
    if not p_min < p_max:
        raise ValueError(f"robot.limits: p_min={p_min} must be below p_max={p_max} kPa")
    if not n_valves * p_min < sum_max:
        raise ValueError(
            f"robot.limits: sum_max={sum_max} kPa must exceed {n_valves} x p_min={p_min} kPa"
        )
    preload = getattr(limits, "preload", None)
    if preload is not None:
        preload = float(preload)
        if not (p_min <= preload <= p_max and n_valves * preload <= sum_max):
            raise ValueError(
                f"robot.limits: preload={preload} kPa is outside the safe set "
                f"[{p_min}, {p_max}] per valve, sum <= {sum_max}"
            )
