"""PPO in the PureJaxRL style: the whole training run is one pure, jittable function.

``make_train(agent, env, env_params)`` returns ``train(rng) -> TrainOutput``; jit it once and
``vmap`` it over seeds. :func:`pipeline.rl.training.train_seeds` runs the same training as its
two parts (:func:`make_train_program`: ``init`` and one evaluation chunk, each vmapped over seeds
and compiled once) with the loop over chunks on the host, where the progress bar advances: no
host callback inside a compiled program, so JAX's persistent cache keeps both. Inside,
``lax.scan`` runs

    evaluation chunks (agent.num_evals)
      └ updates (num_updates / num_evals)
          ├ rollout: agent.num_steps steps of agent.num_envs environments (vmap)
          ├ GAE (bootstrapped on truncation, not on termination)
          └ agent.update_epochs x agent.num_minibatches clipped-PPO gradient steps
      └ deterministic evaluation: agent.eval_envs episodes on the evaluation parameters

Feed-forward and recurrent (GRU) actor-critics share one code path (``pipeline.rl.networks``); the
recurrent one is trained on whole rollout sequences, minibatched over environments, starting from
the hidden state at the start of the rollout.

Time indices in a rollout of length T: ``obs[t]`` is seen, ``action[t]`` taken, ``reward[t]``,
``terminated[t]``, ``truncated[t]`` come back; ``reset[t]`` says ``obs[t]`` starts an episode.
When ``truncated[t]`` (and not ``terminated[t]``), the return is bootstrapped with the value of
the episode's final observation (``bootstrap_value[t]``, gymnax's ``info["final_observation"]``);
when ``terminated[t]`` nothing is bootstrapped.

Actions: the Gaussian policy acts in ``[-1, 1]`` units; samples are clipped and mapped linearly to
the environment's ``Box`` bounds (identity for the soft-arm environment, whose own action is
``[-1, 1]``). Log-probabilities are of the unclipped samples.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax.training.train_state import TrainState

from pipeline.rl.evaluation import evaluate_policy
from pipeline.rl.losses import compute_gae, ppo_loss
from pipeline.rl.minibatches import sequence_minibatches, step_minibatches
from pipeline.rl.networks import make_network
from pipeline.rl.spaces import action_bounds, to_env_action
from pipeline.rl.training import (
    Build,
    RunnerState,
    TrainOutput,
    TrainProgram,
    has_distance,
    init_runner,
    masked_mean,
)

# the host loop's entry points (pipeline.rl.training), importable from here too: the stages,
# bench/ and experiments/ import them from this module
from pipeline.rl.training import held_out_figures as held_out_figures
from pipeline.rl.training import seed_keys as seed_keys
from pipeline.rl.training import train_seeds as train_seeds
from pipeline.schemas import AgentConfig


# ---------------------------------------------------------------------------------------------
# data carried through the scans
# ---------------------------------------------------------------------------------------------
class Transition(NamedTuple):
    """One rollout step of every environment (leading axis [B]; stacked: [T, B])."""

    obs: jax.Array  # [B, obs_dim]
    reset: jax.Array  # [B] bool: obs starts an episode
    action: jax.Array  # [B, action_dim] unclipped policy sample, [-1, 1] units
    log_prob: jax.Array  # [B]
    value: jax.Array  # [B] V(obs)
    reward: jax.Array  # [B] scaled by agent.reward_scale
    terminated: jax.Array  # [B] bool
    truncated: jax.Array  # [B] bool
    bootstrap_value: jax.Array  # [B] V(final obs of the episode); used where truncated (filled
    # after the rollout, for all steps in one call: bootstrap_values in make_train)


# ---------------------------------------------------------------------------------------------
# training
# ---------------------------------------------------------------------------------------------
def make_train(
    agent: Any,
    env: Any,
    env_params: Any,
    eval_env_params: Any = None,
    eval_steps: int | None = None,
) -> Callable[..., TrainOutput]:
    """Build ``train(rng, env_params=None, eval_env_params=None, init_params=None)
    -> TrainOutput``; ``init_params`` (network variables of this agent's network) replace the
    random initialisation: a warm start. It is :func:`make_train_program`'s parts in one
    ``lax.scan``; the arguments are the same.
    """
    program = make_train_program(agent, env, env_params, eval_env_params, eval_steps)
    eval_env_params = env_params if eval_env_params is None else eval_env_params

    def train(rng: jax.Array, env_params=env_params, eval_env_params=eval_env_params,
              init_params=None) -> TrainOutput:
        runner = program.init(rng, env_params, init_params)
        runner, (metrics, evaluation) = jax.lax.scan(
            lambda r, i: program.chunk(r, i, env_params, eval_env_params), runner,
            jnp.arange(program.num_chunks))
        # [num_chunks, updates_per_eval, ...] -> [num_updates, ...]
        metrics = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), metrics)
        return TrainOutput(runner.train_state.params, metrics, evaluation)

    return train


def make_train_program(
    agent: Any,
    env: Any,
    env_params: Any,
    eval_env_params: Any = None,
    eval_steps: int | None = None,
) -> TrainProgram:
    """Build the parts of a training run (:class:`TrainProgram`).

    Args:
      agent: the agent config (``AgentConfig`` or anything :meth:`AgentConfig.from_any` reads).
      env: a gymnax environment with a ``Box`` action space.
      env_params: training parameters; ``eval_env_params`` (default: the same) are used for the
        deterministic evaluations. Both may be passed to ``train`` instead, as arguments, so large
        parameters (model weights) are not baked into the compiled program as constants.
      eval_steps: steps per evaluation (one episode per environment); default
        ``eval_env_params.max_steps_in_episode``.
    """
    config = AgentConfig.from_any(agent)
    config.check()
    eval_env_params = env_params if eval_env_params is None else eval_env_params
    if eval_steps is None:
        eval_steps = int(eval_env_params.max_steps_in_episode)
    low, high = action_bounds(env, env_params)  # read here: the env params are traced below
    eval_bounds = action_bounds(env, eval_env_params)
    build = Build(config, env, make_network(config, int(np.prod(low.shape))), low, high,
                  tuple(env.observation_space(env_params).shape), has_distance(env, env_params))

    def init(rng: jax.Array, env_params=env_params, init_params=None) -> RunnerState:
        return init_runner(build, rng, env_params, init_params)

    def chunk(runner: RunnerState, chunk_index, env_params=env_params,
              eval_env_params=eval_env_params):
        return _chunk(build, runner, chunk_index, env_params, eval_env_params, eval_steps,
                      eval_bounds)

    return TrainProgram(init, chunk, config.num_evals)


def _chunk(build: Build, runner: RunnerState, chunk_index: jax.Array, env_params: Any,
           eval_env_params: Any, eval_steps: int, eval_bounds: Any):
    """``agent.updates_per_eval`` updates, then one deterministic evaluation."""
    config = build.config
    update_indices = chunk_index * config.updates_per_eval + jnp.arange(config.updates_per_eval)
    runner, metrics = jax.lax.scan(
        lambda r, i: _update_step(build, r, i, env_params), runner, update_indices)
    rng, eval_key = jax.random.split(runner.rng)
    evaluation = evaluate_policy(build.env, eval_env_params, build.network,
                                 runner.train_state.params, eval_key, config.eval_envs,
                                 eval_steps, build.has_distance, eval_bounds)
    evaluation["timesteps"] = metrics["timesteps"][-1]
    return runner._replace(rng=rng), (metrics, evaluation)


def _apply_step(network: Any, params: Any, hidden: jax.Array, obs: jax.Array, reset: jax.Array):
    """One time step for a batch: [B, H], [B, D], [B] -> hidden, pi, value [B]."""
    hidden, pi, value = network.apply(params, hidden, obs[None], reset[None])
    return hidden, pi, value[0]


def _update_step(build: Build, runner: RunnerState, update_index: jax.Array, env_params: Any):
    """One PPO update: a rollout, its advantages, ``agent.update_epochs`` epochs of minibatch
    steps; ``-> (runner, metrics)`` (scalars)."""
    config = build.config
    rollout_hidden = runner.hidden
    runner, trajectory, episodes = _rollout(build, runner, env_params)
    _, _, last_value = _apply_step(build.network, runner.train_state.params, runner.hidden,
                                   runner.obs, runner.reset)
    advantages, targets = compute_gae(
        trajectory.reward, trajectory.value, trajectory.terminated, trajectory.truncated,
        trajectory.bootstrap_value, last_value, config.gamma, config.gae_lambda)
    rng, epoch_key = jax.random.split(runner.rng)
    train_state, losses = _ppo_epochs(build, runner.train_state, epoch_key,
                                      (trajectory, advantages, targets), rollout_hidden)
    runner = runner._replace(train_state=train_state, rng=rng)
    return runner, _update_metrics(build, losses, episodes, update_index)


def _rollout(build: Build, runner: RunnerState, env_params: Any):
    """``agent.num_steps`` steps of every environment: ``-> (runner, trajectory [T, B],
    episodes [T, B])``, the trajectory's ``bootstrap_value`` filled (:func:`_bootstrap_values`)."""
    config, num_envs = build.config, build.config.num_envs

    def rollout_step(runner: RunnerState, _):
        rng, action_key, step_key = jax.random.split(runner.rng, 3)
        params = runner.train_state.params
        hidden, pi, value = _apply_step(build.network, params, runner.hidden, runner.obs,
                                        runner.reset)
        action = pi.sample(seed=action_key)[0]
        log_prob = pi.log_prob(action[None])[0]
        obs, env_state, reward, terminated, truncated, info = jax.vmap(
            build.env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(step_key, num_envs), runner.env_state,
            to_env_action(action, build.low, build.high), env_params)
        done = jnp.logical_or(terminated, truncated)
        episode_return = runner.episode_return + reward
        episode_length = runner.episode_length + 1
        transition = Transition(
            runner.obs, runner.reset, action, log_prob, value,
            reward * config.reward_scale, terminated, truncated, None)
        episode = {
            "done": done,
            "terminated": terminated,
            "return": episode_return,
            "length": episode_length,
            "distance": info["distance_m"] if build.has_distance else jnp.zeros(num_envs),
        }
        runner = RunnerState(
            runner.train_state, env_state, obs, done, hidden,
            jnp.where(done, 0.0, episode_return), jnp.where(done, 0, episode_length), rng)
        return runner, (transition, episode, (info["final_observation"], hidden))

    runner, (trajectory, episodes, finals) = jax.lax.scan(
        rollout_step, runner, None, config.num_steps)
    trajectory = trajectory._replace(
        bootstrap_value=_bootstrap_values(build, runner.train_state.params, *finals))
    return runner, trajectory, episodes


def _bootstrap_values(build: Build, params: Any, final_obs: jax.Array, hidden: jax.Array
                      ) -> jax.Array:
    """V(final observation) of every rollout step in one batched call: ``final_obs [T, B,
    obs_dim]`` (gymnax's ``info["final_observation"]``, the observation after step t before
    any reset) seen with ``hidden [T, B, H]``, the policy state after step t's observation
    -> ``[T, B]``. The parameters do not change during a rollout, so this is what calling
    the critic at every step would give, with T times fewer (and larger) calls."""
    num_steps, num_envs = build.config.num_steps, build.config.num_envs
    flat = lambda x: x.reshape(1, num_steps * num_envs, *x.shape[2:])  # noqa: E731
    _, _, values = build.network.apply(params, flat(hidden)[0], flat(final_obs),
                                       jnp.zeros((1, num_steps * num_envs), bool))
    return values.reshape(num_steps, num_envs)


def _ppo_epochs(build: Build, train_state: TrainState, rng: jax.Array, data: tuple,
                rollout_hidden: jax.Array) -> tuple[TrainState, dict]:
    """``agent.update_epochs`` passes of clipped-PPO minibatch steps over ``data`` =
    (trajectory [T, B], advantages [T, B], targets [T, B]); recurrent policies take whole
    sequences from ``rollout_hidden`` [B, H]. ``-> (train_state, losses [epochs, minibatches])``."""
    config = build.config

    def minibatch_step(train_state: TrainState, minibatch):
        hidden, batch, advantage, target = minibatch
        (total, aux), grads = jax.value_and_grad(ppo_loss, has_aux=True)(
            train_state.params, build.network, hidden, batch, advantage, target, config)
        return train_state.apply_gradients(grads=grads), {"total_loss": total, **aux}

    def epoch_step(carry, _):
        train_state, rng = carry
        rng, permute_key = jax.random.split(rng)
        if config.recurrent:
            hidden, batches = sequence_minibatches(permute_key, data, rollout_hidden,
                                                   config.num_minibatches)
        else:
            hidden, batches = step_minibatches(permute_key, data, config.num_minibatches)
        train_state, losses = jax.lax.scan(minibatch_step, train_state, (hidden, *batches))
        return (train_state, rng), losses

    (train_state, _), losses = jax.lax.scan(
        epoch_step, (train_state, rng), None, config.update_epochs)
    return train_state, losses


def _update_metrics(build: Build, losses: dict, episodes: dict, update_index: jax.Array
                    ) -> dict[str, jax.Array]:
    """The update's mean losses and the episodes that ended in its rollout."""
    config, done = build.config, episodes["done"]
    metrics = {k: v.mean() for k, v in losses.items()}
    metrics.update({
        "timesteps": (update_index + 1) * config.num_steps * config.num_envs,
        "episodes": done.sum(),
        "mean_return": masked_mean(episodes["return"], done),
        "mean_length": masked_mean(episodes["length"].astype(jnp.float32), done),
        "success_rate": masked_mean(episodes["terminated"].astype(jnp.float32), done),
        "final_distance_m": (masked_mean(episodes["distance"], done)
                             if build.has_distance else jnp.nan),
    })
    return metrics
