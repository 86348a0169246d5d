"""Goal-reaching with a soft arm as a gymnax environment, on any :class:`~pipeline.rl.envs.Plant`.

One environment step is one control period (``1 / control_hz`` s, 2 Hz as in the recorded data):
the action is held while the plant advances ``plant.model_hz / control_hz`` of its own steps
(zero-order hold, as the data was recorded).

- **Action** ``[3]`` in ``[-1, 1]`` (clipped), mapped linearly onto each valve's range
  ``[p_min, p_max]`` kPa; or, with ``incremental_actions``, the change of each valve's last
  command, ``action * action_step_kpa`` kPa per control period (integral action: the commands stand
  still only where the policy's output is zero, whatever pressure that takes on this plant).
  Plus Gaussian action noise (kPa), then projected onto the safe set
  (:func:`pipeline.arm.safety.project`) before it reaches the plant.
- **Observation** ``[6]``: the measured position (plus Gaussian noise, m) and the goal, both
  standardized with ``obs_mean`` / ``obs_scale``; with ``include_error`` ``+3``, the error
  ``goal - measured`` divided by ``error_scale_m`` (a few mm, so that the last millimetres are not
  a hundredth of an input's range); with ``include_error_integral`` ``+3``, the accumulated
  error ``I_t = decay * I_(t-1) + (1 - decay) * (goal - measured_t) / error_scale_m`` after each
  control period (``EnvState.error_integral``, 0 at a reset; ``EnvParams.error_integral_decay``);
  with ``include_last_action`` ``+3``, the last applied pressure mapped back to ``[-1, 1]``.
- **Reward** ``-||goal - position||`` in **millimetres** at the end of the control period, minus
  ``command_change_cost_mm_per_kpa`` (mm per kPa, 0 by default) times the summed absolute change of the
  applied command ``sum_v |p_t - p_{t-1}|`` kPa: a price on moving the valves, so that a policy
  that can stand still at the goal does so instead of dithering around it.
  Plus ``hold_bonus_mm`` for every control period that ends within ``goal_tolerance_m`` (0 by
  default): a reward for staying at the goal, not only for getting there.
- **Terminated** when the distance has been within ``goal_tolerance_m`` (1 mm) at the end of
  ``hold_periods`` consecutive control periods (1 by default: at the first arrival;
  ``EnvState.periods_within`` counts them, a period outside the tolerance sets it back to 0);
  **truncated** by gymnax at ``max_steps_in_episode`` steps. Both are returned separately
  (gymnax 1.x). With ``hold_periods > 1`` an episode goes on after its first arrival, so the
  policy is trained in the states after arrival, where evaluation and the arm keep it.
- **Reset.** The plant rests at the preload: an initial pose (rest pose ± its spread) seeds the
  plant's carry, the preload is held for ``settle_seconds`` and the episode starts from the
  resulting pose. Settling takes tens of plant steps, and gymnax computes a reset on every step
  (auto-reset), so the settled states are computed once, in
  :func:`~pipeline.rl.envs.learned.make_env_params`, into a bank of ``reset_bank_size`` states in
  ``EnvParams``; a reset draws one of them.
- **Goal.** ``goal_mode=data``: uniform over ``goal_set`` (positions seen in the data or predicted
  by the model); ``goal_mode=perturb`` (the paper): ``initial_pose + N(0, 1) * perturbation``.
  With ``goal_redraw_periods = k > 0`` a new goal is drawn after every k-th control period of
  an episode, in the same way (``perturb``: around the position then); the reward of that period
  is still the old goal's, the count of periods at the goal starts again.
- **Tracking** (``task="track"``): the goal of each control period is a reference at its end,
  no termination, no redraws; ``preview`` adds ``3 * preview`` observations (:mod:`.task`).
- **Randomization around the plant** (:class:`Randomization`, magnitudes in
  ``EnvParams.randomization``, all zero by default: the nominal plant), drawn once per episode at
  reset into ``EnvState.perturbation`` (:class:`Perturbation`): each valve receives
  ``gain * command + offset`` (gain ``1 + N(0, gain_std)``, offset ``N(0, offset_std)`` kPa), then
  projected onto the safe set and, where the chambers saturate (``a ~ U(0, saturation_max)``
  1/kPa), pulled toward the preload as ``preload + tanh(a (p - preload)) / a``; the previous
  received command is held for the first
  ``delay ~ U{0 .. max_delay_steps}`` plant steps of every control period; the plant's position is
  shifted by ``rest_offset + drift * seconds since the reset`` (``N(0, std)`` m and m/s per axis).
  The policy observes (and ``last_pressure`` holds) the command it sent, not what the plant got.

Everything that varies between fitted models or settings is in :class:`EnvParams`; only the
plant's static description and the step counts live on the environment object.
"""

from __future__ import annotations

from typing import Any

import chex
import jax
import jax.numpy as jnp
from gymnax.environments import environment, spaces

from pipeline.arm.safety import project
from pipeline.arm.sim_arm import saturating
from pipeline.rl.envs import observation, task
from pipeline.rl.envs.params import EnvParams, EnvState, HoldState, Perturbation
from pipeline.rl.envs.plants import NUM_VALVES, POSITION_DIM, Plant, hold
from pipeline.rl.envs.task import check_task

MM_PER_M = 1000.0
# the reset's randomization draws come from fold_in(key, _PERTURBATION_STREAM), so that the
# reset's other draws (split from the key as before randomization existed) stay as they were
_PERTURBATION_STREAM = 1
# and a step's goal redraw from fold_in(key, _REDRAW_STREAM): the step's other draws stay as
# they were without redraws
_REDRAW_STREAM = 2
_REFERENCE_STREAM = 3  # and a tracking episode's reference at its reset
# the chambers' saturation of an episode from fold_in(perturbation key, _SATURATION_STREAM): the
# randomization's other draws stay as they were without it
_SATURATION_STREAM = 4
# a correction overshot where the error turned past the goal and grew, beyond this share of the
# hold's radius (env.deadband_m)
HOLD_OVERSHOOT_SHARE = 0.25


class SoftArmReachEnv(environment.Environment[EnvState, EnvParams]):
    """Reach a goal position with a pneumatic soft arm; see the module docstring.

    Args:
      plant: the dynamics (static functions and rate).
      control_hz: rate of the actions; ``plant.model_hz / control_hz`` must be an integer.
      settle_seconds: how long the preload is held before an episode (used by
        :func:`~pipeline.rl.envs.learned.make_env_params` to fill the reset bank).
      include_last_action: append the last applied pressure (in ``[-1, 1]``) to the observation.
      include_error: append ``(goal - measured) / error_scale_m`` to the observation.
      include_error_integral: append the accumulated error (``EnvState.error_integral``).
      incremental_actions: an action changes the last command (``params.action_step_kpa`` kPa at
        1) instead of setting it.
      task, preview: ``reach`` or ``track``, observing the goals of ``preview`` next periods.

    Its step is differentiable in the action, the state and the parameters (each plant is JAX
    arithmetic; the projection onto the safe set passes gradients where a pressure is inside the
    box, its sum multiplier held constant): ``env.with_transition_gradients()`` (gymnax) is the
    copy whose observations and states keep them (``pipeline.rl.apg``).
    """

    _supports_transition_gradients = True

    def __init__(self, plant: Plant, control_hz: float = 2.0, settle_seconds: float = 5.0,
                 include_last_action: bool = False, include_error: bool = False,
                 incremental_actions: bool = False, include_error_integral: bool = False,
                 task: str = "reach", preview: int = 0):
        super().__init__()
        check_task(task, preview)
        ratio = plant.model_hz / control_hz
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-6:
            raise ValueError(
                f"plant rate {plant.model_hz} Hz must be an integer multiple of the control rate "
                f"{control_hz} Hz")
        self.plant = plant
        self.control_hz = float(control_hz)
        self.steps_per_action = round(ratio)
        self.settle_steps = max(1, round(settle_seconds * plant.model_hz))
        self.include_last_action = bool(include_last_action)
        self.include_error = bool(include_error)
        self.include_error_integral = bool(include_error_integral)
        self.incremental_actions = bool(incremental_actions)
        self.tracking = str(task) == "track"
        self.preview = int(preview)

    # -----------------------------------------------------------------------------------------
    # gymnax API
    # -----------------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return f"SoftArmReach-{self.plant.name}"

    @property
    def num_actions(self) -> int:
        return NUM_VALVES

    @property
    def default_params(self) -> EnvParams:
        raise ValueError("SoftArmReachEnv has no default parameters: build them with "
                         "pipeline.rl.envs.make_env_params(env, plant_params, ...)")

    @property
    def obs_dim(self) -> int:
        return (2 * POSITION_DIM + (POSITION_DIM if self.include_error else 0)
                + (POSITION_DIM if self.include_error_integral else 0)
                + (NUM_VALVES if self.include_last_action else 0) + POSITION_DIM * self.preview)

    def action_space(self, params: EnvParams | None = None) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, (NUM_VALVES,), jnp.float32)

    def observation_space(self, params: EnvParams | None = None) -> spaces.Box:
        return spaces.Box(-jnp.inf, jnp.inf, (self.obs_dim,), jnp.float32)

    def reset_env(self, key: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
        """Draw a settled start state and a goal; returns ``(obs [obs_dim], state)``."""
        index_key, perturb_key, obs_key = jax.random.split(key, 3)
        # one draw of two indices: [start state in the bank, goal in the goal set]
        bank_index, goal_index = jax.random.randint(
            index_key, (2,), 0, jnp.array([params.reset_positions.shape[0],
                                           params.goal_set.shape[0]]))
        carry = jax.tree.map(lambda leaf: leaf[bank_index], params.reset_carries)
        position = params.reset_positions[bank_index]
        perturbed_goal = position + params.goal_perturbation_m * jax.random.normal(
            perturb_key, (POSITION_DIM,))
        data_goal = params.goal_set[goal_index]
        goal = jnp.where(params.goal_from_data, data_goal, perturbed_goal)
        reference = None
        if self.tracking:
            reference = task.draw_reference(jax.random.fold_in(key, _REFERENCE_STREAM), goal, params)
            goal = task.period_goal(reference, jnp.zeros((), jnp.int32), self.control_hz)
        state = self.start_state(jax.random.fold_in(key, _PERTURBATION_STREAM), carry, position,
                                 goal, params, reference)
        return self.observe(obs_key, state, None, params), state

    def start_state(self, key: jax.Array, plant_carry: Any, position: jax.Array, goal: jax.Array,
                    params: EnvParams, reference: Any = None) -> EnvState:
        """The state of an episode starting from a settled plant carry at ``position [3]`` m
        (a reset-bank entry) with ``goal [3]`` m (and, tracking, ``reference``): this episode's
        randomization is drawn from ``key`` and the position shifted by its rest offset."""
        perturbation = self.draw_perturbation(key, params)
        return EnvState(plant_carry, position + perturbation.rest_offset, goal, params.preload,
                        jnp.zeros((), jnp.int32), perturbation, jnp.zeros(POSITION_DIM),
                        jnp.zeros((), jnp.int32), reference if self.tracking else None,
                        jnp.zeros(POSITION_DIM))

    def draw_perturbation(self, key: jax.Array, params: EnvParams) -> Perturbation:
        """One episode's :class:`Perturbation` drawn with ``params.randomization`` (one key per
        draw); with zero magnitudes exactly the nominal plant (gain 1, offsets 0, no delay)."""
        spread = params.randomization
        gain_key, offset_key, delay_key, rest_key, drift_key = jax.random.split(key, 5)
        max_delay = jnp.minimum(spread.max_delay_steps, self.steps_per_action)
        return Perturbation(
            gain=1.0 + spread.gain_std * jax.random.normal(gain_key, (NUM_VALVES,)),
            offset=spread.offset_std * jax.random.normal(offset_key, (NUM_VALVES,)),
            delay=jax.random.randint(delay_key, (), 0, max_delay + 1),
            rest_offset=spread.rest_offset_std * jax.random.normal(rest_key, (POSITION_DIM,)),
            drift=spread.drift_std * jax.random.normal(drift_key, (POSITION_DIM,)),
            received=params.preload,
            saturation=spread.saturation_max * jax.random.uniform(
                jax.random.fold_in(key, _SATURATION_STREAM), ()))

    def step_env(self, key: jax.Array, state: EnvState, action: jax.Array, params: EnvParams
                 ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, dict[str, Any]]:
        """One control period: ``action [3]`` in [-1, 1] held for ``steps_per_action`` steps.

        Returns ``(obs, state, reward [mm], terminated, info)`` (the reward is <= 0 unless
        ``params.hold_bonus_mm`` is positive); ``info["distance_m"]`` is
        the distance to the goal at the end of the period and ``info["pressure"]`` the applied
        (projected) command in kPa (before the episode's gain, offset and delay).
        """
        chex.assert_shape(action, (NUM_VALVES,))
        action_noise_key, obs_key = jax.random.split(key)
        pressure = self.command(action, state.last_pressure, params)
        pressure = pressure + params.action_noise_std_kpa * jax.random.normal(
            action_noise_key, (NUM_VALVES,))
        perturbation = state.perturbation
        received = project(perturbation.gain * pressure + perturbation.offset, params.safe_set)
        received = jnp.where(perturbation.saturation > 0,  # none: the command exactly
                             saturating(received, perturbation.saturation, params.preload),
                             received)  # between the preload and it: still in the safe set
        pressure = project(pressure, params.safe_set)
        carry, positions = self._hold_delayed(params.plant, state.plant_carry,
                                              perturbation.received, received,
                                              perturbation.delay)
        seconds = (state.time + 1).astype(jnp.float32) / self.control_hz
        position = positions[-1] + (perturbation.rest_offset + perturbation.drift * seconds)
        distance = jnp.linalg.norm(state.goal - position)
        change = jnp.sum(jnp.abs(pressure - state.last_pressure))  # [] kPa, applied commands
        measured = self.measure(obs_key, position, params)
        integral = observation.update_error_integral(state.error_integral, measured, state.goal,
                                                     params)
        shift = state.reference_shift
        if self.tracking:
            shift = observation.update_reference_shift(shift, measured, state.goal, params)
        within = distance <= params.goal_tolerance_m
        periods_within = jnp.where(within, state.periods_within + 1, 0)
        terminated = periods_within >= params.hold_periods
        reward = (-MM_PER_M * distance - params.command_change_cost_mm_per_kpa * change
                  + params.hold_bonus_mm * within)
        if self.tracking:  # the next period's goal; no end at the goal, no redraws
            terminated = jnp.zeros((), bool)
            goal = task.period_goal(state.reference, state.time + 1, self.control_hz)
        else:
            period = params.goal_redraw_periods
            redraw = (period > 0) & ((state.time + 1) % jnp.maximum(period, 1) == 0)
            goal = jnp.where(redraw, self.draw_goal(jax.random.fold_in(key, _REDRAW_STREAM),
                                                    position, params), state.goal)
            periods_within = jnp.where(redraw, 0, periods_within)
        state = EnvState(carry, position, goal, pressure, state.time + 1,
                         perturbation.replace(received=received), integral, periods_within,
                         state.reference, shift)
        obs = self.observe_measured(measured, state, params)
        obs, state = self._apply_transition_gradient_policy(obs, state)
        return obs, state, reward, terminated, {"distance_m": distance, "pressure": pressure}

    def draw_goal(self, key: jax.Array, position: jax.Array, params: EnvParams) -> jax.Array:
        """``[3]`` m: a goal drawn as at a reset, uniform over ``goal_set`` (``goal_mode=data``)
        or ``position [3]`` m plus ``N(0, goal_perturbation_m)`` per axis (``perturb``)."""
        index_key, perturb_key = jax.random.split(key)
        index = jax.random.randint(index_key, (), 0, params.goal_set.shape[0])
        perturbed = position + params.goal_perturbation_m * jax.random.normal(
            perturb_key, (POSITION_DIM,))
        return jnp.where(params.goal_from_data, params.goal_set[index], perturbed)

    def observe(self, key: jax.Array, state: EnvState, action: Any, params: EnvParams
                ) -> jax.Array:
        """``[obs_dim]``: standardized noisy position, standardized goal (, scaled error)
        (, accumulated error) (, last pressure); see
        :func:`pipeline.rl.envs.observation.observe`."""
        return self.observe_measured(self.measure(key, state.position, params), state, params)

    def measure(self, key: jax.Array, position: jax.Array, params: EnvParams) -> jax.Array:
        """``[3]`` m: ``position`` as measured (plus ``N(0, obs_noise_std_m)`` per axis)."""
        return position + params.obs_noise_std_m * jax.random.normal(key, (POSITION_DIM,))

    def observe_measured(self, measured: jax.Array, state: EnvState, params: EnvParams
                         ) -> jax.Array:
        """``[obs_dim]``: the observation of ``state`` with its position measured at ``measured``
        [3] m (:meth:`observe` draws that measurement)."""
        return observation.observe(
            measured, state.goal, state.last_pressure, params, include_error=self.include_error,
            include_last_action=self.include_last_action,
            error_integral=state.error_integral if self.include_error_integral else None,
            preview=(task.preview(state.reference, state.time, self.control_hz, self.preview)
                     if self.preview else None),
            reference_shift=state.reference_shift if self.tracking else None)

    def is_terminated(self, state: EnvState, params: EnvParams) -> jax.Array:
        """Whether the goal has been held for ``params.hold_periods`` periods (without a count
        in ``state``: whether the position is within the tolerance now); tracking: never."""
        if self.tracking:
            return jnp.zeros((), bool)
        if state.periods_within is None:
            return jnp.linalg.norm(state.goal - state.position) <= params.goal_tolerance_m
        return state.periods_within >= params.hold_periods

    # -----------------------------------------------------------------------------------------
    # helpers
    # -----------------------------------------------------------------------------------------
    def command(self, action: jax.Array, last_pressure: jax.Array, params: EnvParams
                ) -> jax.Array:
        """``[..., 3]`` action -> the pressures it commands, kPa (before noise and projection):
        :meth:`pressure_command`, or with ``incremental_actions`` ``last_pressure`` (the last
        applied command) plus ``clip(action) * action_step_kpa``."""
        if self.incremental_actions:
            return last_pressure + jnp.clip(action, -1.0, 1.0) * params.action_step_kpa
        return self.pressure_command(action, params)

    def action_for(self, pressure: jax.Array, last_pressure: jax.Array, params: EnvParams
                   ) -> jax.Array:
        """The action that commands ``pressure`` [..., 3] kPa after ``last_pressure``: the
        inverse of :meth:`command`, clipped to ``[-1, 1]`` (an incremental action reaches at
        most ``action_step_kpa`` from the last command)."""
        if self.incremental_actions:
            return jnp.clip((pressure - last_pressure) / params.action_step_kpa, -1.0, 1.0)
        return self.pressure_to_action(pressure, params)

    @staticmethod
    def initial_hold(goal: jax.Array) -> HoldState:
        """The hold's memory before the first period of an episode with ``goal [3]`` m."""
        return HoldState(jnp.ones((), jnp.float32), jnp.zeros(POSITION_DIM, jnp.float32),
                         jnp.zeros((), bool), jnp.asarray(goal, jnp.float32))

    def deadband_action(self, hold: HoldState, action: jax.Array, measured: jax.Array,
                        goal: jax.Array, last_pressure: jax.Array, params: EnvParams
                        ) -> tuple[HoldState, jax.Array]:
        """``(hold, [3] action)``: the action deployment sends, ``action`` or, where ``measured
        [3]`` m lies within ``params.deadband_m`` of ``goal [3]`` m, the hold's: the action that
        commands

            p = last_pressure + scale * hold_gain * hold_map @ (goal - measured)    [3] kPa

        (:meth:`action_for`; ``hold_map`` the damped inverse of the static map of the policy's
        model, :func:`~pipeline.rl.envs.learned.with_hold_map`; ``hold_gain`` 0: the last
        command again, a deadband).
        Near its goal the policy hands over to integral action: a slow, steady correction that
        closes the last millimetres and holds them against the arm's creep, where a policy
        trained to the first arrival dithers or drifts off. Evaluation's reaching episodes and
        the arm apply it; training does not (its episodes end at the goal).

        ``scale`` (``hold``, :class:`HoldState`) adapts the gain to the arm's response where it
        is steeper than the map's average: after a period that held, an error that turned past
        the goal (``error · previous error < 0``) and grew, to more than ``HOLD_OVERSHOOT_SHARE``
        of ``deadband_m``, multiplies it by ``params.hold_backoff``; a new goal sets it back to
        1. A correction that more than doubles the error across the goal is one whose gain is
        over twice what the arm can take; an error that shrinks across it, or grows on its own
        side (creep, drift), says nothing against the gain, nor does a swing within the last
        tenths of a millimetre (the measurement's noise). Where a tenth of a kPa moves the
        arm by millimetres (a valve near the preload on the recorded arm), a fixed gain swings
        the arm across the goal and out of the hold; the backed-off one settles it."""
        error = goal - measured
        distance = jnp.linalg.norm(error)
        within = (params.deadband_m > 0) & (distance <= params.deadband_m)
        same_goal = jnp.all(goal == hold.goal)
        overshot = (same_goal & hold.held & (jnp.dot(error, hold.error) < 0)
                    & (distance > jnp.linalg.norm(hold.error))
                    & (distance > HOLD_OVERSHOOT_SHARE * params.deadband_m))
        scale = (jnp.where(same_goal, hold.scale, 1.0)
                 * jnp.where(overshot, params.hold_backoff, 1.0))
        pressure = last_pressure + scale * params.hold_gain * (params.hold_map @ error)
        hold = HoldState(scale, error, within, jnp.asarray(goal, jnp.float32))
        return hold, jnp.where(within, self.action_for(pressure, last_pressure, params), action)

    @staticmethod
    def pressure_command(action: jax.Array, params: EnvParams) -> jax.Array:
        """``[..., 3]`` action in [-1, 1] (clipped) -> pressures in ``[p_min, p_max]`` kPa.

        Not yet projected onto the sum constraint (``step_env`` does that after the noise).
        """
        safe = params.safe_set
        unit = (jnp.clip(action, -1.0, 1.0) + 1.0) / 2.0
        return safe.p_min + unit * (safe.p_max - safe.p_min)

    @staticmethod
    def pressure_to_action(pressure: jax.Array, params: EnvParams) -> jax.Array:
        """Inverse of :meth:`pressure_command`: kPa -> [-1, 1]."""
        return observation.pressure_to_action(pressure, params.safe_set)

    def _hold_delayed(self, plant_params: Any, carry: Any, previous: jax.Array,
                      pressure: jax.Array, delay: jax.Array) -> tuple[Any, jax.Array]:
        """One control period: ``previous [3]`` kPa for the first ``delay`` plant steps, then
        ``pressure [3]`` kPa; returns the carry and the ``[steps_per_action, 3]`` positions (m)."""

        def one(carry, index):
            return self.plant.step(plant_params, carry,
                                   jnp.where(index < delay, previous, pressure))

        return jax.lax.scan(one, carry, jnp.arange(self.steps_per_action))

    def settle(self, plant_params: Any, initial_pose: jax.Array, preload: jax.Array
               ) -> tuple[Any, jax.Array]:
        """Carry and pose ``[3]`` m after holding the preload for ``settle_steps`` from rest."""
        carry = self.plant.init_carry(plant_params, initial_pose)
        carry, positions = hold(self.plant, plant_params, carry, preload, self.settle_steps)
        return carry, positions[-1]

