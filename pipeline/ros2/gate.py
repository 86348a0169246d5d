"""The safety gate every pressure command passes on its way to the valves.

First the same projection onto the safe set as the exploration (:func:`pipeline.arm.safety.project`),
then the float64 check :func:`pipeline.arm.limits.assert_safe` against ``robot.limits`` and the
arm's ``robot.rating`` right before it is published: a bug upstream (or a config whose limits
escaped validation) can stop the collection but never send a command outside either.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pipeline.arm.limits import assert_safe
from pipeline.arm.safety import SafeSet, project
from pipeline.schemas import RobotConfig


class CommandGate:
    """``gate(pressures) -> safe float64 pressures [kPa]``; raises ``ValueError`` if unsafe.

    :meth:`project` and :meth:`check` are the two halves, for a caller that projects ahead of
    time and checks right before publishing.
    """

    def __init__(self, limits: Any, n_valves: int, rating: Any = None):
        self.limits, self.rating = limits, rating
        self._safe = SafeSet.from_limits(limits, n_valves)
        self._project = jax.jit(project)
        self.preload = self(np.full(n_valves, float(limits.preload)))  # compiles before a run

    def project(self, pressures: np.ndarray) -> np.ndarray:
        projected = np.asarray(
            self._project(jnp.asarray(pressures, jnp.float32), self._safe), np.float64)
        # The projection works in float32: a bound such as 6.9 kPa rounds to 6.9000001, which the
        # float64 gate would refuse. Clipping to the float64 box moves a command only inward.
        return np.clip(projected, float(self.limits.p_min), float(self.limits.p_max))

    @classmethod
    def for_robot(cls, robot: RobotConfig) -> CommandGate:
        """The gate of a robot config: its ``limits`` inside its ``rating``."""
        return cls(robot.limits, int(robot.n_valves), robot.rating)

    def check(self, pressures: np.ndarray) -> np.ndarray:
        """``pressures`` in float64 if inside the limits and the rating; else
        :class:`pipeline.arm.limits.UnsafeCommandError`."""
        if self.rating is not None:
            assert_safe(pressures, self.rating, "the arm's rating robot.rating")
        return assert_safe(pressures, self.limits)

    def __call__(self, pressures: np.ndarray) -> np.ndarray:
        return self.check(self.project(pressures))
