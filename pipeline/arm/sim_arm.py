"""A simulated 3-chamber pneumatic bellows arm hanging from a frame, with motion capture.

It stands in for the real arm of the paper (``shared/data/sorolex``) as the default robot and as
the ground-truth plant that policies are evaluated on. Everything is pure JAX: ``vmap`` it over
many arms, ``jit`` it, and it runs on simulated time, never the wall clock.

Model (all parameters in :class:`pipeline.schemas.SimPhysics`, units SI unless kPa):

1. **Valves to chambers.** Each chamber pressure follows its valve command with a first-order lag
   ``dp/dt = (p_cmd - p) / pressure_tau_s``.
2. **Hysteresis.** A play (backlash) operator of half-width ``hysteresis_kpa`` per chamber: the
   effective pressure ``h`` only moves once the pressure has pushed it past the play.
3. **Creep.** A fraction ``creep_gain`` of the effective pressure acts through a slow first-order
   lag ``creep_tau_s``: ``pe = (1 - c) h + c s``, ``ds/dt = (h - s) / creep_tau_s``.
4. **Configuration.** Bending vector ``b = theta (cos phi, sin phi)`` in the horizontal x-z plane
   (theta the bending angle of the constant-curvature segment, phi its direction) and elongation
   ``e``. Pressurising chamber k (at angle ``a_k`` around the axis, gain ``g_k``) bends the arm
   away from it: ``b* = -bend_gain * exp(-s (mean_k pe_k - c)) * sum_k g_k f(pe_k) (cos a_k,
   sin a_k)``, ``e* = elong_gain * mean_k pe_k``. Two measured nonlinearities of the real arm
   (docs/results/CALIBRATION_RESULTS.md): each chamber's strain saturates, ``f(p) = c +
   tanh(a (p - c)) / a`` (``a = saturation_per_kpa``, ``c = saturation_center_kpa``; linear for
   ``a = 0``), and the whole arm stiffens as its mean pressure rises (``s =
   mean_stiffening_per_kpa``): the real arm bends 2-3 times more per kPa of pressure difference
   at a mean pressure of 2.2 kPa than at 3.6 kPa.
5. **Second-order dynamics with gravity.** ``b'' = w^2 (b* - b - g sin(theta) b / theta) -
   2 zeta w b'`` (gravity pulls the hanging arm back toward vertical with a torque ~ sin theta, a
   stiffening that weakens at large angles), ``e'' = w^2 (e* - e) - 2 zeta w e'``, integrated with
   semi-implicit Euler at ``substeps`` per mocap frame.
6. **Kinematics.** The constant-curvature segment of length ``L + e`` hangs down (-y) from the
   base; a rigid end piece of length ``tip_offset_m`` carries the markers. Lateral offset
   ``(L+e)(1 - cos theta)/theta + d sin theta``, drop ``(L+e) sin theta/theta + d cos theta``.
   Each session adds a rest-pose offset drawn with ``rest_pose_std_m`` (the real arm's rest pose
   differs by a few mm between runs) and, for the parameters named in ``session_std``, its own
   physics: the nominal value plus a normal draw of that spread (:func:`session_params`).
7. **Motion capture.** Frames at ``mocap.rate_hz`` with Gaussian position noise, timestamp jitter
   (clipped to keep time increasing), single dropped frames and bursts of dropped frames
   (``valid = False``, position NaN).

Magnitudes were calibrated by hand to the real runs: at 2 kPa preload the markers rest near
(32, 353, 202) mm; a 5 kPa pressure difference moves them about 20 mm sideways and lifts them
about 2 mm (the real arm: ``dy ≈ 0.006 mm⁻¹ r²``); the mean pressure lengthens the arm by about
0.5 mm/kPa; steps settle in roughly half a second with a slight overshoot.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

_SMALL_ANGLE = 1e-4  # rad; below it the kinematics use their Taylor expansions


@struct.dataclass
class SimParams:
    """Physical and sensing parameters of one arm (a pytree: vmap over a batch of them)."""

    base: chex.Array  # [3] m, top of the bending segment at zero elongation
    chamber_dirs: chex.Array  # [3 chambers, 2] unit vectors (x, z) of the chamber angles
    chamber_gains: chex.Array  # [3] relative bending gain of each chamber
    segment_length: chex.Array
    tip_offset: chex.Array
    pressure_tau: chex.Array
    bend_gain: chex.Array
    elong_gain: chex.Array
    omega: chex.Array
    damping_ratio: chex.Array
    gravity_stiffening: chex.Array
    hysteresis: chex.Array
    creep_gain: chex.Array
    creep_tau: chex.Array
    saturation: chex.Array  # 1/kPa
    saturation_center: chex.Array  # kPa
    mean_stiffening: chex.Array  # 1/kPa
    rest_pose_std: chex.Array  # [3] m
    noise_std: chex.Array
    jitter_std: chex.Array
    drop_prob: chex.Array
    burst_prob: chex.Array
    mocap_hz: float = struct.field(pytree_node=False, default=100.0)
    substeps: int = struct.field(pytree_node=False, default=10)
    burst_len: int = struct.field(pytree_node=False, default=8)
    # SimPhysics name -> spread between sessions, in that parameter's unit (empty: none)
    session_std: dict[str, chex.Array] = struct.field(default_factory=dict)

    @classmethod
    def from_config(cls, robot: Any) -> SimParams:
        """The parameters of ``robot.physics`` (:class:`pipeline.schemas.SimPhysics`) and
        ``robot.mocap`` (:class:`pipeline.schemas.MocapConfig`)."""
        mocap, physics = robot.mocap, robot.physics
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        values = {k: _plain(getattr(physics, k)) for k in PHYSICS_VALUES}
        spread = getattr(physics, "session_std", None) or {}  # plain values may have none
        return cls(
            **physics_fields(values),
            session_std=session_spread(values, {k: _plain(v) for k, v in spread.items()}),
            noise_std=f32(mocap.noise_std_m),
            jitter_std=f32(mocap.jitter_std_s),
            drop_prob=f32(mocap.drop_prob),
            burst_prob=f32(mocap.burst_prob),
            mocap_hz=float(mocap.rate_hz),
            substeps=int(physics.substeps),
            burst_len=int(mocap.burst_len),
        )

    @classmethod
    def noise_free(cls, physics: Mapping[str, Any], rate_hz: float, substeps: int) -> SimParams:
        """Parameters with ``physics`` (SimPhysics values by field name; its ``session_std``, if
        any, ignored: one physics for every session), frames at ``rate_hz`` of ``substeps``
        integrator steps each, and a perfect motion capture (no noise, jitter or drops)."""
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        values = {k: _plain(physics[k]) for k in PHYSICS_VALUES}
        return cls(
            **physics_fields(values),
            session_std=session_spread(values, {}),
            noise_std=f32(0.0),
            jitter_std=f32(0.0),
            drop_prob=f32(0.0),
            burst_prob=f32(0.0),
            mocap_hz=float(rate_hz),
            substeps=int(substeps),
            burst_len=1,
        )

    def with_physics(self, values: Mapping[str, Any]) -> SimParams:
        """These parameters with the physics ``values`` (SimPhysics field names, SI units and
        kPa; arrays may be traced, so a fit can differentiate through them) replaced."""
        return self.replace(**physics_fields(values))


# SimPhysics fields that become array parameters (the rest are static: substeps).
PHYSICS_VALUES = (
    "base_position_m", "chamber_angles_deg", "chamber_gains", "segment_length_m", "tip_offset_m",
    "pressure_tau_s", "bend_gain", "elong_gain", "natural_freq_hz", "damping_ratio",
    "gravity_stiffening", "hysteresis_kpa", "creep_gain", "creep_tau_s", "saturation_per_kpa",
    "saturation_center_kpa", "mean_stiffening_per_kpa", "rest_pose_std_m")
_FIELD_OF = {
    "base_position_m": "base", "chamber_gains": "chamber_gains",
    "segment_length_m": "segment_length", "tip_offset_m": "tip_offset",
    "pressure_tau_s": "pressure_tau", "bend_gain": "bend_gain", "elong_gain": "elong_gain",
    "damping_ratio": "damping_ratio", "gravity_stiffening": "gravity_stiffening",
    "hysteresis_kpa": "hysteresis", "creep_gain": "creep_gain", "creep_tau_s": "creep_tau",
    "saturation_per_kpa": "saturation", "saturation_center_kpa": "saturation_center",
    "mean_stiffening_per_kpa": "mean_stiffening", "rest_pose_std_m": "rest_pose_std"}


def _plain(value: Any) -> Any:
    """A config list (ListConfig, tuple) as a list; numbers and arrays unchanged."""
    return value if np.ndim(value) == 0 or hasattr(value, "shape") else list(value)


def physics_fields(values: Mapping[str, Any]) -> dict[str, chex.Array]:
    """SimParams fields from SimPhysics values (any subset): angles in degrees become unit
    direction vectors, the natural frequency in Hz an angular frequency."""
    unknown = sorted(set(values) - set(PHYSICS_VALUES))
    if unknown:
        raise ValueError(f"unknown physics parameters {unknown}; known: {list(PHYSICS_VALUES)}")
    fields = {}
    for name, value in values.items():
        value = jnp.asarray(value, jnp.float32)
        if name == "chamber_angles_deg":
            angles = jnp.deg2rad(value)
            fields["chamber_dirs"] = jnp.stack([jnp.cos(angles), jnp.sin(angles)], axis=1)
        elif name == "natural_freq_hz":
            fields["omega"] = 2 * jnp.pi * value
        else:
            fields[_FIELD_OF[name]] = value
    return fields


# Parameters a session may draw (session_std), with the least value a draw may take: a draw
# below it is clipped there (the lags divide, the gains and widths are not negative).
SESSION_FLOORS: dict[str, float | None] = {
    "chamber_angles_deg": None, "chamber_gains": 0.0, "segment_length_m": 0.01,
    "tip_offset_m": 0.0, "pressure_tau_s": 1e-3, "bend_gain": 0.0, "elong_gain": None,
    "natural_freq_hz": 0.01, "damping_ratio": 0.0, "gravity_stiffening": 0.0,
    "hysteresis_kpa": 0.0, "creep_gain": 0.0, "creep_tau_s": 1e-3, "saturation_per_kpa": 0.0,
    "saturation_center_kpa": None, "mean_stiffening_per_kpa": 0.0}


def session_spread(values: Mapping[str, Any], spread: Mapping[str, Any]
                   ) -> dict[str, chex.Array]:
    """``session_std`` as arrays shaped like the parameters they spread (checked)."""
    unknown = sorted(set(spread) - set(SESSION_FLOORS))
    if unknown:
        raise ValueError(f"physics.session_std: {unknown} cannot vary between sessions; "
                         f"known: {list(SESSION_FLOORS)}")
    out = {}
    for name, std in spread.items():
        shape = np.shape(values[name])
        std = np.asarray(std, np.float64)
        if std.ndim == 0:
            std = np.broadcast_to(std, shape)
        if std.shape != shape or np.any(std < 0) or not np.all(np.isfinite(std)):
            raise ValueError(f"physics.session_std.{name}={std.tolist()}: expected one "
                             f"non-negative spread per element of {name} (shape {shape})")
        out[name] = jnp.asarray(std, jnp.float32)
    return out


def session_params(params: SimParams, key: chex.PRNGKey) -> SimParams:
    """One session's physics: every parameter of ``params.session_std`` plus its own
    ``N(0, std^2)`` draw per element (clipped at :data:`SESSION_FLOORS`); ``params`` unchanged
    when the spread is empty. A draw of the chamber angles turns the chamber directions."""
    changes = {}
    for index, name in enumerate(sorted(params.session_std)):
        std = params.session_std[name]
        draw = std * jax.random.normal(jax.random.fold_in(key, index), std.shape)
        if name == "chamber_angles_deg":
            turn = jnp.deg2rad(draw)
            cos, sin = jnp.cos(turn), jnp.sin(turn)
            x, z = params.chamber_dirs[:, 0], params.chamber_dirs[:, 1]
            changes["chamber_dirs"] = jnp.stack([cos * x - sin * z, sin * x + cos * z], axis=1)
            continue
        field, scale = ("omega", 2 * jnp.pi) if name == "natural_freq_hz" else (_FIELD_OF[name], 1.0)
        value = getattr(params, field) + scale * draw
        floor = SESSION_FLOORS[name]
        changes[field] = value if floor is None else jnp.maximum(value, scale * floor)
    return params.replace(**changes) if changes else params


def physics_value(params: SimParams, name: str) -> chex.Array:
    """The value of SimPhysics parameter ``name`` in ``params``, in its SimPhysics unit."""
    if name == "chamber_angles_deg":
        return jnp.rad2deg(jnp.arctan2(params.chamber_dirs[:, 1], params.chamber_dirs[:, 0])
                           ) % 360.0
    if name == "natural_freq_hz":
        return params.omega / (2 * jnp.pi)
    return getattr(params, _FIELD_OF[name])


@struct.dataclass
class SimState:
    """State of one arm. Pressures in kPa, bending in rad, elongation in m."""

    pressure: chex.Array  # [3] chamber pressures
    play: chex.Array  # [3] play-operator output (hysteresis)
    creep: chex.Array  # [3] slow part of the effective pressure
    config: chex.Array  # [3] (b_x, b_z, e)
    velocity: chex.Array  # [3] time derivative of config
    rest_offset: chex.Array  # [3] m, this session's rest-pose offset


def saturating(pressure: chex.Array, a: chex.Array, centre: chex.Array) -> chex.Array:
    """``c + tanh(a (p - c)) / a`` of ``pressure`` p (kPa) about ``centre`` c (kPa), ``a`` in
    1/kPa: the identity for ``a = 0``, saturating away from ``c`` otherwise (slope 1 at ``c``;
    the result lies between ``c`` and ``p``)."""
    small = a < 1e-6
    safe_a = jnp.where(small, 1.0, a)
    shifted = pressure - centre
    # tanh(a x) / a ~ x - a^2 x^3 / 3 for small a (keeps the gradient in a finite at 0)
    return centre + jnp.where(small, shifted - a**2 * shifted**3 / 3.0,
                              jnp.tanh(safe_a * shifted) / safe_a)


def chamber_strain(params: SimParams, pressure: chex.Array) -> chex.Array:
    """``f(p) = c + tanh(a (p - c)) / a`` per chamber (kPa, :func:`saturating`): linear for
    ``a = 0``, saturating away from ``c`` otherwise (slope 1 at ``c``)."""
    return saturating(pressure, params.saturation, params.saturation_center)


def _targets(params: SimParams, effective: chex.Array) -> chex.Array:
    stiffening = jnp.exp(-params.mean_stiffening * (effective.mean() - params.saturation_center))
    strain = params.chamber_gains * chamber_strain(params, effective)
    bend = -params.bend_gain * stiffening * strain @ params.chamber_dirs  # [2]
    elong = params.elong_gain * effective.mean()
    return jnp.concatenate([bend, elong[None]])


def settled_state(params: SimParams, preload: chex.Array, rest_offset: chex.Array) -> SimState:
    """The arm at rest after holding ``preload [3]`` kPa for a long time."""
    preload = jnp.asarray(preload, jnp.float32)
    chex.assert_shape(preload, (3,))
    config = _targets(params, preload)
    # With equal chamber pressures there is no bending, so gravity adds nothing at rest.
    return SimState(preload, preload, preload, config, jnp.zeros(3), rest_offset)


def reset(params: SimParams, key: chex.PRNGKey, preload: chex.Array) -> SimState:
    """A new session: a fresh rest-pose offset, the arm settled at the preload."""
    offset = params.rest_pose_std * jax.random.normal(key, (3,))
    return settled_state(params, preload, offset)


def integrate(params: SimParams, state: SimState, command: chex.Array, dt: float) -> SimState:
    """Advance one integrator step of ``dt`` seconds holding valve ``command [3]`` kPa."""
    pressure = state.pressure + dt * (command - state.pressure) / params.pressure_tau
    play = jnp.clip(state.play, pressure - params.hysteresis, pressure + params.hysteresis)
    creep = state.creep + dt * (play - state.creep) / params.creep_tau
    effective = (1.0 - params.creep_gain) * play + params.creep_gain * creep
    target = _targets(params, effective)

    bend = state.config[:2]
    theta = jnp.sqrt(jnp.sum(bend**2) + 1e-12)
    gravity = params.gravity_stiffening * (jnp.sin(theta) / theta) * bend
    restoring = target - state.config - jnp.concatenate([gravity, jnp.zeros(1)])
    accel = params.omega**2 * restoring - 2.0 * params.damping_ratio * params.omega * state.velocity
    velocity = state.velocity + dt * accel
    config = state.config + dt * velocity
    return SimState(pressure, play, creep, config, velocity, state.rest_offset)


def tip_position(params: SimParams, state: SimState) -> chex.Array:
    """Marker position ``[3]`` (x, y, z) in metres, y vertical."""
    bx, bz, elong = state.config
    theta = jnp.sqrt(bx**2 + bz**2)
    small = theta < _SMALL_ANGLE
    safe_theta = jnp.where(small, 1.0, theta)
    length = params.segment_length + elong
    # (1 - cos t)/t and sin t/t with their series near 0 (keeps gradients finite).
    one_minus_cos = jnp.where(small, theta / 2.0, (1.0 - jnp.cos(safe_theta)) / safe_theta)
    sinc = jnp.where(small, 1.0 - theta**2 / 6.0, jnp.sin(safe_theta) / safe_theta)
    lateral_per_theta = jnp.where(
        small, length / 2.0 + params.tip_offset, (length * one_minus_cos +
                                                  params.tip_offset * jnp.sin(safe_theta))
        / safe_theta)
    drop = length * sinc + params.tip_offset * jnp.cos(theta)
    # lateral displacement = lateral_per_theta * theta along (bx, bz) / theta
    return params.base + state.rest_offset + jnp.stack(
        [lateral_per_theta * bx, -drop, lateral_per_theta * bz])


def advance(params: SimParams, state: SimState, command: chex.Array, num_frames: int
            ) -> SimState:
    """Hold ``command [3]`` for ``num_frames`` mocap periods (``substeps`` steps each)."""
    dt = 1.0 / (params.mocap_hz * params.substeps)
    return jax.lax.fori_loop(
        0, num_frames * params.substeps, lambda _, s: integrate(params, s, command, dt), state)


def predict_positions(params: SimParams, state: SimState, commands: chex.Array) -> chex.Array:
    """Noise-free marker positions ``[K, 3]`` (m) holding ``commands[k]`` during frame k.

    Frame k's position is the arm's at the start of the frame (so position 0 is ``state``'s).
    """
    chex.assert_rank(commands, 2)

    def frame(state, command):
        position = tip_position(params, state)
        return advance(params, state, command, 1), position

    return jax.lax.scan(frame, state, commands)[1]


def simulate_run(
    params: SimParams,
    key: chex.PRNGKey,
    commands: chex.Array,
    frame_command: chex.Array,
    preload: chex.Array,
) -> dict[str, chex.Array]:
    """Drive one session with ``commands [N, 3]`` and record motion capture.

    Args:
      commands: valve commands in kPa; command i is sent at ``t = i / control_hz``.
      frame_command: ``[K]`` int, index of the command in force during mocap frame k (frame k
        covers ``[k, k+1) / mocap_hz``); see :func:`frame_command_index`.
      preload: ``[3]`` kPa the arm has settled at before the run.

    Returns:
      ``t [K]`` mocap timestamps (s, with jitter), ``position [K, 3]`` (m, noisy, NaN where not
      valid), ``valid [K]`` bool, ``true_position [K, 3]`` (noise-free, for tests and plots).
      Frame k's position is the arm's at the frame's nominal time ``k / mocap_hz``.
      ``physics``: {name: value} the session drew for each parameter of ``session_std``.
    """
    chex.assert_rank(commands, 2)
    chex.assert_rank(frame_command, 1)
    session_key, noise_key, jitter_key, drop_key, burst_key = jax.random.split(key, 5)
    params = session_params(params, jax.random.fold_in(session_key, 1))
    state = reset(params, session_key, preload)
    true_position = predict_positions(params, state, commands[frame_command])
    num_frames = frame_command.shape[0]
    period = 1.0 / params.mocap_hz
    jitter = jnp.clip(params.jitter_std * jax.random.normal(jitter_key, (num_frames,)),
                      -0.4 * period, 0.4 * period)
    t = jnp.arange(num_frames) * period + jitter
    noisy = true_position + params.noise_std * jax.random.normal(noise_key, (num_frames, 3))
    dropped = jax.random.bernoulli(drop_key, params.drop_prob, (num_frames,))
    burst_start = jax.random.bernoulli(burst_key, params.burst_prob, (num_frames,))
    in_burst = jnp.convolve(burst_start.astype(jnp.float32), jnp.ones(params.burst_len),
                            mode="full")[:num_frames] > 0
    valid = ~(dropped | in_burst)
    position = jnp.where(valid[:, None], noisy, jnp.nan)
    return {"t": t, "position": position, "valid": valid, "true_position": true_position,
            "physics": {name: physics_value(params, name) for name in params.session_std}}


def frame_command_index(num_commands: int, control_hz: float, mocap_hz: float) -> np.ndarray:
    """Index of the command in force in each mocap frame of a run of ``num_commands`` commands.

    The run lasts ``num_commands / control_hz`` seconds; frame k starts at ``k / mocap_hz``.
    """
    num_frames = int(np.floor(num_commands * mocap_hz / control_hz + 1e-9))
    frames = np.arange(num_frames)
    # Integer arithmetic where the rates allow it avoids 0.999... rounding at command edges.
    index = np.floor(frames * control_hz / mocap_hz + 1e-9).astype(np.int32)
    return np.minimum(index, num_commands - 1)
