"""A fitted model calibrated to a session, as a model of its own.

:func:`fold_correction` folds a :class:`~pipeline.dynamics.adaptation.SessionCorrection` into
the model's parameters, so that the calibrated model is a plain ``DynamicsParams`` (one model
file, read wherever a fit_model artifact's model is read: the learned environment, evaluation):

* the input affine ``p' = (1 + g) p + o`` into the pressure normalizer:
  ``mean' = (mean - o) / (1 + g)``, ``std' = std / (1 + g)`` (the standardized pressure and the
  pressure-change features, divided by the same std, are then those of ``p'``; the command-step
  detection still sees ``p``, and play operators, whose widths are in kPa, are not folded:
  :func:`fold_error_m` measures what is left);
* the readout change into the readout layer;
* the output affine ``x̂ = c + (I + M)(y - c) + b`` into the readout and the target mean: with
  ``y = x_0 + s ⊙ u + m`` (``u`` the readout, ``s``, ``m`` the target std and mean, ``x_0``
  only for a displacement model) the readout becomes ``A u`` with
  ``A = diag(1/s) (I + M) diag(s)`` and ``m' = m + M (m + x_ref - c) + b``; exact for an
  absolute model, for a displacement model exact at ``x_0 = x_ref`` (the pose the session's
  context starts from) and off by ``M (x_0 - x_ref)`` elsewhere.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np

from pipeline.dynamics import model as dynamics
from pipeline.dynamics.adaptation import SessionCorrection, predict_adapted
from pipeline.dynamics.model import NUM_CHAMBERS, POSITION_DIM, DynamicsParams


def fold_correction(params: DynamicsParams, correction: SessionCorrection,
                    reference_pose: jax.Array) -> DynamicsParams:
    """``params`` with ``correction`` folded in (module docstring); ``reference_pose`` [3] m:
    the initial pose the output turn is exact at (a displacement model's ``x_ref``)."""
    chex.assert_shape(reference_pose, (POSITION_DIM,))
    normalizer = params.normalizer
    gain = 1.0 + correction.input_gain
    normalizer = normalizer.replace(
        pressure_mean=(normalizer.pressure_mean - correction.input_offset_kpa) / gain,
        pressure_std=normalizer.pressure_std / gain)
    network = params.network["params"]
    readout = network["readout"]
    if correction.readout_delta is not None:
        readout = jax.tree.map(jnp.add, readout, correction.readout_delta)
    turn = jnp.eye(POSITION_DIM) + correction.output_matrix
    std, mean = normalizer.target_std, normalizer.target_mean
    mix = turn * std[None, :] / std[:, None]  # A = diag(1/s) (I + M) diag(s)
    readout = {**readout, "kernel": readout["kernel"] @ mix.T, "bias": mix @ readout["bias"]}
    reference = (jnp.asarray(reference_pose, jnp.float32) if params.config.predict_displacement
                 else jnp.zeros((POSITION_DIM,), jnp.float32))
    mean = (mean + correction.output_matrix @ (mean + reference - correction.center_m)
            + correction.output_offset_m)
    normalizer = normalizer.replace(target_mean=mean)
    return params.replace(network={**params.network, "params": {**network, "readout": readout}},
                          normalizer=normalizer)


def fold_error_m(params: DynamicsParams, correction: SessionCorrection, folded: DynamicsParams,
                 pressures: np.ndarray, initial_pose: np.ndarray) -> float:
    """Largest distance [m] between the folded model's open-loop prediction and the calibrated
    one (:func:`~pipeline.dynamics.adaptation.predict_adapted`) along pressures [T, 3] kPa from
    ``initial_pose`` [3] m."""
    chex.assert_shape(pressures, (None, NUM_CHAMBERS))
    pressures = jnp.asarray(pressures, jnp.float32)
    pose = jnp.asarray(initial_pose, jnp.float32)
    calibrated = predict_adapted(params, correction, pressures, pose)
    plain = dynamics.predict_sequence(folded, pressures, pose)
    return float(jnp.max(jnp.linalg.norm(calibrated - plain, axis=-1)))
