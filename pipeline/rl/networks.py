"""Actor-critic networks for PPO: feed-forward (MLP) and recurrent (GRU), one call signature.

Both are called on time-major batches::

    hidden_T, pi, value = network.apply(variables, hidden_0, obs, resets)

with ``obs [T, B, obs_dim]``, ``resets [T, B]`` (True where ``obs[t]`` starts a new episode: the
GRU state is zeroed before it is read), ``hidden_0 [B, H]``; ``pi`` is a diagonal Gaussian over
``[T, B, action_dim]`` (actions in ``[-1, 1]`` units, clipped by the caller) and ``value [T, B]``.
The feed-forward network ignores ``hidden`` and ``resets`` (its hidden state is a dummy
``[B, 1]``), so the PPO code has one path for both.
"""

from __future__ import annotations

from typing import Any

import chex
import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax.linen.initializers import constant, orthogonal

from pipeline.rl.gru import gru_sequence

ACTIVATIONS = {"tanh": nn.tanh, "relu": nn.relu}


def _activation(name: str):
    if name not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {name!r}")
    return ACTIVATIONS[name]


class MLP(nn.Module):
    """``num_layers`` dense layers of ``width`` with orthogonal(sqrt 2) init, then a linear
    output of ``out`` units with orthogonal(``out_scale``) init."""

    width: int
    num_layers: int
    out: int
    out_scale: float
    activation: str = "tanh"

    @nn.compact
    def __call__(self, x):
        act = _activation(self.activation)
        for _ in range(self.num_layers):
            x = act(nn.Dense(self.width, kernel_init=orthogonal(np.sqrt(2)),
                             bias_init=constant(0.0))(x))
        return nn.Dense(self.out, kernel_init=orthogonal(self.out_scale),
                        bias_init=constant(0.0))(x)


class GaussianActorCriticHeads(nn.Module):
    """Separate actor and critic MLPs on the same features.

    The log std is one learned vector by default. With ``state_dependent_std`` the actor also
    outputs it (as gymnax-blines' Gaussian MLP does), so the policy can be precise in some states
    and explore in others; it starts at ``log_std_init`` everywhere and is kept in [-5, 2]."""

    action_dim: int
    width: int
    num_layers: int
    activation: str
    log_std_init: float
    state_dependent_std: bool = False

    @nn.compact
    def __call__(self, features):
        outputs = (2 if self.state_dependent_std else 1) * self.action_dim
        actor = MLP(self.width, self.num_layers, outputs, 0.01, self.activation,
                    name="actor")(features)
        mean = actor[..., :self.action_dim]
        if self.state_dependent_std:
            log_std = jnp.clip(self.log_std_init + actor[..., self.action_dim:], -5.0, 2.0)
        else:
            log_std = self.param("log_std", constant(self.log_std_init), (self.action_dim,))
        value = MLP(self.width, self.num_layers, 1, 1.0, self.activation, name="critic")(features)
        pi = distrax.MultivariateNormalDiag(mean, jnp.exp(log_std) * jnp.ones_like(mean))
        return pi, jnp.squeeze(value, axis=-1)


class ActorCriticFF(nn.Module):
    """Feed-forward actor-critic (``hidden`` and ``resets`` are ignored and passed through)."""

    action_dim: int
    width: int = 64
    num_layers: int = 2
    activation: str = "tanh"
    log_std_init: float = 0.0
    state_dependent_std: bool = False

    @nn.compact
    def __call__(self, hidden, obs, resets):
        pi, value = GaussianActorCriticHeads(self.action_dim, self.width, self.num_layers,
                                             self.activation, self.log_std_init,
                                             self.state_dependent_std)(obs)
        return hidden, pi, value

    @staticmethod
    def initialize_carry(batch_size: int) -> jax.Array:
        return jnp.zeros((batch_size, 1), jnp.float32)


class _Dense(nn.Module):
    """The variables of one ``nn.Dense``: ``kernel [fan_in, features]`` and optional ``bias``."""

    features: int
    use_bias: bool
    kernel_init: Any
    bias_init: Any

    @nn.compact
    def __call__(self, fan_in: int):
        kernel = self.param("kernel", self.kernel_init, (fan_in, self.features))
        bias = self.param("bias", self.bias_init, (self.features,)) if self.use_bias else None
        return kernel, bias


class GRUWeights(nn.Module):
    """The variables of ``flax.linen.GRUCell`` (same names, shapes and initializers), returned
    fused, gates in the order (r, z, n): ``input_kernel [D, 3H]``, ``input_bias [3H]``,
    ``hidden_kernel [H, 3H]`` and the candidate's own hidden bias ``hidden_bias [H]``."""

    features: int

    @nn.compact
    def __call__(self, input_dim: int):
        cell, h = nn.GRUCell(self.features), self.features  # the cell: for its initializers
        inputs = [_Dense(h, True, cell.kernel_init, cell.bias_init, name=f"i{gate}")(input_dim)
                  for gate in "rzn"]
        hidden = [_Dense(h, gate == "n", cell.recurrent_kernel_init, cell.bias_init,
                         name=f"h{gate}")(h) for gate in "rzn"]
        return (jnp.concatenate([k for k, _ in inputs], axis=1),
                jnp.concatenate([b for _, b in inputs]),
                jnp.concatenate([k for k, _ in hidden], axis=1), hidden[2][1])


class ResettingGRU(nn.Module):
    """A GRU over time; the state is zeroed where ``resets[t]`` before step t.

    ``carry [B, H]``, ``inputs = (x [T, B, D], resets [T, B])`` -> ``(carry_T, y [T, B, H])``.
    The equations and parameters are ``flax.linen.GRUCell``'s (variables under ``GRUCell_0``):
    the input projections of all T steps in one ``[T*B, D] x [D, 3H]`` product before the
    recurrence, then :func:`pipeline.rl.gru.gru_sequence` (per-gate products, its own
    backward pass)."""

    features: int

    @nn.compact
    def __call__(self, carry, inputs):
        x, resets = inputs
        chex.assert_rank(x, 3)
        chex.assert_shape(resets, x.shape[:2])
        input_kernel, input_bias, hidden_kernel, hidden_bias = GRUWeights(
            self.features, name="GRUCell_0")(x.shape[-1])
        return gru_sequence(hidden_kernel, hidden_bias, carry, x @ input_kernel + input_bias,
                            resets)


class ActorCriticRNN(nn.Module):
    """Dense embedding -> GRU (reset at episode starts) -> Gaussian actor and critic heads.

    With ``skip`` the heads read the GRU output next to the current embedding, so what the
    present observation decides need not pass through the recurrent state (the GRU then only
    has to carry what the past adds)."""

    action_dim: int
    width: int = 64
    num_layers: int = 2
    rnn_hidden: int = 64
    activation: str = "tanh"
    log_std_init: float = 0.0
    state_dependent_std: bool = False
    skip: bool = False

    @nn.compact
    def __call__(self, hidden, obs, resets):
        act = _activation(self.activation)
        embedding = act(nn.Dense(self.rnn_hidden, kernel_init=orthogonal(np.sqrt(2)),
                                 bias_init=constant(0.0), name="embed")(obs))
        hidden, features = ResettingGRU(self.rnn_hidden, name="gru")(hidden, (embedding, resets))
        if self.skip:
            features = jnp.concatenate([features, embedding], axis=-1)
        pi, value = GaussianActorCriticHeads(self.action_dim, self.width, self.num_layers,
                                             self.activation, self.log_std_init,
                                             self.state_dependent_std)(features)
        return hidden, pi, value

    def initialize_carry(self, batch_size: int) -> jax.Array:
        return jnp.zeros((batch_size, self.rnn_hidden), jnp.float32)


def make_network(agent, action_dim: int) -> nn.Module:
    """The actor-critic of the ``agent`` config (fields recurrent, hidden, num_layers, ...)."""
    common = {"action_dim": int(action_dim), "width": int(agent.hidden),
              "num_layers": int(agent.num_layers), "activation": str(agent.activation),
              "log_std_init": float(agent.log_std_init),
              "state_dependent_std": bool(agent.state_dependent_std)}
    if agent.recurrent:
        return ActorCriticRNN(rnn_hidden=int(agent.rnn_hidden), skip=bool(agent.rnn_skip),
                              **common)
    return ActorCriticFF(**common)


def initial_hidden(network: nn.Module, batch_size: int) -> jax.Array:
    """Zero hidden state ``[batch_size, H]`` of either network (H = 1 for the MLP)."""
    if isinstance(network, ActorCriticRNN):
        return network.initialize_carry(batch_size)
    return ActorCriticFF.initialize_carry(batch_size)
