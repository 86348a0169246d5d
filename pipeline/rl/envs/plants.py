"""Plants: the dynamics an environment steps, behind one small interface.

A :class:`Plant` is a bundle of pure functions on physical quantities (pressures in kPa,
positions in metres) together with its step rate::

    carry_0          = plant.init_carry(plant_params, initial_pose)      # pose [3] m at rest
    carry_{t+1}, x_t = plant.step(plant_params, carry_t, p_t)             # p_t [3] kPa, x_t [3] m

``plant_params`` is a pytree that lives in the environment parameters, so one compiled
environment runs any fitted model (or a batch of them under ``vmap``); the :class:`Plant` itself
is static (hashable) and lives on the environment object. ``initial_pose`` is the pose observed
with the arm resting at the preload; the environment then holds the preload for a few seconds
before an episode starts.

Three plants:

- :func:`learned_plant` — the learned recurrent model (GRU or LSTM) of
  :mod:`pipeline.dynamics.model` (``DynamicsParams``).
- :func:`sim_plant` — the simulated arm of :mod:`pipeline.arm.sim_arm` (the ground-truth plant).
- :func:`linear_lag_plant` — a tiny linear first-order lag from pressures to position (tests).

and one wrapper, :func:`ensemble_plant`: K fitted models of one kind, one of them per episode.

A plant may say how the entries of an environment's reset bank differ (``Plant.bank_params``):
the ensemble settles bank entry ``i`` in member ``i % K``, so that drawing a start state uniformly
draws a member uniformly.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
from flax import struct

from pipeline.arm import sim_arm
from pipeline.dynamics import model as dynamics

NUM_VALVES = 3
POSITION_DIM = 3


class Plant(NamedTuple):
    """Static description of a dynamics model: pure functions and the rate they step at.

    init_carry: ``(plant_params, initial_pose [3] m) -> carry``.
    step: ``(plant_params, carry_t, pressure_t [3] kPa) -> (carry_{t+1}, position_t [3] m)``.
    model_hz: steps per second of simulated time.
    name: for logs and tables.
    bank_params: optional ``(plant_params, n) -> (params, in_axes)``: the parameters that settle
      each of ``n`` reset-bank entries, ``vmap``-ped with ``in_axes`` (a prefix of their pytree);
      None: every entry settles with ``plant_params`` itself.
    """

    init_carry: Callable[[Any, jax.Array], Any]
    step: Callable[[Any, Any, jax.Array], tuple[Any, jax.Array]]
    model_hz: float
    name: str
    bank_params: Callable[[Any, int], tuple[Any, Any]] | None = None


def hold(plant: Plant, plant_params: Any, carry: Any, pressure: jax.Array, num_steps: int
         ) -> tuple[Any, jax.Array]:
    """Hold ``pressure [3]`` kPa for ``num_steps`` plant steps (zero-order hold).

    Returns the carry after the hold and the ``[num_steps, 3]`` positions along it (m); the last
    row is the pose at the end of the hold.
    """
    chex.assert_shape(pressure, (NUM_VALVES,))
    return jax.lax.scan(lambda c, _: plant.step(plant_params, c, pressure), carry, None,
                        length=num_steps)


# ---------------------------------------------------------------------------------------------
# the learned model
# ---------------------------------------------------------------------------------------------
def learned_plant(model_hz: float) -> Plant:
    """The recurrent model of :mod:`pipeline.dynamics.model`; ``plant_params`` is a
    ``DynamicsParams``."""
    return Plant(dynamics.init_carry, dynamics.step, float(model_hz), "learned")


# ---------------------------------------------------------------------------------------------
# the simulated arm
# ---------------------------------------------------------------------------------------------
@struct.dataclass
class SimPlantParams:
    """The simulated arm as a plant: physics plus the preload it rests at (kPa, [3])."""

    sim: sim_arm.SimParams
    preload: jax.Array


def _sim_init_carry(params: SimPlantParams, initial_pose: jax.Array) -> sim_arm.SimState:
    """The arm settled at the preload, its rest offset chosen so the tip lies at the pose."""
    chex.assert_shape(initial_pose, (POSITION_DIM,))
    no_offset = sim_arm.settled_state(params.sim, params.preload, jnp.zeros(POSITION_DIM))
    offset = initial_pose - sim_arm.tip_position(params.sim, no_offset)
    return sim_arm.settled_state(params.sim, params.preload, offset)


def sim_plant(mocap_hz: float, frames_per_step: int) -> Plant:
    """The simulated arm stepping ``frames_per_step`` mocap frames per plant step.

    ``plant_params`` is a :class:`SimPlantParams`; the position is the noise-free marker
    position at the end of each step (measurement noise is the environment's business).
    """
    frames = int(frames_per_step)
    if frames < 1:
        raise ValueError(f"frames_per_step must be >= 1, got {frames_per_step}")

    def step(params: SimPlantParams, state: sim_arm.SimState, pressure: jax.Array):
        chex.assert_shape(pressure, (NUM_VALVES,))
        state = sim_arm.advance(params.sim, state, pressure, frames)
        return state, sim_arm.tip_position(params.sim, state)

    return Plant(_sim_init_carry, step, float(mocap_hz) / frames, "sim")


# ---------------------------------------------------------------------------------------------
# an ensemble: one of K members per episode
# ---------------------------------------------------------------------------------------------
ENSEMBLE_SELECTIONS = ("gather", "all")


@struct.dataclass
class EnsembleParams:
    """K plants of one kind (same static description, e.g. models of one architecture).

    members: the members' parameters, every leaf with a leading [K] axis (:func:`stack_members`).
    member: int32 scalar, the member :func:`ensemble_plant`'s ``init_carry`` starts in (the reset
      bank sets it per entry, see ``Plant.bank_params``); ``step`` follows the carry's member.
    """

    members: Any
    member: jax.Array

    @property
    def num_members(self) -> int:
        return int(jax.tree.leaves(self.members)[0].shape[0])


class EnsembleCarry(NamedTuple):
    member: jax.Array  # int32 scalar, the member this episode runs in
    carry: Any  # that member's carry


def stack_members(members: Any) -> EnsembleParams:
    """:class:`EnsembleParams` of a sequence of plant parameters (member 0 first)."""
    members = list(members)
    if not members:
        raise ValueError("an ensemble needs at least one member")
    structures = {jax.tree.structure(m) for m in members}
    if len(structures) > 1:
        raise ValueError(f"ensemble members must share one structure (e.g. one model "
                         f"architecture: model.* settings); got {len(structures)} different ones")
    stacked = jax.tree.map(lambda *leaves: jnp.stack([jnp.asarray(x) for x in leaves]), *members)
    return EnsembleParams(stacked, jnp.zeros((), jnp.int32))


def _member(members: Any, index: jax.Array) -> Any:
    return jax.tree.map(lambda leaf: leaf[index], members)


def ensemble_plant(member: Plant, selection: str = "all") -> Plant:
    """One of K ``member`` plants per episode; ``plant_params``: :class:`EnsembleParams`.

    The carry is an :class:`EnsembleCarry` (member index, member carry); ``init_carry`` starts in
    ``params.member``, ``step`` steps the carry's member. ``selection`` chooses how (same results):
    ``gather`` takes the member's parameters per call (under ``vmap`` over environments: one copy
    of the weights per environment), ``all`` steps every member with its own weights, shared by
    all environments, and keeps the carry's member (K times the arithmetic, in larger matrix
    products; the faster one on CPU for small K, see ``bench/ensemble_selection.py``).
    """
    if selection not in ENSEMBLE_SELECTIONS:
        raise ValueError(f"selection must be one of {ENSEMBLE_SELECTIONS}, got {selection!r}")

    def init_carry(params: EnsembleParams, initial_pose: jax.Array) -> EnsembleCarry:
        chex.assert_shape(initial_pose, (POSITION_DIM,))
        index = jnp.asarray(params.member, jnp.int32)
        return EnsembleCarry(index, member.init_carry(_member(params.members, index),
                                                      initial_pose))

    def step(params: EnsembleParams, carry: EnsembleCarry, pressure: jax.Array):
        chex.assert_shape(pressure, (NUM_VALVES,))
        if selection == "gather":
            inner, position = member.step(_member(params.members, carry.member), carry.carry,
                                          pressure)
        else:
            every = jax.vmap(member.step, in_axes=(0, None, None))(params.members, carry.carry,
                                                                  pressure)
            inner, position = _member(every, carry.member)
        return EnsembleCarry(carry.member, inner), position

    def bank_params(params: EnsembleParams, n: int) -> tuple[EnsembleParams, EnsembleParams]:
        members = jnp.arange(n, dtype=jnp.int32) % params.num_members
        return params.replace(member=members), EnsembleParams(members=None, member=0)

    return Plant(init_carry, step, member.model_hz, f"{member.name}_ensemble", bank_params)


# ---------------------------------------------------------------------------------------------
# a toy: linear first-order lag
# ---------------------------------------------------------------------------------------------
@struct.dataclass
class LinearLagParams:
    """``position = offset + gain @ lagged``, ``lagged += lag_factor * (pressure - lagged)``.

    gain: [3 position, 3 valves] m/kPa. lag_factor: scalar in (0, 1], per plant step.
    preload: [3] kPa, the pressure the arm rests at in :func:`linear_lag_plant`'s init_carry.
    """

    gain: jax.Array
    lag_factor: jax.Array
    preload: jax.Array


class LinearLagCarry(NamedTuple):
    lagged_pressure: jax.Array  # [3] kPa
    offset: jax.Array  # [3] m


def linear_lag_plant(model_hz: float) -> Plant:
    """A linear first-order lag from pressures to position (``plant_params``: LinearLagParams)."""

    def init_carry(params: LinearLagParams, initial_pose: jax.Array) -> LinearLagCarry:
        chex.assert_shape(initial_pose, (POSITION_DIM,))
        return LinearLagCarry(params.preload, initial_pose - params.gain @ params.preload)

    def step(params: LinearLagParams, carry: LinearLagCarry, pressure: jax.Array):
        chex.assert_shape(pressure, (NUM_VALVES,))
        lagged = carry.lagged_pressure + params.lag_factor * (pressure - carry.lagged_pressure)
        return LinearLagCarry(lagged, carry.offset), carry.offset + params.gain @ lagged

    return Plant(init_carry, step, float(model_hz), "linear_lag")


def default_linear_lag_params(preload: float = 2.0, lag_factor: float = 0.5) -> LinearLagParams:
    """A toy arm like the simulated one: chambers at 90/210/330 degrees push the tip away
    (about 4 mm/kPa sideways) and the mean pressure lengthens it downwards (0.5 mm/kPa)."""
    angles = jnp.deg2rad(jnp.array([90.0, 210.0, 330.0]))
    sideways = 0.004
    gain = jnp.stack([
        -sideways * jnp.cos(angles),
        jnp.full((3,), -0.0005 / 3.0),
        -sideways * jnp.sin(angles),
    ]).astype(jnp.float32)
    return LinearLagParams(gain, jnp.asarray(lag_factor, jnp.float32),
                           jnp.full((NUM_VALVES,), preload, jnp.float32))
