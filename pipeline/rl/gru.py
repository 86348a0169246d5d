"""The recurrence of a resetting GRU over a sequence, with its gradient written out.

:func:`gru_sequence` runs flax ``GRUCell``'s equations on inputs already projected for all steps
(``x_t = input_t @ input_kernel + input_bias``, split into the gates' parts ``x_r, x_z, x_n``)::

    h'  = 0 where reset_t, else h_{t-1}
    r   = sigmoid(x_r + h' W_r)
    z   = sigmoid(x_z + h' W_z)
    n   = tanh(x_n + r * (h' W_n + b_n))
    h_t = (1 - z) * n + z * h'

Two choices make its gradient cheaper than autodiff of a plain ``lax.scan`` on XLA's CPU
backend, where a step of a small GRU is dominated by the number and shape of its operations:

- three ``[B, H] x [H, H]`` products per step, one per gate, rather than one ``[B, H] x [H, 3H]``
  product whose output is then sliced into the gates;
- a backward pass (``jax.custom_vjp``) that carries only ``dL/dh`` through the reversed scan and
  computes the hidden kernel's gradient after it, as one product over all ``T * B`` rows,
  instead of adding a ``[H, 3H]`` product into a loop-carried gradient at every step.

``python -m bench gru_kernel`` compares it with flax's ``GRUCell`` scanned: about 1.5 times
faster for a PPO gradient step, the same for acting (docs/results/PPO_RESULTS.md).

The results are GRUCell's to float rounding (``tests/test_ppo.py`` checks values and gradients
against the cell: outputs, and gradients by autodiff through it).
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp


def _gates(array: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``[..., 3H]`` (gates r, z, n side by side on the last axis) -> the three ``[..., H]``."""
    r, z, n = jnp.split(array, 3, axis=-1)
    return r, z, n


def _forward(hidden_kernel, hidden_bias, carry, projected, resets):
    """The scan; returns ``((carry_T, ys), residuals)``, the residuals ``[T, B, H]`` each:
    the state each step read (after its reset), r, z, n and ``h' W_n + b_n``."""
    chex.assert_rank([carry, projected, resets], [2, 3, 2])
    chex.assert_shape(projected, (*resets.shape, 3 * carry.shape[-1]))
    chex.assert_shape([hidden_kernel, hidden_bias], [(carry.shape[-1], 3 * carry.shape[-1]),
                                                     (carry.shape[-1],)])
    w_r, w_z, w_n = _gates(hidden_kernel)
    x_r, x_z, x_n = _gates(projected)

    def step(state, inputs):
        x_r_t, x_z_t, x_n_t, reset_t = inputs
        read = jnp.where(reset_t[:, None], 0.0, state)
        r = jax.nn.sigmoid(x_r_t + read @ w_r)
        z = jax.nn.sigmoid(x_z_t + read @ w_z)
        candidate_in = read @ w_n + hidden_bias
        n = jnp.tanh(x_n_t + r * candidate_in)
        state = (1.0 - z) * n + z * read
        return state, (state, read, r, z, n, candidate_in)

    last, (ys, *residuals) = jax.lax.scan(step, carry, (x_r, x_z, x_n, resets))
    return (last, ys), tuple(residuals)


@jax.custom_vjp
def gru_sequence(hidden_kernel: jax.Array, hidden_bias: jax.Array, carry: jax.Array,
                 projected: jax.Array, resets: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A resetting GRU over T steps (equations in the module docstring).

    Args:
      hidden_kernel: ``[H, 3H]`` the recurrent kernels of gates r, z, n side by side.
      hidden_bias: ``[H]`` the candidate's recurrent bias ``b_n``.
      carry: ``[B, H]`` the state before step 0.
      projected: ``[T, B, 3H]`` the projected inputs (gates r, z, n; input biases included).
      resets: ``[T, B]`` bool, the state is zeroed before step t where True.

    Returns ``(carry_T [B, H], ys [T, B, H])``, ``ys[t]`` the state after step t.
    """
    return _forward(hidden_kernel, hidden_bias, carry, projected, resets)[0]


def _gru_sequence_forward(hidden_kernel, hidden_bias, carry, projected, resets):
    outputs, residuals = _forward(hidden_kernel, hidden_bias, carry, projected, resets)
    return outputs, (hidden_kernel, residuals, resets)


def _gru_sequence_backward(saved, cotangents):
    hidden_kernel, (read, r, z, n, candidate_in), resets = saved
    d_last, d_ys = cotangents
    w_r, w_z, w_n = (w.T for w in _gates(hidden_kernel))

    def step(d_state, inputs):
        # d_state: dL/dh_t from the steps after t; inputs: step t's output cotangent, residuals
        d_y, read_t, r_t, z_t, n_t, candidate_t, reset_t = inputs
        d_state = d_state + d_y
        d_n = d_state * (1.0 - z_t) * (1.0 - n_t * n_t)  # at tanh's input
        d_z = d_state * (read_t - n_t) * z_t * (1.0 - z_t)  # at sigmoid's input
        d_r = d_n * candidate_t * r_t * (1.0 - r_t)
        d_candidate = d_n * r_t
        d_read = d_state * z_t + d_r @ w_r + d_z @ w_z + d_candidate @ w_n
        return jnp.where(reset_t[:, None], 0.0, d_read), (d_r, d_z, d_n, d_candidate)

    d_carry, (d_r, d_z, d_n, d_candidate) = jax.lax.scan(
        step, d_last, (d_ys, read, r, z, n, candidate_in, resets), reverse=True)
    d_recurrent = jnp.concatenate([d_r, d_z, d_candidate], axis=-1)  # at h' W, [T, B, 3H]
    d_kernel = read.reshape(-1, read.shape[-1]).T @ d_recurrent.reshape(-1, d_recurrent.shape[-1])
    d_projected = jnp.concatenate([d_r, d_z, d_n], axis=-1)
    return d_kernel, d_candidate.sum(axis=(0, 1)), d_carry, d_projected, None


gru_sequence.defvjp(_gru_sequence_forward, _gru_sequence_backward)
