"""The reaching task's observation, one function for training and for the arm.

:class:`pipeline.rl.envs.learned.SoftArmReachEnv` builds its observations with :func:`observe`, and
so does the control loop on the arm (:mod:`pipeline.control.loop`), from the measured pose: a
policy sees on the arm exactly the inputs it was trained on (same standardization, error scaling
and last action).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp


def pressure_to_action(pressure: jax.Array, safe_set: Any) -> jax.Array:
    """``[..., 3]`` kPa -> ``[-1, 1]`` on each valve's range ``[p_min, p_max]`` (unclipped)."""
    return 2.0 * (pressure - safe_set.p_min) / (safe_set.p_max - safe_set.p_min) - 1.0


def update_error_integral(integral: jax.Array, measured: jax.Array, goal: jax.Array,
                          params: Any) -> jax.Array:
    """``[3]``: the accumulated error after a control period, ``decay * integral + (1 - decay) *
    (goal - measured) / error_scale_m`` (``params.error_integral_decay``, ``params.error_scale_m``):
    a leaky integral of the error on the scale of the observed error, 0 before the first period."""
    decay = params.error_integral_decay
    return decay * integral + (1.0 - decay) * (goal - measured) / params.error_scale_m


def observe(measured: jax.Array, goal: jax.Array, last_pressure: jax.Array, params: Any, *,
            include_error: bool, include_last_action: bool,
            error_integral: jax.Array | None = None, preview: jax.Array | None = None
            ) -> jax.Array:
    """``[obs_dim]`` float32: standardized measured position, standardized goal (, scaled error)
    (, accumulated error) (, last pressure in ``[-1, 1]``) (, preview).

    Args:
      measured: [3] m, the position as measured (the environment adds its observation noise).
      goal: [3] m.
      last_pressure: [3] kPa, the last command applied (the preload before the first).
      params: anything with ``obs_mean``, ``obs_scale`` ([3] m), ``error_scale_m`` (m) and
        ``safe_set`` (an ``EnvParams``).
      include_error: append ``(goal - measured) / error_scale_m`` [3].
      include_last_action: append the last pressure mapped to ``[-1, 1]`` [3].
      error_integral: [3], appended where given (:func:`update_error_integral`).
      preview: [P, 3] m, the goals of the next P control periods (tracking), appended where
        given as ``(preview - measured) / error_scale_m`` [3 P] (in the error's scale).
    """
    parts = [(measured - params.obs_mean) / params.obs_scale,
             (goal - params.obs_mean) / params.obs_scale]
    if include_error:
        parts.append((goal - measured) / params.error_scale_m)
    if error_integral is not None:
        parts.append(error_integral)
    if include_last_action:
        parts.append(pressure_to_action(last_pressure, params.safe_set))
    if preview is not None:
        parts.append(((preview - measured) / params.error_scale_m).reshape(-1))
    return jnp.concatenate(parts).astype(jnp.float32)
