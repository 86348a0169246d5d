"""The learned environment's pytrees: its parameters (:class:`EnvParams`), an episode's state
(:class:`EnvState`) and randomization draw (:class:`Perturbation`), the randomization's
magnitudes (:class:`Randomization`) and the hold's memory (:class:`HoldState`).

:class:`~pipeline.rl.envs.reach.SoftArmReachEnv` steps them;
:func:`~pipeline.rl.envs.learned.make_env_params` builds :class:`EnvParams` for a plant.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pipeline.arm.safety import SafeSet
from pipeline.schemas import EnvConfig


@struct.dataclass
class Randomization:
    """Magnitudes of the per-episode randomization around the plant (zero: none).

    gain_std: [3], std of each valve's gain ``1 + N(0, gain_std)`` on the command (unitless).
    offset_std: [3] kPa, std of each valve's offset added to the command.
    max_delay_steps: int32 scalar, the previous command is held for ``U{0 .. max_delay_steps}``
      plant steps at the start of each control period (at most ``steps_per_action``: one period).
    rest_offset_std: [3] m, std of the offset added to the plant's position (rest pose error).
    drift_std: [3] m/s, std of the rate at which that offset grows along the episode.
    saturation_max: scalar 1/kPa, the chambers saturate about the preload by ``U(0,
      saturation_max)`` (:class:`Perturbation` ``saturation``).
    """

    gain_std: jax.Array
    offset_std: jax.Array
    max_delay_steps: jax.Array
    rest_offset_std: jax.Array
    drift_std: jax.Array
    saturation_max: jax.Array


def randomization(gain_std: float | jax.Array = 0.0, offset_std_kpa: float | jax.Array = 0.0,
                  max_delay_steps: int = 0, rest_offset_std_m: float | jax.Array = 0.0,
                  drift_std_m_per_s: float | jax.Array = 0.0,
                  saturation_max_per_kpa: float = 0.0) -> Randomization:
    """:class:`Randomization` from scalars or per-valve / per-axis ``[3]`` values (default: none)."""
    if int(max_delay_steps) < 0:
        raise ValueError(f"max_delay_steps must be >= 0, got {max_delay_steps}")
    if not (np.isfinite(saturation_max_per_kpa) and saturation_max_per_kpa >= 0):
        raise ValueError(f"randomization saturation_max_per_kpa must be finite and >= 0, got "
                         f"{saturation_max_per_kpa}")
    values = {"gain_std": gain_std, "offset_std": offset_std_kpa,
              "rest_offset_std": rest_offset_std_m, "drift_std": drift_std_m_per_s}
    for name, value in values.items():
        if np.any(np.asarray(value) < 0):
            raise ValueError(f"randomization {name} must be >= 0, got {value}")
    vector = lambda value: jnp.broadcast_to(jnp.asarray(value, jnp.float32), (3,))  # noqa: E731
    return Randomization(**{name: vector(value) for name, value in values.items()},
                         max_delay_steps=jnp.asarray(int(max_delay_steps), jnp.int32),
                         saturation_max=jnp.asarray(float(saturation_max_per_kpa), jnp.float32))


@struct.dataclass
class Perturbation:
    """One episode's draw of the randomization (a pytree; see :class:`Randomization`).

    gain: [3], multiplies each valve's command (1: none).
    offset: [3] kPa, added to it.
    delay: int32 scalar, plant steps of each control period that the previous command is held.
    rest_offset: [3] m, added to the plant's position.
    drift: [3] m/s, the position offset grows by ``drift * seconds since the reset``.
    received: [3] kPa, the pressure the plant received last (held during the delay; the preload
      at reset, which the start states settled at).
    saturation: scalar 1/kPa, each valve's pressure (after gain and offset) reaches the plant as
      ``preload + tanh(a (p - preload)) / a`` (``a = saturation``; 0: as it is): chambers that
      answer less the farther their pressure lies from the preload
      (:func:`pipeline.arm.sim_arm.saturating`).
    """

    gain: jax.Array
    offset: jax.Array
    delay: jax.Array
    rest_offset: jax.Array
    drift: jax.Array
    received: jax.Array
    saturation: jax.Array


@struct.dataclass
class EnvState:
    """State of one episode (a pytree).

    plant_carry: the plant's carry after the last step.
    position: [3] m, true marker position at the end of the last control period.
    goal: [3] m.
    last_pressure: [3] kPa, the last command applied (the preload after a reset).
    time: int32 scalar, control periods since the reset.
    perturbation: this episode's randomization draw (:class:`Perturbation`, from
      :meth:`~pipeline.rl.envs.reach.SoftArmReachEnv.start_state`); ``position`` is the plant's
      position shifted by its offset. None only in a state that is observed, never stepped.
    error_integral: [3], the accumulated scaled error (:func:`observation.update_error_integral`
      of the measured positions since the reset; zeros at a reset). None like ``perturbation``.
    periods_within: int32 scalar, consecutive control periods up to now that ended within the
      goal tolerance (0 at a reset). None like ``perturbation``.
    reference: the episode's reference (``pipeline.arm.references.Reference``); None to reach.
    reference_shift: [3] m, tracking: where the observed reference is moved to
      (:func:`observation.update_reference_shift` of the measured positions since the reset;
      zeros at a reset). None like ``perturbation``.
    """

    plant_carry: Any
    position: jax.Array
    goal: jax.Array
    last_pressure: jax.Array
    time: jax.Array
    perturbation: Perturbation | None = None
    error_integral: jax.Array | None = None
    periods_within: jax.Array | None = None
    reference: Any = None
    reference_shift: jax.Array | None = None


@struct.dataclass
class HoldState:
    """What the hold of deployment remembers between control periods (a pytree; leaves may carry
    leading batch axes): :meth:`~pipeline.rl.envs.reach.SoftArmReachEnv.deadband_action` reads
    and returns it, :meth:`~pipeline.rl.envs.reach.SoftArmReachEnv.initial_hold` starts it.

    scale: the share of ``hold_gain`` in force (1 at a new goal; multiplied by
      ``hold_backoff`` after every period whose correction overshot the goal).
    error: [3] m, ``goal - measured`` at the last period.
    held: bool scalar, the last period sent the hold's command.
    goal: [3] m, the last period's goal (a different goal starts the hold afresh).
    """

    scale: jax.Array
    error: jax.Array
    held: jax.Array
    goal: jax.Array


@struct.dataclass
class EnvParams:
    """Everything that varies: the plant, limits, resets, goals, noise (a pytree: vmap it).

    plant: the plant's parameters (e.g. ``DynamicsParams``, ``SimPlantParams``).
    safe_set: pressure limits (kPa).
    preload: [3] kPa.
    reset_carries: bank of settled plant carries, every leaf with a leading [N] axis.
    reset_positions: [N, 3] m, the pose of each settled carry.
    reset_initial_poses: [N, 3] m, the pose each of them settled from (before the preload hold).
    goal_set: [G, 3] m, the goals of ``goal_mode=data``.
    goal_from_data: bool scalar, True for ``goal_mode=data``, False for ``perturb``.
    goal_perturbation_m: m, std of the ``perturb`` goals around the initial pose (per axis).
    goal_redraw_periods: int32 scalar, a new goal after every this many control periods (0:
      never).
    goal_tolerance_m: m, the distance within which a control period counts as at the goal.
    hold_periods: int32 scalar >= 1, terminate after this many consecutive periods at the goal.
    hold_bonus_mm: mm of reward for every control period that ends at the goal.
    deadband_m: m, deployment only: a control period whose measured position is within it of the
      goal does not send the policy's action
      (:meth:`~pipeline.rl.envs.reach.SoftArmReachEnv.deadband_action`; 0: off).
    hold_gain: the share of the measured error the command corrects per control period there
      (0: the last command stays).
    hold_backoff: what the hold's gain is multiplied by after a correction that overshot (the
      error turned past the goal and grew), until the goal changes (1: a fixed gain).
    hold_map: [3 valves, 3 axes] kPa/m, the damped inverse of the static map of the model the
      policy was trained in (:func:`~pipeline.rl.envs.learned.with_hold_map`; zeros where the
      hold does not correct).
    obs_mean, obs_scale: [3] m, standardization of positions and goals in the observation.
    obs_noise_std_m: m, Gaussian noise on the observed position.
    error_scale_m: m, divides ``goal - measured`` in the observation (``include_error``).
    error_integral_decay: per control period, the accumulated error's weight on its past
      (``include_error_integral``).
    action_step_kpa: kPa, the change of a command per control period at action 1
      (``incremental_actions`` only).
    action_noise_std_kpa: kPa, Gaussian noise on the commanded pressures (before projection).
    command_change_cost_mm_per_kpa: mm per kPa, the reward's price on the summed change of the
      command.
    static_share, reference_size_*, reference_period_*: ``task="track"``'s draws
      (:func:`.task.draw_reference`).
    reference_integral_gain, reference_shift_max_mm: ``task="track"``: the share of the measured
      error the observed reference moves by per control period, and the most it moves [mm]
      (:func:`observation.update_reference_shift`; gain 0: never).
    randomization: magnitudes of the per-episode randomization around the plant.
    max_steps: control periods before truncation (gymnax reads it as ``max_steps_in_episode``).

    The fields named as settings of the env schema (:class:`pipeline.schemas.EnvConfig`) take
    their values from it by name (:func:`setting_values`).
    """

    plant: Any
    safe_set: SafeSet
    preload: jax.Array
    reset_carries: Any
    reset_positions: jax.Array
    reset_initial_poses: jax.Array
    goal_set: jax.Array
    goal_from_data: jax.Array
    goal_perturbation_m: jax.Array
    goal_redraw_periods: jax.Array
    goal_tolerance_m: jax.Array
    hold_periods: jax.Array
    hold_bonus_mm: jax.Array
    deadband_m: jax.Array
    hold_gain: jax.Array
    hold_backoff: jax.Array
    hold_map: jax.Array
    obs_mean: jax.Array
    obs_scale: jax.Array
    obs_noise_std_m: jax.Array
    error_scale_m: jax.Array
    error_integral_decay: jax.Array
    action_step_kpa: jax.Array
    action_noise_std_kpa: jax.Array
    command_change_cost_mm_per_kpa: jax.Array
    randomization: Randomization
    static_share: jax.Array
    reference_size_min_mm: jax.Array
    reference_size_max_mm: jax.Array
    reference_period_min_s: jax.Array
    reference_period_max_s: jax.Array
    reference_integral_gain: jax.Array
    reference_shift_max_mm: jax.Array
    max_steps: int = struct.field(pytree_node=False)

    @property
    def max_steps_in_episode(self) -> int:
        """gymnax's name of :attr:`max_steps` (its truncation reads it)."""
        return self.max_steps


# EnvParams fields of the env schema's name that are not copied: the randomization's magnitudes
# are set in seconds there and in plant steps here (:func:`randomization`, by the caller)
_DERIVED = ("randomization",)
_DTYPES = {float: jnp.float32, int: jnp.int32, bool: jnp.bool_}


def setting_values(settings: EnvConfig) -> dict[str, Any]:
    """The :class:`EnvParams` fields that are settings of the env schema, copied by name from
    ``settings`` (an :class:`~pipeline.schemas.EnvConfig`): scalars of the schema's type (float32,
    int32, bool), a static field (``max_steps``) as it is. One name from the YAML to the jitted
    code: a setting reaches the environment by having the field's name in both."""
    declared = typing.get_type_hints(EnvConfig)
    values = {}
    for f in dataclasses.fields(EnvParams):
        if f.name not in declared or f.name in _DERIVED:
            continue
        value = getattr(settings, f.name)
        static = not f.metadata.get("pytree_node", True)
        values[f.name] = declared[f.name](value) if static else jnp.asarray(
            value, _DTYPES[declared[f.name]])
    return values

