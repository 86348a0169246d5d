"""Learned forward dynamics of the arm: an LSTM (or GRU) from chamber pressures to marker position.

Units outside this module are physical: pressures in kPa, positions in metres. Standardization
happens inside, with the statistics of the training runs stored in :class:`Normalizer` next to the
network weights (both live in :class:`DynamicsParams`, one pytree).

Time indices. At model step ``t`` the network consumes the held pressure ``p_t`` and emits the
position ``x_t`` observed at the same grid time::

    carry_0          = init_carry(params, x_0_observed)
    carry_{t+1}, x_t = step(params, carry_t, p_t)          t = 0 .. T-1

so ``predict_sequence(params, p[0:T], x_0_observed)[t] == x_t`` depends on ``p_0 .. p_t`` and the
observed initial pose only (open loop).

Initial pose. Rest poses differ by a few mm between runs. Two switches let the model use the pose
observed at reset (both are measured in ``docs/results/MODEL_RESULTS.md``):

* ``predict_displacement``: the network predicts ``x_t - x_0_observed`` and the observed pose is
  added back, so a run-to-run offset of the rest pose passes straight through.
* ``condition_on_initial_pose``: the initial LSTM carry is a dense map of the standardized
  observed pose (otherwise it is zero).

Input features. Besides the standardized pressure the network may read causal features of the
pressure history (``pipeline/dynamics/features.py``: pressure differences, the last command step
and the time since it, play operators), computed by a recurrence whose state rides in the carry,
so stepping the model and rolling it out over a sequence agree.

Session latent (optional, ``pipeline/dynamics/session_latent.py``). A model trained with one
holds a second flax collection, ``session``: per training run a latent ``z_r`` [d] and the map
``gate_map`` [d, 3, hidden] that turns a latent into a bias of the first GRU layer's gates
(:func:`session_gate_bias`). :func:`predict_sequence` takes the latent of a session; without
one (or with ``z = 0``) the model is the model without session, and :func:`step` runs it so.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pipeline.data.runs import Run
from pipeline.dynamics import features as model_features
from pipeline.schemas import ModelArchitecture, frozen_twin

NUM_CHAMBERS = 3
POSITION_DIM = 3
_MIN_STD = 1.0e-6  # floor of every standard deviation, so a constant channel cannot divide by 0
CELLS = ("lstm", "gru")


# ---------------------------------------------------------------------------------------------
# configuration and parameters
# ---------------------------------------------------------------------------------------------
# the architecture's settings that are lists of numbers (kPa, model steps), stored as tuples
FLOAT_LIST_FIELDS = ("step_decays", "pressure_transients", "play_widths_kpa")


def freeze_lists(settings: Any) -> None:
    """Store the list settings of ``settings`` (a frozen dataclass with the architecture's
    fields) as tuples: ``head`` of ints, :data:`FLOAT_LIST_FIELDS` of floats (hashable)."""
    object.__setattr__(settings, "head", tuple(int(width) for width in settings.head))
    for name in FLOAT_LIST_FIELDS:
        object.__setattr__(settings, name, tuple(float(v) for v in getattr(settings, name)))


@dataclass(frozen=True)
class DynamicsConfig(frozen_twin(ModelArchitecture, "ArchitectureFields")):
    """The architecture (:class:`pipeline.schemas.ModelArchitecture`, its only declaration) as a
    frozen dataclass, lists as tuples: hashable, the static data of :class:`DynamicsParams`, and
    what a saved model stores. Defaults: the project's recipe (a GRU reading the pressures'
    transients); the paper's network is ``hidden=1024, cell="lstm", pressure_transients=()``."""

    def __post_init__(self):
        freeze_lists(self)
        object.__setattr__(self, "cell", str(getattr(self.cell, "value", self.cell)))
        if self.cell not in CELLS:
            raise ValueError(f"cell must be one of {CELLS}, got {self.cell!r}")
        for name in ("step_decays", "pressure_transients"):
            if any(v <= 0 for v in getattr(self, name)):
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if any(v < 0 for v in self.play_widths_kpa):
            raise ValueError(f"play_widths_kpa must be >= 0, got {self.play_widths_kpa}")

    @property
    def feature_spec(self) -> model_features.FeatureSpec:
        return model_features.FeatureSpec(
            pressure_delta=self.pressure_delta, step_size=self.step_size,
            decays=self.step_decays, play_widths=self.play_widths_kpa,
            step_threshold=self.step_threshold_kpa, transients=self.pressure_transients)

    @property
    def input_dim(self) -> int:
        """Width of the network's input per step: 3 pressures + the features."""
        return NUM_CHAMBERS + self.feature_spec.dim


@struct.dataclass
class Normalizer:
    """Per-axis statistics of the training runs; every field has shape [3].

    ``target_*`` standardize what the network outputs: ``x_t - x_0`` with ``predict_displacement``
    and ``x_t`` otherwise. ``pose_*`` standardize the observed initial pose fed to the carry.
    """

    pressure_mean: jax.Array
    pressure_std: jax.Array
    pose_mean: jax.Array
    pose_std: jax.Array
    target_mean: jax.Array
    target_std: jax.Array


@struct.dataclass
class DynamicsParams:
    """Everything needed to run the model: flax variables, normalizer, static architecture."""

    network: Any  # flax variables, {"params": ...}
    normalizer: Normalizer
    config: DynamicsConfig = struct.field(pytree_node=False)


class DynamicsCarry(NamedTuple):
    """Recurrent state between model steps.

    lstm: per layer, the cell's carry: a ``(c, h)`` pair of [hidden] arrays (LSTM) or ``h``
        (GRU).
    initial_pose: [3] metres, the observed pose at reset (added back to predicted displacements).
    features: the input features' state (``pipeline/dynamics/features.py``).
    """

    lstm: tuple[Any, ...]
    initial_pose: jax.Array
    features: model_features.FeatureState


# ---------------------------------------------------------------------------------------------
# network
# ---------------------------------------------------------------------------------------------
class DropoutGRUCell(nn.GRUCell):
    """flax's ``GRUCell`` (same parameters and names) whose recurrent products may read a
    dropped-out ``h`` (variational dropout, Gal & Ghahramani 2016).

    The mask multiplies ``h`` where it enters the gates and the candidate (``U_r h``, ``U_z h``,
    ``U_n h``), never the carried ``h`` of the update ``h' = (1 - z) n + z h``: masking the carry
    itself would rescale it by ``1 / (1 - rate)`` at every step and let it grow without bound.
    """

    @nn.compact
    def __call__(self, carry, inputs, recurrent_mask=None, gate_bias=None):
        """``gate_bias`` ([3, hidden], optional): added to the input parts of the reset, update
        and candidate pre-activations (rows in that order), as a constant extra input would be:
        a session latent's modulation (``session_gate_bias``)."""
        h = carry
        h_in = h if recurrent_mask is None else h * recurrent_mask
        features = h.shape[-1]
        dense_h = functools.partial(nn.Dense, features=features, use_bias=False, dtype=self.dtype,
                                    param_dtype=self.param_dtype,
                                    kernel_init=self.recurrent_kernel_init,
                                    bias_init=self.bias_init)
        dense_i = functools.partial(nn.Dense, features=features, use_bias=True, dtype=self.dtype,
                                    param_dtype=self.param_dtype, kernel_init=self.kernel_init,
                                    bias_init=self.bias_init)
        bias = jnp.zeros((3, features), h.dtype) if gate_bias is None else gate_bias
        r = self.gate_fn(dense_i(name="ir")(inputs) + bias[0] + dense_h(name="hr")(h_in))
        z = self.gate_fn(dense_i(name="iz")(inputs) + bias[1] + dense_h(name="hz")(h_in))
        n = self.activation_fn(dense_i(name="in")(inputs) + bias[2]
                               + r * dense_h(name="hn", use_bias=True)(h_in))
        new_h = (1.0 - z) * n + z * h
        return new_h, new_h


class LSTMDynamicsNet(nn.Module):
    """Stacked LSTM (or GRU) + MLP head, one unbatched time step per call (vmap for batches)."""

    hidden: int
    layers: int
    head: tuple[int, ...]
    condition_on_initial_pose: bool
    cell: str = "lstm"

    def setup(self):
        if self.cell == "gru":
            self.cells = [DropoutGRUCell(self.hidden, name=f"gru_{i}")
                          for i in range(self.layers)]
        else:
            self.cells = [
                nn.OptimizedLSTMCell(self.hidden, name=f"lstm_{i}") for i in range(self.layers)
            ]
        if self.condition_on_initial_pose:
            # Small init: the conditioned carry starts near the zero carry of the plain model.
            self.carry_encoder = nn.Dense(
                2 * self.hidden * self.layers,
                kernel_init=nn.initializers.normal(0.1),
                name="carry_encoder",
            )
        self.head_layers = [nn.Dense(width, name=f"head_{i}") for i, width in enumerate(self.head)]
        self.readout = nn.Dense(POSITION_DIM, name="readout")

    def initial_carry(self, pose_normalized: jax.Array):
        """[3] standardized observed pose -> per layer ``(c, h)`` (LSTM) or ``h`` (GRU)."""
        if not self.condition_on_initial_pose:
            zeros = jnp.zeros((self.hidden,), pose_normalized.dtype)
            if self.cell == "gru":
                return tuple(zeros for _ in range(self.layers))
            return tuple((zeros, zeros) for _ in range(self.layers))
        encoded = self.carry_encoder(pose_normalized).reshape(self.layers, 2, self.hidden)
        if self.cell == "gru":
            return tuple(jnp.tanh(encoded[i, 1]) for i in range(self.layers))
        return tuple((encoded[i, 0], jnp.tanh(encoded[i, 1])) for i in range(self.layers))

    def __call__(self, carry, inputs: jax.Array, recurrent_mask: jax.Array | None = None,
                 gate_bias: jax.Array | None = None):
        """One step: ``(carry_t, [D] standardized inputs_t) -> (carry_{t+1}, [3] standardized
        y_t)``; the inputs are ``p_t`` and its features (:func:`network_inputs`).

        ``recurrent_mask`` ([layers, hidden], training only): recurrent dropout, multiplying each
        layer's ``h`` where it enters the cell's recurrent products (for the LSTM that is all of
        ``h_t``'s use; its cell state ``c`` and the outputs are never masked).
        ``gate_bias`` ([3, hidden], GRU only): the first layer's session modulation
        (:class:`DropoutGRUCell`).
        """
        if gate_bias is not None and self.cell != "gru":
            raise ValueError(f"a session latent needs cell='gru', got {self.cell!r}")
        features = inputs
        next_carry = []
        for i, (cell, layer_carry) in enumerate(zip(self.cells, carry)):
            bias = gate_bias if i == 0 else None
            if self.cell == "gru" and (recurrent_mask is not None or bias is not None):
                mask = None if recurrent_mask is None else recurrent_mask[i]
                layer_carry, features = cell(layer_carry, features, mask, bias)
            elif recurrent_mask is None:
                layer_carry, features = cell(layer_carry, features)
            else:
                c, h = layer_carry
                layer_carry, features = cell((c, h * recurrent_mask[i]), features)
            next_carry.append(layer_carry)
        for dense in self.head_layers:
            features = nn.relu(dense(features))
        return tuple(next_carry), self.readout(features)

    def initialize(self, pose_normalized: jax.Array, inputs: jax.Array):
        """Touches every submodule once; only used by ``init``."""
        return self(self.initial_carry(pose_normalized), inputs)


def make_network(config: DynamicsConfig) -> LSTMDynamicsNet:
    return LSTMDynamicsNet(
        hidden=config.hidden,
        layers=config.layers,
        head=config.head,
        condition_on_initial_pose=config.condition_on_initial_pose,
        cell=config.cell,
    )


@functools.partial(jax.jit, static_argnames="config")
def init_network(key: jax.Array, config: DynamicsConfig) -> Any:
    """Fresh flax variables for ``config`` (jitted: one compilation per architecture)."""
    pose = jnp.zeros((POSITION_DIM,), jnp.float32)
    inputs = jnp.zeros((config.input_dim,), jnp.float32)
    return make_network(config).init(key, pose, inputs, method=LSTMDynamicsNet.initialize)


# ---------------------------------------------------------------------------------------------
# normalization
# ---------------------------------------------------------------------------------------------
def fit_normalizer(runs: Sequence[Run], predict_displacement: bool) -> Normalizer:
    """Statistics over all steps of ``runs`` (dicts with "p" [T, 3] kPa and "pos" [T, 3] m).

    Displacements are measured from each run's first pose, as the training windows are by default
    (``reference_pose="run_start"`` in ``train_model``).
    """
    pressures = np.concatenate([np.asarray(run.pressures_kpa, np.float64) for run in runs])
    positions = np.concatenate([np.asarray(run.positions_m, np.float64) for run in runs])
    if predict_displacement:
        targets = np.concatenate(
            [np.asarray(run.positions_m, np.float64) - np.asarray(run.positions_m[0], np.float64)
             for run in runs]
        )
    else:
        targets = positions

    def stats(values):
        return (
            jnp.asarray(values.mean(axis=0), jnp.float32),
            jnp.asarray(np.maximum(values.std(axis=0), _MIN_STD), jnp.float32),
        )

    pressure_mean, pressure_std = stats(pressures)
    pose_mean, pose_std = stats(positions)
    target_mean, target_std = stats(targets)
    return Normalizer(pressure_mean, pressure_std, pose_mean, pose_std, target_mean, target_std)


def normalize_pressure(normalizer: Normalizer, pressure: jax.Array) -> jax.Array:
    return (pressure - normalizer.pressure_mean) / normalizer.pressure_std


def normalize_pose(normalizer: Normalizer, pose: jax.Array) -> jax.Array:
    return (pose - normalizer.pose_mean) / normalizer.pose_std


def normalize_inputs(params: DynamicsParams, pressure: jax.Array, raw_features: jax.Array
                     ) -> jax.Array:
    """[..., 3] kPa and [..., F] raw features -> [..., 3 + F] standardized network inputs."""
    normalizer = params.normalizer
    offset, scale = model_features.affine(params.config.feature_spec, normalizer.pressure_mean,
                                          normalizer.pressure_std)
    return jnp.concatenate(
        [normalize_pressure(normalizer, pressure), (raw_features - offset) / scale], axis=-1)


def network_inputs(params: DynamicsParams, pressures: jax.Array) -> jax.Array:
    """[T, 3] kPa -> [T, 3 + F] standardized inputs of a sequence that starts at ``t = 0``."""
    chex.assert_shape(pressures, (None, NUM_CHAMBERS))
    pressures = jnp.asarray(pressures, jnp.float32)
    raw = model_features.sequence(params.config.feature_spec, pressures)
    return normalize_inputs(params, pressures, raw)


def normalize_target(
    params: DynamicsParams, position: jax.Array, initial_pose: jax.Array
) -> jax.Array:
    """[..., 3] positions (m) -> standardized network targets, given the [3] initial pose."""
    normalizer = params.normalizer
    if params.config.predict_displacement:
        position = position - initial_pose
    return (position - normalizer.target_mean) / normalizer.target_std


def denormalize_target(
    params: DynamicsParams, output: jax.Array, initial_pose: jax.Array
) -> jax.Array:
    """Inverse of :func:`normalize_target`: standardized outputs -> positions (m)."""
    normalizer = params.normalizer
    position = output * normalizer.target_std + normalizer.target_mean
    if params.config.predict_displacement:
        position = position + initial_pose
    return position


# ---------------------------------------------------------------------------------------------
# public model API (physical units)
# ---------------------------------------------------------------------------------------------
def init_carry(params: DynamicsParams, initial_pose: jax.Array) -> DynamicsCarry:
    """Carry before step 0 from the observed pose at reset ([3] metres)."""
    chex.assert_shape(initial_pose, (POSITION_DIM,))
    network = make_network(params.config)
    pose_normalized = normalize_pose(params.normalizer, initial_pose)
    lstm = network.apply(params.network, pose_normalized, method=LSTMDynamicsNet.initial_carry)
    return DynamicsCarry(lstm=lstm, initial_pose=jnp.asarray(initial_pose, jnp.float32),
                         features=model_features.init_state(params.config.feature_spec))


def step(
    params: DynamicsParams, carry: DynamicsCarry, pressure: jax.Array
) -> tuple[DynamicsCarry, jax.Array]:
    """One model step: ``(carry_t, p_t [3] kPa) -> (carry_{t+1}, x_t [3] m)``."""
    chex.assert_shape(pressure, (NUM_CHAMBERS,))
    network = make_network(params.config)
    features, raw = model_features.step(params.config.feature_spec, carry.features, pressure)
    inputs = normalize_inputs(params, jnp.asarray(pressure, jnp.float32), raw)
    lstm, output = network.apply(params.network, carry.lstm, inputs)
    position = denormalize_target(params, output, carry.initial_pose)
    return DynamicsCarry(lstm=lstm, initial_pose=carry.initial_pose, features=features), position


def step_held(
    params: DynamicsParams, carry: DynamicsCarry, pressure: jax.Array, num_steps: int
) -> tuple[DynamicsCarry, jax.Array]:
    """Holds ``pressure`` ([3] kPa) for ``num_steps`` model steps (one control period).

    Returns the carry after the period and the [num_steps, 3] positions (m) along it; the last
    row is the pose at the end of the period.
    """
    chex.assert_shape(pressure, (NUM_CHAMBERS,))
    held = jnp.broadcast_to(pressure, (num_steps, NUM_CHAMBERS))
    return jax.lax.scan(lambda c, p: step(params, c, p), carry, held)


def predict_normalized(
    params: DynamicsParams,
    inputs: jax.Array,
    pose_normalized: jax.Array,
    hidden_mask: jax.Array | None = None,
    latent: jax.Array | None = None,
) -> jax.Array:
    """Open-loop rollout in standardized units: [T, D], [3] -> [T, 3] (the training path).

    ``inputs``: :func:`network_inputs` rows (``D = config.input_dim``). ``hidden_mask``
    ([layers, hidden], optional): one recurrent-dropout mask for the whole rollout (training),
    see :meth:`LSTMDynamicsNet.__call__`. ``latent`` ([d], optional): the session latent the
    rollout is conditioned on (a model with a session collection, :func:`session_gate_bias`);
    ``None`` or zeros: the model without session.
    """
    chex.assert_shape(inputs, (None, params.config.input_dim))
    chex.assert_shape(pose_normalized, (POSITION_DIM,))
    network = make_network(params.config)
    carry = network.apply(params.network, pose_normalized, method=LSTMDynamicsNet.initial_carry)
    gate_bias = None if latent is None else session_gate_bias(params, latent)

    def one_step(carry, inputs_t):
        return network.apply(params.network, carry, inputs_t, hidden_mask, gate_bias)

    _, outputs = jax.lax.scan(one_step, carry, inputs)
    return outputs


def predict_sequence(
    params: DynamicsParams, pressures: jax.Array, initial_pose: jax.Array,
    latent: jax.Array | None = None,
) -> jax.Array:
    """Open-loop positions [T, 3] m from pressures [T, 3] kPa and the observed pose x_0 [3] m.

    Row ``t`` is the pose after the network consumed ``p_0 .. p_t`` (see the module docstring);
    identical to stepping :func:`step` from :func:`init_carry`. ``latent`` ([d], optional): the
    session latent (:func:`predict_normalized`).
    """
    chex.assert_shape(pressures, (None, NUM_CHAMBERS))
    chex.assert_shape(initial_pose, (POSITION_DIM,))
    outputs = predict_normalized(
        params, network_inputs(params, pressures), normalize_pose(params.normalizer, initial_pose),
        latent=latent,
    )
    return denormalize_target(params, outputs, initial_pose)


# ---------------------------------------------------------------------------------------------
# session latents
# ---------------------------------------------------------------------------------------------
SESSION = "session"  # the flax collection of a model's session latents


def init_session(key: jax.Array, params: DynamicsParams, num_runs: int, dim: int
                 ) -> DynamicsParams:
    """``params`` with a session collection: per training run a latent ``z_r`` ([num_runs,
    dim], zeros) and the map ``gate_map`` ([dim, 3, hidden], normal with std ``1 / sqrt(dim)``)
    that turns a latent into the first GRU layer's gate bias (:func:`session_gate_bias`).

    Row ``r`` of ``latents`` belongs to the ``r``-th run of the training data
    (``TrainData.row_run``); a row no window reads stays zero.
    """
    if params.config.cell != "gru":
        raise ValueError(f"a session latent needs cell='gru', got {params.config.cell!r}")
    if dim < 1 or num_runs < 1:
        raise ValueError(f"a session latent needs dim >= 1 and a run, got {dim}, {num_runs}")
    gate_map = jax.random.normal(key, (dim, 3, params.config.hidden)) / np.sqrt(dim)
    session = {"gate_map": gate_map.astype(jnp.float32),
               "latents": jnp.zeros((num_runs, dim), jnp.float32)}
    return params.replace(network={**params.network, SESSION: session})


def session_latent_dim(params: DynamicsParams) -> int:
    """The dimension of the model's session latent; 0: a model without one."""
    session = params.network.get(SESSION) if isinstance(params.network, dict) else None
    return 0 if session is None else int(session["latents"].shape[-1])


def session_gate_bias(params: DynamicsParams, latent: jax.Array) -> jax.Array:
    """[d] session latent -> [3, hidden] gate bias of the first GRU layer (``z @ gate_map``)."""
    gate_map = params.network[SESSION]["gate_map"]
    chex.assert_shape(latent, (gate_map.shape[0],))
    return jnp.einsum("d,dgh->gh", latent, gate_map)
