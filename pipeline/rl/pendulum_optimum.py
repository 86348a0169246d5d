"""The optimum of gymnax's Pendulum-v1: a reference that no policy can beat by much.

Backward value iteration over a grid of (angle, angular velocity) with bilinear interpolation
and a set of torque levels, 200 steps as in an episode (:func:`solve`); the greedy policy of that
value function run on the exact dynamics from gymnax's reset distribution
(:func:`optimal_returns`); a trained policy run, deterministically or sampled, from the same
start states (:func:`policy_returns`). The measurement scripts ``experiments/pendulum_*.py``
compare PPO with it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import gymnax
import jax
import jax.numpy as jnp
import numpy as np

from pipeline.rl.envs.factory import BoundsScaledObservation
from pipeline.rl.networks import initial_hidden
from pipeline.rl.policy_io import deterministic_action, load_policy
from pipeline.rl.spaces import to_env_action


class Optimum(NamedTuple):
    """The value-iteration solution: ``values[t]`` [A, V], the optimal return from step t."""

    env: Any
    params: Any
    torques: jax.Array  # [K] torque levels
    values: jax.Array  # [horizon, A, V]
    q_values: Callable  # (value [A, V], theta [...], theta_dot [...]) -> [..., K]
    interpolate: Callable  # (value [A, V], theta [...], theta_dot [...]) -> [...]


def solve(num_angles: int = 512, num_velocities: int = 321, num_torques: int = 41) -> Optimum:
    """Backward value iteration over 200 steps on a (angle, velocity) grid."""
    env, params = gymnax.make("Pendulum-v1")
    horizon = int(params.max_steps_in_episode)
    angles = jnp.linspace(-jnp.pi, jnp.pi, num_angles, endpoint=False)
    angle_step = 2 * jnp.pi / num_angles
    velocities = jnp.linspace(-params.max_speed, params.max_speed, num_velocities)
    velocity_step = velocities[1] - velocities[0]
    torques = jnp.linspace(-params.max_torque, params.max_torque, num_torques)

    def dynamics(theta, theta_dot, torque):
        """gymnax Pendulum-v1: reward and next state (the same equations as ``step_env``)."""
        wrapped = ((theta + jnp.pi) % (2 * jnp.pi)) - jnp.pi
        reward = -(wrapped**2 + 0.1 * theta_dot**2 + 0.001 * torque**2)
        new_dot = jnp.clip(theta_dot + (3 * params.g / (2 * params.l) * jnp.sin(theta)
                                        + 3.0 / (params.m * params.l**2) * torque) * params.dt,
                           -params.max_speed, params.max_speed)
        return reward, theta + new_dot * params.dt, new_dot

    def interpolate(value, theta, theta_dot):
        """Bilinear in (angle, periodic; velocity, clamped) on the grid; value [A, V]."""
        a = ((theta + jnp.pi) % (2 * jnp.pi)) / angle_step
        v = jnp.clip((theta_dot + params.max_speed) / velocity_step, 0, num_velocities - 1.001)
        a0, v0 = jnp.floor(a).astype(int), jnp.floor(v).astype(int)
        fa, fv = a - a0, v - v0
        a1 = (a0 + 1) % num_angles
        a0 = a0 % num_angles
        return ((1 - fa) * (1 - fv) * value[a0, v0] + fa * (1 - fv) * value[a1, v0]
                + (1 - fa) * fv * value[a0, v0 + 1] + fa * fv * value[a1, v0 + 1])

    theta_grid, dot_grid = jnp.meshgrid(angles, velocities, indexing="ij")

    def q_values(value, theta, theta_dot):
        """[..., torques]: reward + value of the next state, for every torque level."""
        reward, next_theta, next_dot = dynamics(theta[..., None], theta_dot[..., None], torques)
        return reward + interpolate(value, next_theta, next_dot)

    @jax.jit
    def backward(_):
        def sweep(value, _):
            new = q_values(value, theta_grid, dot_grid).max(-1)
            return new, new
        _, values = jax.lax.scan(sweep, jnp.zeros_like(theta_grid), None, length=horizon)
        return values[::-1]  # values[t]: optimal return from step t to the end

    return Optimum(env, params, torques, backward(0), q_values, interpolate)


def greedy_torque(optimum: Optimum, value: jax.Array, theta: jax.Array, theta_dot: jax.Array
                  ) -> jax.Array:
    """[...] the torque level that is greedy with respect to ``value`` [A, V] (value to go from
    the next step)."""
    return optimum.torques[jnp.argmax(optimum.q_values(value, theta, theta_dot), axis=-1)]


def optimal_returns(optimum: Optimum, keys: jax.Array, stationary: bool = False
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Returns of the greedy policy from ``reset_env(keys[i])`` on the exact dynamics, and the
    grid's own prediction of them. The policy is time-dependent (the optimum), or with
    ``stationary`` greedy with respect to ``values[1]`` at every step (what a policy that does not
    see the time can copy)."""
    env, params, values = optimum.env, optimum.params, optimum.values
    horizon = int(params.max_steps_in_episode)

    @jax.jit
    def run(keys, values):  # values an argument, not a constant XLA would fold
        def episode(key):
            _, state = env.reset_env(key, params)

            def step(state, value):
                value = values[1] if stationary else value
                torque = greedy_torque(optimum, value, state.theta, state.theta_dot)
                _, state, reward, _, _ = env.step_env(key, state, jnp.array([torque]), params)
                return state, reward
            predicted = optimum.interpolate(values[0], state.theta, state.theta_dot)
            # the value to go from step t+1 decides the action at step t
            next_values = (None if stationary else
                           jnp.concatenate([values[1:], jnp.zeros_like(values[:1])]))
            return jax.lax.scan(step, state, next_values, horizon)[1].sum(), predicted
        return jax.vmap(episode)(keys)

    returns, predicted = run(keys, values)
    return np.asarray(returns), np.asarray(predicted)


def policy_returns(env, params, policy_path: str | Path, keys: jax.Array,
                   sampled: bool = False) -> np.ndarray:
    """[seeds, episodes] returns of the policy's mean action from ``reset_env(keys[i])``, or with
    ``sampled`` of actions drawn from its distribution (as in training, and as the gymnax-blines
    evaluation that the published figure comes from)."""
    network, stacked, meta = load_policy(policy_path)
    if meta.get("env", {}).get("scale_observations"):
        env = BoundsScaledObservation(env)  # as the policy was trained (train_ppo)
    low, high = np.asarray(meta["action_low"], np.float32), np.asarray(meta["action_high"],
                                                                       np.float32)
    horizon = int(params.max_steps_in_episode)

    @jax.jit
    def run(variables):
        def episode(key):
            obs, state = env.reset(key, params)  # reset_env(key): the optimum's start state

            def step(carry, noise_key):
                obs, state, hidden = carry
                if sampled:
                    hidden, pi, _ = network.apply(variables, hidden, obs[None, None],
                                                  jnp.zeros((1, 1), bool))
                    action = pi.sample(seed=noise_key)[0]
                else:
                    hidden, action = deterministic_action(network, variables, hidden, obs[None],
                                                          jnp.zeros(1, bool))
                # 200 steps: the auto-reset of step() comes after the last reward
                obs, state, reward, _, _, _ = env.step(
                    key, state, to_env_action(action[0], low, high), params)
                return (obs, state, hidden), reward
            carry = (obs, state, initial_hidden(network, 1))
            noise_keys = jax.random.split(jax.random.fold_in(key, 1), horizon)
            return jax.lax.scan(step, carry, noise_keys)[1].sum()
        return jax.vmap(episode)(keys)

    num_seeds = int(meta.get("num_seeds", 1))
    return np.stack([np.asarray(run(jax.tree.map(lambda x, i=i: x[i], stacked)))
                     for i in range(num_seeds)])
