"""What the trainers share: the running state, a training run's two parts, and the host loop
that runs the part of ``agent.trainer`` for every seed.

A trainer (:mod:`pipeline.rl.ppo`, :mod:`pipeline.rl.apg`) builds a :class:`TrainProgram` from a
:class:`Build` (the agent config, the environment, the network, the action bounds): ``init``
(:func:`init_runner`: the network, its optimizer, ``agent.num_envs`` environments reset) and one
evaluation chunk (``agent.updates_per_eval`` updates, then a deterministic evaluation).
:func:`train_seeds` runs the program of ``agent.trainer`` (:func:`program_builder`) for
``agent.num_seeds`` seeds: ``init`` and the chunk each vmapped over seeds and compiled once, the
loop over chunks on the host, where the progress bar advances and ``agent.stop_at`` may end it.

The trainers import this module and never each other; :func:`program_builder` imports the chosen
one where it is chosen.
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
from pipeline.rl.networks import initial_hidden
from pipeline.rl.policy_io import NETWORK_FIELDS
from pipeline.rl.spaces import action_bounds
from pipeline.schemas import AgentConfig, Trainer


# ---------------------------------------------------------------------------------------------
# data carried through the scans
# ---------------------------------------------------------------------------------------------
class RunnerState(NamedTuple):
    """What a trainer carries from one update to the next (``[B]``: the agent.num_envs running
    environments)."""

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


class Build(NamedTuple):
    """What every part of a training run is built from (fixed when the program is built; the
    environment parameters, which may be large, stay arguments of the parts)."""

    config: AgentConfig
    env: Any
    network: Any
    low: Any  # action bounds of the training env
    high: Any
    obs_shape: tuple[int, ...]
    has_distance: bool


# ---------------------------------------------------------------------------------------------
# what every trainer's program is built from
# ---------------------------------------------------------------------------------------------
def masked_mean(values: jax.Array, mask: jax.Array) -> jax.Array:
    """Mean of ``values`` where ``mask``; NaN where nothing is selected."""
    count = mask.sum()
    return jnp.where(count > 0, jnp.where(mask, values, 0.0).sum() / jnp.maximum(count, 1),
                     jnp.nan)


def has_distance(env: Any, env_params: Any) -> bool:
    """Whether the environment reports ``info["distance_m"]`` (abstract evaluation only)."""

    def probe(key):
        _, state = env.reset(key, env_params)
        low, high = action_bounds(env, env_params)
        return env.step(key, state, jnp.asarray((low + high) / 2), env_params)[-1]

    info = jax.eval_shape(probe, jax.random.PRNGKey(0))
    return "distance_m" in info


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


def init_runner(build: Build, rng: jax.Array, env_params: Any, init_params: Any) -> RunnerState:
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


# ---------------------------------------------------------------------------------------------
# the host loop: every seed, one trainer
# ---------------------------------------------------------------------------------------------
def seed_keys(seed: int, num_seeds: int, stream: int = 0) -> jax.Array:
    """``[num_seeds]`` keys: ``fold_in(PRNGKey(seed), i)`` for seed index i; a later phase of
    the same run (``stream`` > 0) folds ``stream`` into ``PRNGKey(seed)`` first, so that it draws
    anew."""
    base = jax.random.PRNGKey(int(seed))
    if stream:
        base = jax.random.fold_in(base, int(stream))
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(num_seeds))


def program_builder(config: AgentConfig) -> Callable[..., TrainProgram]:
    """The ``make_train_program`` of ``agent.trainer``: PPO's (:mod:`pipeline.rl.ppo`) or APG's
    (:mod:`pipeline.rl.apg`); both build on this module, so the chosen one is imported here,
    where it is chosen."""
    if Trainer(config.trainer) is Trainer.apg:
        from pipeline.rl.apg import make_train_program as make_apg_program

        return make_apg_program
    from pipeline.rl.ppo import make_train_program as make_ppo_program

    return make_ppo_program


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
    (``[num_seeds, ...]`` leaves, as :func:`~pipeline.rl.policy_io.load_policy` returns them).
    ``stream``: a later phase of the run draws its own keys (:func:`seed_keys`).

    Two compiled programs, the same for every run of this configuration and so kept by the
    persistent compilation cache: ``init``, and one evaluation chunk, called ``agent.num_evals``
    times from here with the chunk index as an argument; the progress bar advances after each.
    Where there are several local devices (the CPU's cores, :mod:`pipeline.infra.devices`), the
    seeds are split over as many as divide ``num_seeds``, each part run in parallel.
    With ``agent.stop_at`` set, training ends after the evaluation chunk that reaches it
    (:func:`_run_chunks`): the arrays then hold the chunks run, and ``timings`` also receives
    ``stopped_at`` (where, when and with which figures; None if never reached) and
    ``chunk_seconds`` (the wall time after compilation at the end of each chunk).
    The result is :func:`pipeline.rl.ppo.make_train`'s (PPO) for the chunks run."""
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
