"""A learned session latent: a forward model that calibrates to a session through a few numbers.

Training (``cv.fit_members(..., latent=...)``, ``training.make_train_step``) gives every training
run ``r`` its own latent vector ``z_r`` ([d], zeros at the start) learned jointly with the
weights; the latent enters the first GRU layer as a bias of its reset, update and candidate
gates, exactly as a constant extra input would (``dynamics.session_gate_bias``: ``z @ G`` with
``G`` [d, 3, hidden] learned too)::

    loss = mean over windows of the standardized squared error (window of run r, given z_r)
           + prior * mean over the batch's windows of |z_r|²

so the latents of different runs share one space around 0 and the gates can express what
differs between sessions (their time constants: the transients after each command step).

At test time the weights are fixed and the latent of a new session is inferred from a context,
its first ``n`` steps of commands [n, 3] kPa and measured positions [n, 3] m
(:func:`infer_latent`): a fixed number of Adam steps on ``z`` alone (one jitted scan), the same
objective on the context rollout from the run's start, ``z = 0`` (the prior's mean) without
context. The model then predicts the session open loop from its commands and first pose with that
``z`` (``dynamics.predict_sequence(..., latent=z)``). With ``z = 0`` a latent model is the model
without session, and :func:`pipeline.dynamics.model.step` (the environments' path) runs it so.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax

from pipeline.dynamics import model as dynamics
from pipeline.dynamics.model import NUM_CHAMBERS, POSITION_DIM, DynamicsParams

DEFAULT_PRIOR = 1.0e-3  # standardized squared error per unit of |z|²


@dataclass(frozen=True)
class SessionLatentSettings:
    """The session latent a model trains with (hashable: static under ``jit``).

    dim: the latent's dimension ``d`` (>= 1).
    prior: weight of ``|z|²`` against the mean standardized squared error, in training and in
        inference (:func:`infer_latent`).
    """

    dim: int = 4
    prior: float = DEFAULT_PRIOR

    def __post_init__(self):
        if isinstance(self.dim, bool) or not isinstance(self.dim, int) or self.dim < 1:
            raise ValueError(f"session latent dim must be an integer >= 1, got {self.dim!r}")
        if not self.prior >= 0:
            raise ValueError(f"session latent prior must be >= 0, got {self.prior}")


def training_latents(params: DynamicsParams, trained_only: bool = False) -> jax.Array:
    """[R, d] the latents the model learned for its training data's runs (sorted by id);
    ``trained_only``: without the rows no window read (a held-out run's row, exactly 0)."""
    if dynamics.session_latent_dim(params) == 0:
        raise ValueError("the model has no session latent (trained without one)")
    table = params.network[dynamics.SESSION]["latents"]
    if trained_only:
        table = table[np.any(np.asarray(table) != 0, axis=-1)]
    return table


def context_loss(params: DynamicsParams, latent: jax.Array, inputs: jax.Array,
                 targets: jax.Array, pose_normalized: jax.Array, prior: float,
                 center: jax.Array) -> jax.Array:
    """The inference objective, a scalar: the mean standardized squared error of the rollout
    over the context given ``latent`` [d], plus ``prior * |latent - center|²``.

    inputs: [n, D] network inputs of the context; targets: [n, 3] standardized targets;
    pose_normalized: [3] the standardized first pose of the run.
    """
    outputs = dynamics.predict_normalized(params, inputs, pose_normalized, latent=latent)
    chex.assert_equal_shape((outputs, targets))
    return (jnp.mean(jnp.square(outputs - targets))
            + prior * jnp.sum(jnp.square(latent - center)))


@functools.partial(jax.jit, static_argnames=("steps",))
def infer_latent(params: DynamicsParams, pressures: jax.Array, positions: jax.Array,
                 steps: int, learning_rate: float, prior: float,
                 center: jax.Array | None = None) -> jax.Array:
    """The session latent [d] of a context: pressures [n, 3] kPa, positions [n, 3] m (n >= 1,
    the run's first ``n`` steps; its first pose is the rollout's initial pose).

    ``steps`` Adam steps from ``z = center`` (default 0) with the step size ``learning_rate``
    decaying to 0 on a cosine, the weights fixed; ``prior`` weighs ``|z - center|²`` (as
    ``|z|²`` in training: ``SessionLatentSettings``).
    """
    chex.assert_shape(pressures, (None, NUM_CHAMBERS))
    chex.assert_shape(positions, (pressures.shape[0], POSITION_DIM))
    dim = dynamics.session_latent_dim(params)
    inputs = dynamics.network_inputs(params, pressures)
    initial_pose = positions[0]
    targets = dynamics.normalize_target(params, positions, initial_pose)
    pose_normalized = dynamics.normalize_pose(params.normalizer, initial_pose)
    optimizer = optax.adam(optax.cosine_decay_schedule(learning_rate, max(steps, 1)))
    center = jnp.zeros((dim,), jnp.float32) if center is None else center
    chex.assert_shape(center, (dim,))
    grad = jax.grad(lambda z: context_loss(params, z, inputs, targets, pose_normalized, prior,
                                           center))

    def one_step(state, _):
        latent, opt_state = state
        updates, opt_state = optimizer.update(grad(latent), opt_state, latent)
        return (optax.apply_updates(latent, updates), opt_state), None

    latent = center
    (latent, _), _ = jax.lax.scan(one_step, (latent, optimizer.init(latent)), None, length=steps)
    return latent
