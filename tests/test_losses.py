"""PPO's loss and minibatching on hand-computed numbers."""

from __future__ import annotations

import distrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipeline.rl.losses import ppo_loss
from pipeline.rl.minibatches import sequence_minibatches, step_minibatches
from pipeline.rl.ppo import Transition
from pipeline.schemas import AgentConfig


class FixedNetwork:
    """Stands in for the actor-critic: a unit Gaussian at ``mean`` and the given values."""

    def __init__(self, mean, value):
        self.mean, self.value = jnp.asarray(mean), jnp.asarray(value)

    def apply(self, params, hidden, obs, reset):
        pi = distrax.MultivariateNormalDiag(self.mean + params, jnp.ones_like(self.mean))
        return hidden, pi, self.value


def batch_for(action, log_prob, value):
    shape = value.shape
    return Transition(obs=jnp.zeros((*shape, 1)), reset=jnp.zeros(shape, bool), action=action,
                      log_prob=log_prob, value=value, reward=jnp.zeros(shape),
                      terminated=jnp.zeros(shape, bool), truncated=jnp.zeros(shape, bool),
                      bootstrap_value=jnp.zeros(shape))


def test_ppo_loss_on_hand_computed_numbers():
    # two steps, one action dimension; the policy is unchanged since the rollout: ratio 1
    mean = jnp.zeros((1, 2, 1))
    action = jnp.array([[[0.5], [-1.0]]])
    pi = distrax.MultivariateNormalDiag(mean, jnp.ones_like(mean))
    batch = batch_for(action, pi.log_prob(action), value=jnp.array([[1.0, 2.0]]))
    network = FixedNetwork(mean, value=jnp.array([[1.5, 1.0]]))
    advantage, target = jnp.array([[1.0, -1.0]]), jnp.array([[2.0, 2.0]])
    config = AgentConfig(clip_eps=0.2, clip_value=False, vf_coef=0.5, ent_coef=0.0)
    total, aux = ppo_loss(0.0, network, None, batch, advantage, target, config)
    # standardized advantages are +-1 with mean 0: actor loss -mean(1 * A) = 0
    assert float(aux["actor_loss"]) == pytest.approx(0.0, abs=1e-6)
    # value loss 0.5 * mean((1.5 - 2)^2, (1 - 2)^2) = 0.5 * (0.25 + 1) / 2
    assert float(aux["value_loss"]) == pytest.approx(0.3125)
    assert float(total) == pytest.approx(0.5 * 0.3125)
    assert float(aux["approx_kl"]) == pytest.approx(0.0, abs=1e-6)
    # entropy of a unit Gaussian: 0.5 * log(2 pi e)
    assert float(aux["entropy"]) == pytest.approx(0.5 * np.log(2 * np.pi * np.e), rel=1e-6)

    # the value clipped around the rollout's values: 1 + clip(0.5, +-0.2) = 1.2 for step 0,
    # 2 + clip(-1, +-0.2) = 1.8 for step 1; the loss takes the larger squared error of each
    clipped = AgentConfig(clip_eps=0.2, clip_value=True, vf_coef=0.5, ent_coef=0.0)
    _, aux = ppo_loss(0.0, network, None, batch, advantage, target, clipped)
    expected = 0.5 * np.mean([max(0.25, (1.2 - 2) ** 2), max(1.0, (1.8 - 2) ** 2)])
    assert float(aux["value_loss"]) == pytest.approx(expected)


def test_ppo_loss_clips_the_ratio():
    # the policy mean moved by +1 since the rollout: ratio exp(log N(a; 1) - log N(a; 0))
    mean = jnp.zeros((1, 2, 1))
    action = jnp.array([[[1.0], [1.0]]])
    old = distrax.MultivariateNormalDiag(mean, jnp.ones_like(mean))
    batch = batch_for(action, old.log_prob(action), value=jnp.zeros((1, 2)))
    network = FixedNetwork(mean, value=jnp.zeros((1, 2)))
    config = AgentConfig(clip_eps=0.2, clip_value=False, vf_coef=0.0, ent_coef=0.0)
    _, aux = ppo_loss(1.0, network, None, batch, jnp.array([[1.0, -1.0]]), jnp.zeros((1, 2)),
                      config)
    ratio = np.exp(0.5)  # log N(1; 1) - log N(1; 0) = 0.5
    # A = +1: min(r, 1.2) = 1.2; A = -1: min(-r, -1.2) = -r; actor loss = -(1.2 - r) / 2
    assert float(aux["actor_loss"]) == pytest.approx(-(1.2 - ratio) / 2, rel=1e-5)
    assert float(aux["clip_fraction"]) == 1.0


def test_step_minibatches_shuffle_every_step_once():
    data = jnp.arange(24.0).reshape(4, 6)  # [T=4, B=6]
    hidden, batches = step_minibatches(jax.random.key(0), data, num_minibatches=3)
    assert batches.shape == (3, 8) and hidden.shape == (3, 8, 1)
    assert sorted(np.asarray(batches).ravel().tolist()) == list(range(24))
    assert not np.array_equal(np.asarray(batches).ravel(), np.arange(24))  # shuffled


def test_sequence_minibatches_keep_whole_sequences_and_their_hidden_state():
    num_steps, num_envs = 5, 4
    data = 100.0 * jnp.arange(num_envs)[None, :] + jnp.arange(num_steps)[:, None]  # 100 b + t
    rollout_hidden = jnp.arange(num_envs, dtype=jnp.float32)[:, None] * jnp.ones((1, 3))
    hidden, batches = sequence_minibatches(jax.random.key(1), data, rollout_hidden, 2)
    assert batches.shape == (2, num_steps, 2) and hidden.shape == (2, 2, 3)
    envs = np.asarray(batches[:, 0, :]) // 100  # the environment of each column
    assert sorted(envs.ravel().tolist()) == list(range(num_envs))
    for m in range(2):
        for column in range(2):
            env = envs[m, column]
            np.testing.assert_array_equal(batches[m, :, column], 100 * env + np.arange(num_steps))
            np.testing.assert_array_equal(hidden[m, column], np.full(3, env))
