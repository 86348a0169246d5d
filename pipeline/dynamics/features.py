"""Causal input features of the learned dynamics, computed from the pressure sequence.

The open-loop error of the real-arm model lies in the transients after each command step
(``docs/results/MODEL_RESULTS.md``). These features carry what such a transient depends on, and
each is a recurrence over model steps with a small state, so that a model stepped one pressure at
a time (an environment) computes exactly what training computed over whole runs:

* ``pressure_delta``: ``p_t - p_{t-1}`` per chamber [kPa] (zero at the first step);
* ``step_size``: the pressure change at the last command step, held until the next [kPa];
* ``step_decays`` (time constants ``tau_k`` in model steps): ``exp(-n_t / tau_k)`` where ``n_t``
  is the number of model steps since the last command step (a step: some chamber changed by more
  than ``step_threshold_kpa``); before any step ``n_t`` is taken as infinite;
* ``play_widths_kpa`` (half-widths ``r_k``): Prandtl–Ishlinskii play (backlash) operators on
  each chamber's pressure, ``y_t = max(p_t - r, min(p_t + r, y_{t-1}))`` with ``y_0 = p_0``;
* ``transients`` (time constants ``tau_k`` in model steps): per chamber the part of the pressure
  the arm has not yet settled to, ``u_t = exp(-1 / tau_k) u_{t-1} + (p_t - p_{t-1})`` with
  ``u_0 = 0``: a step of ``d`` kPa gives ``d exp(-n / tau_k)`` after ``n`` steps, and steps
  superpose. Unlike the step features it is linear and continuous in the commands (a step of
  0.06 kPa gives 1.5 times what one of 0.04 kPa gives, where the step features jump from nothing
  to a whole step at the threshold) and zero under a held command: a model fed only these cannot
  tie its resting pose to the size of the last step.

Time indices: the features of step ``t`` depend on ``p_0 .. p_t`` only. The state starts
"unstarted" and the first pressure it sees initializes it (the previous pressure and every play
operator start at ``p_0``, as for an arm resting at its first command).

Feature vector layout (``F = feature_dim``): ``[delta (3), step_size (3), decays (K),
play (R * 3, width-major), transients (J * 3, tau-major)]``, each block present only when
switched on.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

NUM_CHAMBERS = 3
_NEVER = 1.0e6  # steps since the last command step before any step was seen


class FeatureSpec(NamedTuple):
    """Which features, hashable (static). ``decays`` in model steps, ``play_widths`` in kPa."""

    pressure_delta: bool = False
    step_size: bool = False
    decays: tuple[float, ...] = ()
    play_widths: tuple[float, ...] = ()
    step_threshold: float = 0.05
    transients: tuple[float, ...] = ()

    @property
    def dim(self) -> int:
        return (NUM_CHAMBERS * (int(self.pressure_delta) + int(self.step_size))
                + len(self.decays)
                + NUM_CHAMBERS * (len(self.play_widths) + len(self.transients)))


class FeatureState(NamedTuple):
    """Recurrent state of the features (all float32).

    started: [] 1 once a pressure was seen, else 0.
    previous_pressure: [3] kPa, ``p_{t-1}``.
    steps_since_step: [] model steps since the last command step.
    last_step: [3] kPa, the change at the last command step.
    play: [R, 3] kPa, the play operators' outputs.
    transient: [J, 3] kPa, the unsettled part of the pressure per time constant.
    """

    started: jax.Array
    previous_pressure: jax.Array
    steps_since_step: jax.Array
    last_step: jax.Array
    play: jax.Array
    transient: jax.Array


def init_state(spec: FeatureSpec) -> FeatureState:
    """The unstarted state (the first pressure initializes it)."""
    zeros = jnp.zeros((NUM_CHAMBERS,), jnp.float32)
    return FeatureState(
        started=jnp.zeros((), jnp.float32),
        previous_pressure=zeros,
        steps_since_step=jnp.asarray(_NEVER, jnp.float32),
        last_step=zeros,
        play=jnp.zeros((len(spec.play_widths), NUM_CHAMBERS), jnp.float32),
        transient=jnp.zeros((len(spec.transients), NUM_CHAMBERS), jnp.float32),
    )


def play_operator(previous: jax.Array, pressure: jax.Array, width: jax.Array) -> jax.Array:
    """One step of the play operator: ``max(p - r, min(p + r, y_prev))`` (broadcasting)."""
    return jnp.maximum(pressure - width, jnp.minimum(pressure + width, previous))


def step(spec: FeatureSpec, state: FeatureState, pressure: jax.Array
         ) -> tuple[FeatureState, jax.Array]:
    """``(state_t, p_t [3] kPa) -> (state_{t+1}, raw features_t [F])`` (physical units)."""
    pressure = jnp.asarray(pressure, jnp.float32)
    started = state.started > 0.5
    previous = jnp.where(started, state.previous_pressure, pressure)
    delta = pressure - previous
    changed = jnp.max(jnp.abs(delta)) > spec.step_threshold
    since = jnp.where(changed, 0.0, jnp.where(started, state.steps_since_step + 1.0, _NEVER))
    last_step = jnp.where(changed, delta, state.last_step)
    widths = jnp.asarray(spec.play_widths, jnp.float32).reshape(-1, 1)
    play_previous = jnp.where(started, state.play, jnp.broadcast_to(pressure, state.play.shape))
    play = play_operator(play_previous, pressure[None, :], widths)
    retention = jnp.exp(-1.0 / jnp.asarray(spec.transients, jnp.float32)).reshape(-1, 1)
    transient = retention * state.transient + delta[None, :]
    blocks = []
    if spec.pressure_delta:
        blocks.append(delta)
    if spec.step_size:
        blocks.append(last_step)
    if spec.decays:
        blocks.append(jnp.exp(-since / jnp.asarray(spec.decays, jnp.float32)))
    if spec.play_widths:
        blocks.append(play.reshape(-1))
    if spec.transients:
        blocks.append(transient.reshape(-1))
    features = jnp.concatenate(blocks) if blocks else jnp.zeros((0,), jnp.float32)
    new_state = FeatureState(jnp.ones((), jnp.float32), pressure, since.astype(jnp.float32),
                             last_step, play, transient)
    return new_state, features


def sequence(spec: FeatureSpec, pressures: jax.Array) -> jax.Array:
    """Raw features [T, F] of a pressure sequence [T, 3] kPa from the unstarted state."""
    _, features = jax.lax.scan(lambda s, p: step(spec, s, p), init_state(spec), pressures)
    return features


def affine(spec: FeatureSpec, pressure_mean: jax.Array, pressure_std: jax.Array
           ) -> tuple[jax.Array, jax.Array]:
    """``(offset [F], scale [F])``: standardized features are ``(raw - offset) / scale``.

    Pressure changes and transients are divided by the chamber's pressure std, play outputs
    standardized like the pressure, decays (already in [0, 1]) left as they are.
    """
    offsets, scales = [], []
    zeros, ones = jnp.zeros((NUM_CHAMBERS,)), jnp.ones((NUM_CHAMBERS,))
    for _ in range(int(spec.pressure_delta) + int(spec.step_size)):
        offsets.append(zeros)
        scales.append(pressure_std)
    if spec.decays:
        offsets.append(jnp.zeros((len(spec.decays),)))
        scales.append(jnp.ones((len(spec.decays),)))
    for _ in spec.play_widths:
        offsets.append(pressure_mean * ones)
        scales.append(pressure_std * ones)
    for _ in spec.transients:
        offsets.append(zeros)
        scales.append(pressure_std)
    if not offsets:
        return jnp.zeros((0,)), jnp.ones((0,))
    return jnp.concatenate(offsets), jnp.concatenate(scales)
