"""The reaching task's observation, one function for training and for the arm.

:class:`pipeline.rl.envs.reach.SoftArmReachEnv` builds its observations with :func:`observe`, and
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


def update_reference_shift(shift: jax.Array, measured: jax.Array, goal: jax.Array,
                           params: Any) -> jax.Array:
    """``[3]`` m: where the reference a tracking policy observes is moved after a control period,
    ``shift + reference_integral_gain * (goal - measured)``, its length bounded by
    ``params.reference_shift_max_mm``: integral action on the tracking error (a steady offset
    between the path and the reference is taken out over about ``1 / gain`` periods); 0 before
    the first period, and for good with a gain of 0. ``goal`` is the goal of the period that led
    to ``measured`` (the reference at the time it was measured)."""
    shift = shift + params.reference_integral_gain * (goal - measured)
    limit = params.reference_shift_max_mm / 1000.0
    length = jnp.sqrt(jnp.sum(shift**2) + 1e-24)  # differentiable at 0 (analytic gradients)
    return shift * jnp.minimum(1.0, limit / length)


def observe(measured: jax.Array, goal: jax.Array, last_pressure: jax.Array, params: Any, *,
            include_error: bool, include_last_action: bool,
            error_integral: jax.Array | None = None, preview: jax.Array | None = None,
            reference_shift: jax.Array | None = None) -> jax.Array:
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
      reference_shift: [3] m (tracking, :func:`update_reference_shift`): where given, the goal
        and the preview are observed moved by it.
    """
    if reference_shift is not None:
        goal = goal + reference_shift
        preview = None if preview is None else preview + reference_shift
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
