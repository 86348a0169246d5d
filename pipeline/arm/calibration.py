"""Calibrating the simulated arm to recorded runs: gradient descent through the simulator.

The simulated arm (:mod:`pipeline.arm.sim_arm`) is pure JAX, so its open-loop prediction of a whole
recorded run is differentiable in its physics. A fit drives the simulator with each run's own
pressure commands from the settled preload state and minimises the mean squared distance (mm²)
between simulated and recorded marker positions, per run, averaged over runs.

- **Bounds.** Each fitted parameter ``v`` lives in ``[lower, upper]`` through ``v = lower +
  (upper - lower) sigmoid(z)``; the optimizer moves the unconstrained ``z``, so no step can leave
  the bounds (:data:`BOUNDS`, SI units and kPa, as in :class:`pipeline.schemas.SimPhysics`).
- **Nuisance offsets.** The arm's rest pose differs by a few mm between runs: each training run
  gets its own offset ``[3]`` (m), fitted with the physics; the base position is not fitted (the
  offsets carry it). A run that is not trained on (held out) gets the mean of the training runs'
  offsets (nothing of the held-out run is used, as for the baselines), or, for comparison, the
  offset that puts the simulated rest pose on its first recorded position (the information the
  learned model gets).
- **Members.** One program fits ``M`` members at once (vmap): every leave-one-run-out fold (its
  held-out run has weight 0) and the fit on all runs, each from several restarts (the first from
  the initial physics, the others perturbed in ``z``). A fold's restart is chosen by its
  training loss, never by its held-out run.

Shapes: ``R`` runs padded to ``T`` frames at ``rate_hz``, ``M`` members, ``D`` fitted scalars.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax

from pipeline.arm import sim_arm

# SimPhysics field -> (lower, upper, unit, relative): relative bounds are offsets from the
# initial value (the chamber angles: each may turn 60 degrees either way).
BOUNDS: dict[str, tuple[float, float, str, bool]] = {
    "chamber_angles_deg": (-60.0, 60.0, "deg", True),
    "chamber_gains": (0.5, 2.0, "1", False),
    "segment_length_m": (0.03, 0.25, "m", False),
    "tip_offset_m": (0.0, 0.15, "m", False),
    "pressure_tau_s": (0.02, 1.5, "s", False),
    "bend_gain": (0.005, 0.5, "rad/kPa", False),
    "elong_gain": (-0.005, 0.01, "m/kPa", False),
    "natural_freq_hz": (0.1, 5.0, "Hz", False),
    "damping_ratio": (0.1, 4.0, "1", False),
    "gravity_stiffening": (0.0, 3.0, "1", False),
    "hysteresis_kpa": (0.0, 1.5, "kPa", False),
    "creep_gain": (0.0, 0.9, "1", False),
    "creep_tau_s": (0.5, 120.0, "s", False),
    "saturation_per_kpa": (0.0, 2.0, "1/kPa", False),
    "saturation_center_kpa": (-3.0, 7.0, "kPa", False),
    "mean_stiffening_per_kpa": (0.0, 2.0, "1/kPa", False),
}
UNITS = {**{name: bound[2] for name, bound in BOUNDS.items()},
         "base_position_m": "m", "rest_pose_std_m": "m", "substeps": "1"}
_EDGE = 0.02  # an initial value on a bound starts this fraction of the range inside


@dataclass(frozen=True)
class Parameterization:
    """The map between unconstrained ``z [D]`` and bounded physics values (SimPhysics names)."""

    names: tuple[str, ...]
    sizes: tuple[int, ...]
    scalar: tuple[bool, ...]  # a scalar parameter (a list otherwise, even of one)
    lower: np.ndarray  # [D]
    upper: np.ndarray  # [D]

    @classmethod
    def create(cls, names: Sequence[str], initial: Mapping[str, Any]) -> Parameterization:
        """Bounds of the fitted ``names`` (keys of :data:`BOUNDS`) around ``initial`` values."""
        unknown = [n for n in names if n not in BOUNDS]
        if unknown:
            raise ValueError(f"calibration.fitted: cannot fit {unknown}; fittable parameters: "
                             f"{list(BOUNDS)}")
        if len(set(names)) != len(names):
            raise ValueError(f"calibration.fitted names a parameter twice: {list(names)}")
        lower, upper, sizes, scalar = [], [], [], []
        for name in names:
            low, high, _, relative = BOUNDS[name]
            value = np.atleast_1d(np.asarray(initial[name], np.float64))
            sizes.append(value.size)
            scalar.append(np.ndim(initial[name]) == 0 and not isinstance(initial[name], list))
            base = value if relative else np.zeros_like(value)
            lower.append(base + low)
            upper.append(base + high)
        return cls(tuple(names), tuple(sizes), tuple(scalar), np.concatenate(lower),
                   np.concatenate(upper))

    @property
    def size(self) -> int:
        return int(sum(self.sizes))

    def to_physics(self, z: chex.Array) -> dict[str, chex.Array]:
        """``z [D]`` -> {name: value} inside the bounds (traceable)."""
        chex.assert_shape(z, (self.size,))
        values = self.lower + (self.upper - self.lower) * jax.nn.sigmoid(z)
        out, start = {}, 0
        for name, size, scalar in zip(self.names, self.sizes, self.scalar):
            piece = values[start:start + size]
            out[name] = piece[0] if scalar else piece
            start += size
        return out

    def from_physics(self, values: Mapping[str, Any]) -> np.ndarray:
        """{name: value} -> ``z [D]``; values on or beyond a bound start just inside it."""
        flat = np.concatenate([np.atleast_1d(np.asarray(values[n], np.float64))
                               for n in self.names])
        fraction = np.clip((flat - self.lower) / (self.upper - self.lower), _EDGE, 1 - _EDGE)
        return np.log(fraction) - np.log1p(-fraction)


@dataclass(frozen=True)
class RunBatch:
    """Runs padded to a common length: ``commands [R, T, 3]`` kPa (held during each frame),
    ``positions [R, T, 3]`` m, ``mask [R, T]`` (1 on recorded frames), ``preload [R, 3]``."""

    run_ids: tuple[str, ...]
    commands: np.ndarray
    positions: np.ndarray
    mask: np.ndarray
    preload: np.ndarray
    lengths: np.ndarray  # [R] int

    @classmethod
    def from_runs(cls, runs: Sequence[Any]) -> RunBatch:
        """From runs (:class:`~pipeline.data.runs.Run`, a regular grid each); the
        first pressure of each run is the preload it has settled at."""
        if not runs:
            raise ValueError("calibration needs at least one run")
        lengths = np.array([len(r) for r in runs])
        length = int(lengths.max())
        commands = np.zeros((len(runs), length, 3), np.float32)
        positions = np.zeros((len(runs), length, 3), np.float32)
        mask = np.zeros((len(runs), length), np.float32)
        for i, run in enumerate(runs):
            n = lengths[i]
            commands[i, :n] = run.pressures_kpa
            commands[i, n:] = run.pressures_kpa[-1]
            positions[i, :n] = run.positions_m
            positions[i, n:] = run.positions_m[-1]
            mask[i, :n] = 1.0
        preload = commands[:, 0].copy()
        return cls(tuple(r.run_id for r in runs), commands, positions, mask, preload,
                   lengths)


def simulate_batch(template: sim_arm.SimParams, physics: Mapping[str, chex.Array],
                   commands: chex.Array, preload: chex.Array) -> tuple[chex.Array, chex.Array]:
    """Open-loop positions ``[R, T, 3]`` (m, no session offset) of ``commands [R, T, 3]`` from
    the settled ``preload [R, 3]``, and the rest pose ``[R, 3]`` at each preload."""
    params = template.with_physics(physics)

    def one(run_commands, run_preload):
        state = sim_arm.settled_state(params, run_preload, jnp.zeros(3))
        return (sim_arm.predict_positions(params, state, run_commands),
                sim_arm.tip_position(params, state))

    return jax.vmap(one)(commands, preload)


def member_losses(template: sim_arm.SimParams, param: Parameterization, z: chex.Array,
                  offsets: chex.Array, weights: chex.Array, batch: Mapping[str, chex.Array]
                  ) -> chex.Array:
    """Per member ``[M]``: the weighted mean over runs of the mean squared error (mm²).

    ``z [M, D]``, ``offsets [M, R, 3]`` m, ``weights [M, R]`` (0: not trained on).
    """

    def one(z_m, offsets_m, weights_m):
        predicted, _ = simulate_batch(template, param.to_physics(z_m), batch["commands"],
                                      batch["preload"])
        error = 1e3 * (predicted + offsets_m[:, None, :] - batch["positions"])
        per_run = (jnp.sum(error**2, -1) * batch["mask"]).sum(1) / batch["mask"].sum(1)
        return jnp.sum(weights_m * per_run) / jnp.maximum(weights_m.sum(), 1e-9)

    return jax.vmap(one)(z, offsets, weights)


def make_fit(template: sim_arm.SimParams, param: Parameterization, num_steps: int,
             learning_rate: float, max_grad_norm: float = 10.0):
    """``fit(z0 [M, D], offsets0 [M, R, 3], weights [M, R], batch) -> (z, offsets, losses
    [num_steps, M])``: Adam (cosine-decayed) on every member at once, one jitted program.

    The members' losses are summed, so each member's gradient is its own; gradients are clipped
    per member. Offsets are optimised in mm.
    """
    optimizer = optax.chain(
        optax.clip_by_global_norm(max_grad_norm),
        optax.adam(optax.cosine_decay_schedule(learning_rate, num_steps, alpha=0.05)))

    def loss_of(variables, weights, batch):
        z, offsets_mm = variables
        losses = member_losses(template, param, z, offsets_mm * 1e-3, weights, batch)
        return losses.sum(), losses

    grad_fn = jax.value_and_grad(loss_of, has_aux=True)

    def fit(z0, offsets0, weights, batch):
        variables = (z0, offsets0 * 1e3)
        opt_state = jax.vmap(optimizer.init)(variables)

        def step(carry, _):
            variables, opt_state = carry
            (_, losses), grads = grad_fn(variables, weights, batch)
            updates, opt_state = jax.vmap(optimizer.update)(grads, opt_state, variables)
            return (optax.apply_updates(variables, updates), opt_state), losses

        (variables, _), losses = jax.lax.scan(step, (variables, opt_state), None, num_steps)
        z, offsets_mm = variables
        return z, offsets_mm * 1e-3, losses

    return jax.jit(fit)


def make_predict(template: sim_arm.SimParams, param: Parameterization):
    """``predict(z [M, D], batch) -> (positions [M, R, T, 3], rest [M, R, 3])`` (m, no offset)."""

    def predict(z, batch):
        return jax.vmap(lambda z_m: simulate_batch(template, param.to_physics(z_m),
                                                   batch["commands"], batch["preload"]))(z)

    return jax.jit(predict)


def batch_arrays(batch: RunBatch) -> dict[str, jnp.ndarray]:
    return {"commands": jnp.asarray(batch.commands), "positions": jnp.asarray(batch.positions),
            "mask": jnp.asarray(batch.mask), "preload": jnp.asarray(batch.preload)}


def initial_members(param: Parameterization, initial: Mapping[str, Any], num_members: int,
                    num_restarts: int, restart_std: float, key: chex.PRNGKey) -> np.ndarray:
    """``z0 [num_members * num_restarts, D]``: restart 0 at ``initial``, the others perturbed
    (member m's restart r is row ``m * num_restarts + r``; every member gets the same draws)."""
    z0 = param.from_physics(initial)
    noise = restart_std * np.asarray(jax.random.normal(key, (num_restarts, param.size)))
    noise[0] = 0.0
    return np.tile(z0[None] + noise, (num_members, 1)).astype(np.float32)


@dataclass
class FitResult:
    """A calibration: the chosen restart of every member and its physics."""

    z: np.ndarray  # [members, D] of the chosen restarts
    offsets: np.ndarray  # [members, R, 3] m
    chosen: np.ndarray  # [members] restart index
    losses: np.ndarray  # [steps, members, restarts] mm²
    physics: list[dict[str, np.ndarray]]  # per member


def calibrate(template: sim_arm.SimParams, param: Parameterization,
              initial: Mapping[str, Any], batch: RunBatch, weights: np.ndarray, *,
              num_steps: int, learning_rate: float, num_restarts: int, restart_std: float,
              key: chex.PRNGKey, fit=None) -> FitResult:
    """Fit every member (row of ``weights [members, R]``) from ``num_restarts`` starts.

    ``fit`` is a program from :func:`make_fit` to reuse (same template, param and steps).
    """
    weights = np.asarray(weights, np.float32)
    num_members = weights.shape[0]
    arrays = batch_arrays(batch)
    z0 = initial_members(param, initial, num_members, num_restarts, restart_std, key)
    # every start puts each run's rest pose on its first recorded position
    offsets0 = batch.positions[None, :, 0] - rest_poses(template, param, z0, batch.preload)
    fit = fit or make_fit(template, param, num_steps, learning_rate)
    z, offsets, losses = jax.device_get(fit(
        jnp.asarray(z0), jnp.asarray(offsets0, jnp.float32),
        jnp.asarray(np.repeat(weights, num_restarts, axis=0)), arrays))
    final = losses[-1].reshape(num_members, num_restarts)
    final = np.where(np.isfinite(final), final, np.inf)
    chosen = np.argmin(final, axis=1)
    rows = np.arange(num_members) * num_restarts + chosen
    z_best = np.asarray(z)[rows]
    physics = [{k: np.asarray(v) for k, v in param.to_physics(jnp.asarray(z_m)).items()}
               for z_m in z_best]
    return FitResult(z_best, np.asarray(offsets)[rows], chosen,
                     np.asarray(losses).reshape(num_steps, num_members, num_restarts), physics)


def rest_poses(template: sim_arm.SimParams, param: Parameterization, z: np.ndarray,
               preload: np.ndarray) -> np.ndarray:
    """``[M, R, 3]`` m: each member's simulated rest pose at each run's preload (no offset)."""

    def one(z_m):
        params = template.with_physics(param.to_physics(z_m))
        return jax.vmap(lambda p: sim_arm.tip_position(
            params, sim_arm.settled_state(params, p, jnp.zeros(3))))(jnp.asarray(preload))

    return np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(z)))


def training_mean_offsets(offsets: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``[M, 3]`` m: each member's mean offset over the runs it was trained on."""
    weights = np.asarray(weights, np.float64)
    return np.einsum("mr,mrk->mk", weights, offsets) / weights.sum(1, keepdims=True)


def open_loop(template: sim_arm.SimParams, param: Parameterization, z: np.ndarray,
              batch: RunBatch, offsets: np.ndarray | None = None) -> np.ndarray:
    """``[M, R, T, 3]`` m: each member's open-loop positions of every run plus ``offsets
    [M, 3]`` (m, the same for every run), or, if None, the offset that puts the simulated rest
    pose on each run's first recorded position."""
    positions, rest = make_predict(template, param)(jnp.asarray(z), batch_arrays(batch))
    if offsets is None:
        run_offsets = batch.positions[None, :, 0] - np.asarray(rest)
    else:
        run_offsets = np.broadcast_to(np.asarray(offsets)[:, None, :], np.shape(rest))
    return np.asarray(positions) + run_offsets[:, :, None, :]


def open_loop_template(template: sim_arm.SimParams, batch: RunBatch, first_pose: bool = False
                       ) -> np.ndarray:
    """``[R, T, 3]`` m: open-loop positions with the physics in ``template`` itself, at its own
    rest pose or (``first_pose``) with each run's rest pose on its first recorded position."""
    positions, rest = jax.jit(simulate_batch)(template, {}, jnp.asarray(batch.commands),
                                              jnp.asarray(batch.preload))
    offsets = batch.positions[:, 0] - np.asarray(rest) if first_pose else np.zeros((1, 3))
    return np.asarray(positions) + offsets[:, None, :]


def physics_dict(base: Mapping[str, Any], fitted: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` SimPhysics values with ``fitted`` ones replaced, as plain floats and lists."""
    out = {}
    for name, value in {**dict(base), **dict(fitted)}.items():
        array = np.asarray(value, np.float64)
        out[name] = array.tolist() if array.ndim else float(array)
    return out


def session_offsets_to_physics(base_position: Sequence[float], offsets: np.ndarray
                               ) -> dict[str, list[float]]:
    """The base position and rest-pose spread from the fitted per-run offsets ``[R, 3]`` m."""
    offsets = np.asarray(offsets, np.float64)
    return {"base_position_m": (np.asarray(base_position) + offsets.mean(0)).tolist(),
            "rest_pose_std_m": offsets.std(0).tolist()}


def sim_physics_values(physics: Any) -> dict[str, Any]:
    """Plain values of a SimPhysics config (dataclass or OmegaConf node)."""
    if dataclasses.is_dataclass(physics):
        return dataclasses.asdict(physics)
    return {k: (list(v) if hasattr(v, "__len__") and not isinstance(v, str) else v)
            for k, v in physics.items()}
