"""Analytic policy gradients (APG) through the differentiable environment, PureJaxRL style.

The learned environment is JAX from the action to the reward (the policy, the safe-set
projection, the recurrent model, the distance), so the policy's loss can be differentiated
through the environment itself instead of estimated from returns as PPO does. Each update:

    a window of agent.num_steps control periods of agent.num_envs running episodes
      ├ the deterministic (mean) action of the policy at every step, through env.step
      ├ loss = mean over episodes and steps of -reward (the distance to the goal in mm, plus
      │        the env's price on command changes) + a pull back into [-1, 1] of mean actions
      │        beyond it (where the clip passes no gradient)
      └ one Adam step on its gradient (global norm clipped at agent.max_grad_norm)

and the windows follow each other along the episodes (SHAC's truncation, without a critic): the
state at a window's start (plant carry, observation, policy hidden state) is the previous
window's end, detached, so a gradient runs through at most ``agent.num_steps`` periods and a long
episode cannot make it explode. Episodes reset as PPO's do (gymnax's auto-reset: a start state
from the reset bank, a goal as the env draws it, the ensemble member and the randomization of
``env.randomization`` drawn per episode by the env). They run their whole ``max_steps``: the goal
tolerance does not end them (as in the evaluation), so the summed distance also teaches staying
at the goal; a hold bonus (``env.hold_bonus_mm``), paid for a period within the tolerance, is
neither paid nor differentiable here.

The policy is PPO's actor-critic (:func:`pipeline.rl.networks.make_network`, the same variables,
the critic untouched), acting with its mean: checkpoints go to ``evaluate`` and ``control``
unchanged. Feed-forward and recurrent policies share the code (the GRU's hidden state is carried
along the window and detached between windows like the environment's). The parts are
:class:`pipeline.rl.training.TrainProgram`'s, so :func:`pipeline.rl.training.train_seeds` runs
them: seeds vmapped, one compiled chunk, the same evaluations and ``agent.stop_at``.

An environment whose step is not differentiable (gymnax's ``supports_transition_gradients``
false) is refused with a :class:`~pipeline.schemas.ConfigError`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from pipeline.rl.evaluation import evaluate_policy
from pipeline.rl.networks import make_network
from pipeline.rl.spaces import action_bounds, to_env_action
from pipeline.rl.training import (
    Build,
    RunnerState,
    TrainProgram,
    has_distance,
    init_runner,
    masked_mean,
)
from pipeline.schemas import AgentConfig, ConfigError

# weight of the pull of mean actions beyond [-1, 1] back into it, per (action unit)^2 and in
# the loss's units (mm): the clip to [-1, 1] passes no gradient, so a mean that has left the box
# would stay there
_BOUND_WEIGHT = 10.0


class Window(NamedTuple):
    """One window's steps, ``[T, B]`` each (T = agent.num_steps, B = agent.num_envs)."""

    reward: jax.Array  # [T, B] as the env returns it (differentiable)
    done: jax.Array  # [T, B] bool: the episode ended at this step (then reset)
    episode_return: jax.Array  # [T, B] the running episode's return up to this step
    episode_length: jax.Array  # [T, B] int32
    distance: jax.Array  # [T, B] m, to the goal after the step (0 without one)
    excess: jax.Array  # [T, B] (action units)^2: the mean action's squared excess beyond [-1, 1]


def differentiable_env(env: Any) -> Any:
    """``env`` as a copy whose step keeps its gradients (gymnax's
    ``with_transition_gradients``); a :class:`ConfigError` where it has none."""
    if not getattr(env, "supports_transition_gradients", False):
        raise ConfigError(f"agent.trainer=apg needs an environment whose step is "
                          f"differentiable; {env.name} is not (train it with agent=ppo_ff or "
                          f"agent=ppo_rnn)")
    return env.with_transition_gradients()


def make_train_program(agent: Any, env: Any, env_params: Any, eval_env_params: Any = None,
                       eval_steps: int | None = None) -> TrainProgram:
    """Build APG's parts of a training run (:class:`pipeline.rl.training.TrainProgram`:
    ``init``, ``chunk``, ``num_chunks``); the arguments are
    :func:`pipeline.rl.ppo.make_train_program`'s.

    ``init`` is PPO's (network, optimizer, ``agent.num_envs`` environments reset) with one
    optimizer step per update, so ``agent.anneal_lr`` anneals over ``agent.num_updates``.
    """
    config = AgentConfig.from_any(agent)
    config.check()
    eval_env_params = env_params if eval_env_params is None else eval_env_params
    if eval_steps is None:
        eval_steps = int(env_params.max_steps_in_episode)
    low, high = action_bounds(env, env_params)
    eval_bounds = action_bounds(env, eval_env_params)
    # one optimizer step per update: PPO's schedule counts update_epochs x num_minibatches
    one_step = dataclasses.replace(config, update_epochs=1, num_minibatches=1)
    build = Build(one_step, differentiable_env(env), make_network(config, int(np.prod(low.shape))),
                  low, high, tuple(env.observation_space(env_params).shape),
                  has_distance(env, env_params))

    def init(rng: jax.Array, env_params=env_params, init_params=None) -> RunnerState:
        return init_runner(build, rng, env_params, init_params)

    def chunk(runner: RunnerState, chunk_index, env_params=env_params,
              eval_env_params=eval_env_params):
        update_indices = (chunk_index * config.updates_per_eval
                          + jnp.arange(config.updates_per_eval))
        runner, metrics = jax.lax.scan(
            lambda r, i: _update_step(build, r, i, env_params), runner, update_indices)
        rng, eval_key = jax.random.split(runner.rng)
        evaluation = evaluate_policy(env, eval_env_params, build.network,
                                     runner.train_state.params, eval_key, config.eval_envs,
                                     eval_steps, build.has_distance, eval_bounds)
        evaluation["timesteps"] = metrics["timesteps"][-1]
        return runner._replace(rng=rng), (metrics, evaluation)

    return TrainProgram(init, chunk, config.num_evals)


def whole_episodes(env_params: Any) -> Any:
    """``env_params`` whose goal tolerance (where it has one) ends no episode: each runs its
    whole ``max_steps``, as the evaluation runs it."""
    tolerance = getattr(env_params, "goal_tolerance_m", None)
    if tolerance is None:
        return env_params
    return env_params.replace(goal_tolerance_m=jnp.full_like(tolerance, -jnp.inf))


def rollout_window(build: Build, params: Any, runner: RunnerState, key: jax.Array,
                   env_params: Any) -> tuple[RunnerState, Window]:
    """``agent.num_steps`` steps of the mean action from ``runner``'s state (taken as it is:
    the caller detaches it), differentiable in ``params``; returns the runner at the window's
    end (its ``train_state`` and ``rng`` untouched) and the :class:`Window`."""
    num_envs = build.config.num_envs

    def step(runner: RunnerState, step_key: jax.Array):
        hidden, pi, _ = build.network.apply(params, runner.hidden, runner.obs[None],
                                            runner.reset[None])
        mean = pi.mode()[0]  # [B, A]
        obs, env_state, reward, terminated, truncated, info = jax.vmap(
            build.env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(step_key, num_envs), runner.env_state,
            to_env_action(mean, build.low, build.high), env_params)
        done = jnp.logical_or(terminated, truncated)
        episode_return = runner.episode_return + jax.lax.stop_gradient(reward)
        episode_length = runner.episode_length + 1
        distance = info["distance_m"] if build.has_distance else jnp.zeros(num_envs)
        window = Window(reward, done, episode_return, episode_length,
                        jax.lax.stop_gradient(distance),
                        (jax.nn.relu(jnp.abs(mean) - 1.0) ** 2).sum(-1))
        runner = runner._replace(
            env_state=env_state, obs=obs, reset=done, hidden=hidden,
            episode_return=jnp.where(done, 0.0, episode_return),
            episode_length=jnp.where(done, 0, episode_length))
        return runner, window

    return jax.lax.scan(step, runner, jax.random.split(key, build.config.num_steps))


def _update_step(build: Build, runner: RunnerState, update_index: jax.Array, env_params: Any
                 ) -> tuple[RunnerState, dict[str, jax.Array]]:
    """One APG update: a window from the detached running state, the gradient of its loss,
    one optimizer step; ``-> (runner, metrics)`` (scalars)."""
    rng, window_key = jax.random.split(runner.rng)
    start = jax.lax.stop_gradient(runner)
    train_params = whole_episodes(env_params)

    def loss_fn(params):
        end, window = rollout_window(build, params, start, window_key, train_params)
        loss = -window.reward.mean() + _BOUND_WEIGHT * window.excess.mean()
        return loss, (end, window)

    (loss, (end, window)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
        runner.train_state.params)
    train_state = runner.train_state.apply_gradients(grads=grads)
    runner = jax.lax.stop_gradient(end)._replace(train_state=train_state, rng=rng)
    return runner, _update_metrics(build, loss, optax.tree.norm(grads), window, update_index,
                                   env_params)


def _update_metrics(build: Build, loss: jax.Array, grad_norm: jax.Array, window: Window,
                    update_index: jax.Array, env_params: Any) -> dict[str, jax.Array]:
    """The update's loss, gradient norm, mean distance along the window and the episodes that
    ended in it (their return, length, final distance, and success: ending within the env's
    goal tolerance, where it has one)."""
    config, done = build.config, window.done
    tolerance = getattr(env_params, "goal_tolerance_m", None)
    success = (window.distance <= tolerance if tolerance is not None and build.has_distance
               else jnp.zeros_like(done))
    return {
        "loss": loss,
        "grad_norm": grad_norm,
        "window_distance_m": (window.distance.mean() if build.has_distance else jnp.nan),
        "timesteps": (update_index + 1) * config.num_steps * config.num_envs,
        "episodes": done.sum(),
        "mean_return": masked_mean(window.episode_return, done),
        "mean_length": masked_mean(window.episode_length.astype(jnp.float32), done),
        "success_rate": masked_mean(success.astype(jnp.float32), done),
        "final_distance_m": (masked_mean(window.distance, done) if build.has_distance
                             else jnp.nan),
    }
