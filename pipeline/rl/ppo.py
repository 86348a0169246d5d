"""PPO in the PureJaxRL style: the whole training run is one pure, jittable function.

``make_train(agent, env, env_params)`` returns ``train(rng) -> TrainOutput``; jit it once and
``vmap`` it over seeds. ``train_seeds`` runs the same training as its two parts
(:func:`make_train_program`: ``init`` and one evaluation chunk, each vmapped over seeds and
compiled once) with the loop over chunks on the host, where the progress bar advances: no host
callback inside a compiled program, so JAX's persistent cache keeps both. Inside, ``lax.scan``
runs

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

import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training.train_state import TrainState

from pipeline.infra.devices import batch_split
from pipeline.rl.evaluation import evaluate_policy
from pipeline.rl.losses import compute_gae, ppo_loss
from pipeline.rl.minibatches import sequence_minibatches, step_minibatches
from pipeline.rl.networks import initial_hidden, make_network
from pipeline.rl.policy_io import NETWORK_FIELDS
from pipeline.rl.spaces import action_bounds, to_env_action
from pipeline.schemas import AgentConfig, Trainer


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


class RunnerState(NamedTuple):
    train_state: TrainState
    env_state: Any  # [B] environment states
    obs: jax.Array  # [B, obs_dim] the next observation
    reset: jax.Array  # [B] bool: obs starts an episode
    hidden: jax.Array  # [B, H] policy hidden state before obs
    episode_return: jax.Array  # [B] unscaled return of the running episodes
    episode_length: jax.Array  # [B] int32
    rng: jax.Array


class TrainOutput(NamedTuple):
    """``params``: final network variables. ``metrics``: [num_updates] arrays per name.
    ``evaluation``: per evaluation, [num_evals] summaries and [num_evals, eval_envs] episodes."""

    params: Any
    metrics: dict[str, jax.Array]
    evaluation: dict[str, jax.Array]


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def _masked_mean(values: jax.Array, mask: jax.Array) -> jax.Array:
    """Mean of ``values`` where ``mask``; NaN where nothing is selected."""
    count = mask.sum()
    return jnp.where(count > 0, jnp.where(mask, values, 0.0).sum() / jnp.maximum(count, 1),
                     jnp.nan)


# ---------------------------------------------------------------------------------------------
# training
# ---------------------------------------------------------------------------------------------
class TrainProgram(NamedTuple):
    """A training run in its two pure parts, for a host loop between evaluation chunks
    (progress, early inspection) without host callbacks in the compiled programs, which JAX's
    persistent cache cannot keep:

    - ``init(rng, env_params, init_params=None) -> RunnerState``
    - ``chunk(runner, chunk_index, env_params, eval_env_params) -> (runner, (metrics,
      evaluation))``: ``agent.updates_per_eval`` updates, then one deterministic evaluation;
      ``metrics`` are [updates_per_eval] arrays, ``evaluation`` one summary.

    ``init`` then ``chunk`` for indices ``0 .. num_chunks - 1`` is exactly ``train``."""

    init: Callable[..., RunnerState]
    chunk: Callable[..., tuple[RunnerState, tuple[dict, dict]]]
    num_chunks: int


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


class _Build(NamedTuple):
    """What every part of a training run is built from (fixed when the program is built; the
    environment parameters, which may be large, stay arguments of the parts)."""

    config: AgentConfig
    env: Any
    network: Any
    low: Any  # action bounds of the training env
    high: Any
    obs_shape: tuple[int, ...]
    has_distance: bool


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
    build = _Build(config, env, make_network(config, int(np.prod(low.shape))), low, high,
                   tuple(env.observation_space(env_params).shape), _has_distance(env, env_params))

    def init(rng: jax.Array, env_params=env_params, init_params=None) -> RunnerState:
        return _init(build, rng, env_params, init_params)

    def chunk(runner: RunnerState, chunk_index, env_params=env_params,
              eval_env_params=eval_env_params):
        return _chunk(build, runner, chunk_index, env_params, eval_env_params, eval_steps,
                      eval_bounds)

    return TrainProgram(init, chunk, config.num_evals)


def _init(build: _Build, rng: jax.Array, env_params: Any, init_params: Any) -> RunnerState:
    """The network (random, or ``init_params``: a warm start), its optimizer, and
    ``agent.num_envs`` environments reset."""
    config, network, num_envs = build.config, build.network, build.config.num_envs
    init_key, reset_key, runner_key = jax.random.split(rng, 3)
    hidden0 = initial_hidden(network, num_envs)
    variables = network.init(init_key, hidden0, jnp.zeros((1, num_envs, *build.obs_shape)),
                             jnp.zeros((1, num_envs), bool))
    if init_params is not None:  # warm start (e.g. a policy trained on another model)
        check_same_variables(variables, init_params, "init_params")
        variables = jax.tree.map(jnp.asarray, init_params)
    tx = optax.chain(optax.clip_by_global_norm(config.max_grad_norm),
                     optax.adam(learning_rate=_learning_rate(config), eps=1e-5))
    train_state = TrainState.create(apply_fn=network.apply, params=variables, tx=tx)
    obs, env_state = jax.vmap(build.env.reset, in_axes=(0, None))(
        jax.random.split(reset_key, num_envs), env_params)
    return RunnerState(train_state, env_state, obs, jnp.ones(num_envs, bool), hidden0,
                       jnp.zeros(num_envs), jnp.zeros(num_envs, jnp.int32), runner_key)


def _learning_rate(config: AgentConfig) -> Any:
    """``agent.lr``, annealed linearly to zero over the updates where ``agent.anneal_lr``."""
    if not config.anneal_lr:
        return config.lr

    def learning_rate(count):
        fraction = 1.0 - (count // (config.num_minibatches * config.update_epochs)
                          ) / config.num_updates
        return config.lr * fraction

    return learning_rate


def _chunk(build: _Build, runner: RunnerState, chunk_index: jax.Array, env_params: Any,
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


def _update_step(build: _Build, runner: RunnerState, update_index: jax.Array, env_params: Any):
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


def _rollout(build: _Build, runner: RunnerState, env_params: Any):
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


def _bootstrap_values(build: _Build, params: Any, final_obs: jax.Array, hidden: jax.Array
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


def _ppo_epochs(build: _Build, train_state: TrainState, rng: jax.Array, data: tuple,
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


def _update_metrics(build: _Build, losses: dict, episodes: dict, update_index: jax.Array
                    ) -> dict[str, jax.Array]:
    """The update's mean losses and the episodes that ended in its rollout."""
    config, done = build.config, episodes["done"]
    metrics = {k: v.mean() for k, v in losses.items()}
    metrics.update({
        "timesteps": (update_index + 1) * config.num_steps * config.num_envs,
        "episodes": done.sum(),
        "mean_return": _masked_mean(episodes["return"], done),
        "mean_length": _masked_mean(episodes["length"].astype(jnp.float32), done),
        "success_rate": _masked_mean(episodes["terminated"].astype(jnp.float32), done),
        "final_distance_m": (_masked_mean(episodes["distance"], done)
                             if build.has_distance else jnp.nan),
    })
    return metrics


def check_same_variables(expected: Any, given: Any, what: str) -> None:
    """Raise a ValueError naming ``what`` unless ``given`` has ``expected``'s tree and shapes."""
    expected_leaves = jax.tree_util.tree_leaves_with_path(expected)
    given_leaves = jax.tree_util.tree_leaves_with_path(given)
    expected_shapes = {jax.tree_util.keystr(k): tuple(np.shape(v)) for k, v in expected_leaves}
    given_shapes = {jax.tree_util.keystr(k): tuple(np.shape(v)) for k, v in given_leaves}
    if expected_shapes != given_shapes:
        missing = sorted(set(expected_shapes) - set(given_shapes))
        extra = sorted(set(given_shapes) - set(expected_shapes))
        wrong = sorted(f"{k}: {given_shapes[k]}, expected {v}" for k, v in expected_shapes.items()
                       if k in given_shapes and given_shapes[k] != v)
        raise ValueError(f"{what} do not fit the agent's network (the same agent "
                         f"{', '.join(NETWORK_FIELDS)} and environment spaces needed): missing "
                         f"{missing[:4]}, unexpected {extra[:4]}, wrong shapes {wrong[:4]}")


def _has_distance(env: Any, env_params: Any) -> bool:
    """Whether the environment reports ``info["distance_m"]`` (abstract evaluation only)."""

    def probe(key):
        _, state = env.reset(key, env_params)
        low, high = action_bounds(env, env_params)
        return env.step(key, state, jnp.asarray((low + high) / 2), env_params)[-1]

    info = jax.eval_shape(probe, jax.random.PRNGKey(0))
    return "distance_m" in info


def seed_keys(seed: int, num_seeds: int, stream: int = 0) -> jax.Array:
    """``[num_seeds]`` keys: ``fold_in(PRNGKey(seed), i)`` for seed index i; a later phase of
    the same run (``stream`` > 0) folds ``stream`` into ``PRNGKey(seed)`` first, so that it draws
    anew."""
    base = jax.random.PRNGKey(int(seed))
    if stream:
        base = jax.random.fold_in(base, int(stream))
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(num_seeds))


def program_builder(config: AgentConfig) -> Callable[..., TrainProgram]:
    """The ``make_train_program`` of ``agent.trainer``: PPO's (this module) or APG's
    (:mod:`pipeline.rl.apg`, which builds on this module and is imported where chosen)."""
    if Trainer(config.trainer) is Trainer.apg:
        from pipeline.rl.apg import make_train_program as make_apg_program

        return make_apg_program
    return make_train_program


def held_out_figures(evaluation: dict[str, Any]) -> tuple[float, float]:
    """One evaluation during training, all seeds' episodes pooled: ``(median final distance
    [mm], share of episodes that succeeded)``; ``evaluation`` holds ``[num_seeds, E]``
    ``episode_final_distance_m`` and ``episode_success`` (NaN, NaN where there are none)."""
    distances = np.asarray(evaluation["episode_final_distance_m"], np.float64).reshape(-1)
    success = np.asarray(evaluation["episode_success"], np.float64).reshape(-1)
    if not np.isfinite(distances).any():
        return float("nan"), float("nan")
    return float(np.nanmedian(distances) * 1000.0), float(success.mean())


def _run_chunks(config: AgentConfig, chunk: Callable, runner: Any, num_chunks: int, show: bool,
                desc: str) -> tuple[Any, list, dict[str, Any]]:
    """The host loop over the evaluation chunks (``chunk(runner, index) -> (runner, (metrics,
    evaluation))``, compiled once): the progress bar after each, and ``agent.stop_at``: the loop
    ends after the chunk whose evaluation completes ``stop_at.consecutive`` good ones in a row
    (the same compiled program per chunk, nothing computed past the stop). Returns the runner,
    the chunks' host results and ``{"chunk_seconds": seconds from the loop's start to the end
    of each chunk run, "stopped_at": None or {"evaluation", "timesteps_per_seed", "seconds",
    "median_distance_mm", "success_rate"}}``."""
    from tqdm.auto import tqdm

    stop, streak, stopped = config.stop_at, 0, None
    chunks, seconds = [], []
    started = time.perf_counter()
    with tqdm(total=config.num_updates, desc=desc, unit="update", disable=not show) as bar:
        for index in range(num_chunks):
            runner, outputs = chunk(runner, index)
            chunks.append(jax.device_get(outputs))
            seconds.append(time.perf_counter() - started)
            returns = np.asarray(chunks[-1][0]["mean_return"], np.float64)
            if np.isfinite(returns).any():
                bar.set_postfix(train_return=f"{np.nanmean(returns):.3g}", refresh=False)
            bar.update(config.updates_per_eval)
            if not stop.active:
                continue
            median_mm, success = held_out_figures(chunks[-1][1])
            streak = streak + 1 if stop.reached(median_mm, success) else 0
            if streak >= stop.consecutive:
                stopped = {"evaluation": index,
                           "timesteps_per_seed": (index + 1) * config.updates_per_eval
                           * config.steps_per_update,
                           "seconds": round(seconds[-1], 2),
                           "median_distance_mm": round(median_mm, 4),
                           "success_rate": round(success, 4)}
                break
    return runner, chunks, {"chunk_seconds": seconds, "stopped_at": stopped}


def train_seeds(agent: Any, env: Any, env_params: Any, eval_env_params: Any = None,
                seed: int = 0, progress: bool | None = None, desc: str = "ppo",
                timings: dict[str, Any] | None = None, init_params: Any = None,
                stream: int = 0) -> TrainOutput:
    """Train ``agent.num_seeds`` seeds at once (vmap over seeds); arrays come back with a leading
    [num_seeds] axis. ``timings`` (if given) receives ``compile_s``, ``run_s`` and
    ``devices`` (how many devices the seeds were split over).
    ``init_params`` (optional): starting network variables, stacked over seeds
    (``[num_seeds, ...]`` leaves, as :func:`load_policy` returns them). ``stream``: a later
    phase of the run draws its own keys (:func:`seed_keys`).

    Two compiled programs, the same for every run of this configuration and so kept by the
    persistent compilation cache: ``init``, and one evaluation chunk, called ``agent.num_evals``
    times from here with the chunk index as an argument; the progress bar advances after each.
    Where there are several local devices (the CPU's cores, :mod:`pipeline.infra.devices`), the
    seeds are split over as many as divide ``num_seeds``, each part run in parallel.
    With ``agent.stop_at`` set, training ends after the evaluation chunk that reaches it
    (:func:`_run_chunks`): the arrays then hold the chunks run, and ``timings`` also receives
    ``stopped_at`` (where, when and with which figures; None if never reached) and
    ``chunk_seconds`` (the wall time after compilation at the end of each chunk).
    The result is :func:`make_train`'s for the chunks run."""
    config = AgentConfig.from_any(agent)
    show = config.progress if progress is None else progress
    eval_env_params = env_params if eval_env_params is None else eval_env_params
    program = program_builder(config)(config, env, env_params, eval_env_params)
    keys = seed_keys(seed, config.num_seeds, stream)
    if init_params is not None:
        sizes = {int(np.shape(x)[0]) if np.ndim(x) else 0 for x in jax.tree.leaves(init_params)}
        if sizes != {config.num_seeds}:
            raise ValueError(f"init_params must be stacked over agent.num_seeds="
                             f"{config.num_seeds} seeds; leading sizes {sorted(sizes)}")
    # the seeds split over the devices (the CPU's cores: pipeline.infra.devices), each part in
    # parallel; every seed computes what it computes in one batch, to float rounding
    split = batch_split(config.num_seeds)
    by_seed = {}
    if split is not None:
        keys, init_params = split.put(keys), split.put(init_params)
        env_params, eval_env_params = split.put((env_params, eval_env_params), axis=None)
        by_seed = {"out_shardings": split.sharding()}
    started = time.perf_counter()
    init = jax.jit(jax.vmap(program.init, in_axes=(0, None, 0)), **by_seed).lower(
        keys, env_params, init_params).compile()
    runner = init(keys, env_params, init_params)
    chunk = jax.jit(jax.vmap(program.chunk, in_axes=(0, None, None, None)), donate_argnums=0,
                    **by_seed).lower(runner, jnp.int32(0), env_params, eval_env_params).compile()
    compiled_at = time.perf_counter()
    runner, chunks, progress_record = _run_chunks(
        config, lambda runner, index: chunk(runner, jnp.int32(index), env_params,
                                            eval_env_params),
        runner, program.num_chunks, show, desc)
    params = jax.block_until_ready(runner.train_state.params)
    if timings is not None:
        timings.update(compile_s=compiled_at - started, run_s=time.perf_counter() - compiled_at,
                       devices=1 if split is None else int(split.mesh.size), **progress_record)
    metrics = jax.tree.map(lambda *xs: np.concatenate(xs, axis=1), *[m for m, _ in chunks])
    evaluation = jax.tree.map(lambda *xs: np.stack(xs, axis=1), *[e for _, e in chunks])
    return TrainOutput(params, metrics, evaluation)
