"""Train policies in an environment and write them into an artifact: what ``train_ppo`` and
``adapt`` (its policy fine-tune) share.

``train_into`` trains ``agent.num_seeds`` seeds with ``agent.trainer``
(``pipeline.rl.ppo.train_seeds``), optionally warm started from ``agent.init_policy`` and
followed by ``agent.hold_tune``'s phase (:func:`hold_tune`), and writes ``metrics.parquet``
(per seed and update), ``evaluation.parquet`` (per seed and held-out evaluation),
``episodes.parquet`` (the last evaluation's episodes) and ``policy.msgpack`` (the seeds'
parameters stacked, with what ``evaluate`` and ``control`` need to rebuild the network and its
environment). With the hold tune the first two tables have a column ``phase`` (``train``,
``hold_tune``) and the episodes are the tuned policies'.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp
import numpy as np
import pandas as pd

from pipeline.infra.artifacts import ArtifactWriter
from pipeline.rl.policy_io import save_policy, warm_start_params
from pipeline.rl.ppo import action_bounds, train_seeds
from pipeline.rl.results import evaluation_tables, metrics_table, write_results
from pipeline.schemas import AgentConfig


@dataclass(frozen=True)
class Trained:
    """What :func:`train_into` wrote, as tables, and how long it took (``timings``: compile_s,
    run_s, devices, chunk_seconds, stopped_at of ``train_seeds``)."""

    metrics: pd.DataFrame
    summary: pd.DataFrame  # the held-out evaluations
    episodes: pd.DataFrame  # the last evaluation's episodes
    timings: dict[str, Any]
    timesteps_per_seed: int  # the chunks run (fewer than agent.num_evals where stop_at stopped)


def train_into(writer: ArtifactWriter, stage: str, agent: AgentConfig, env: Any,
               train_params: Any, eval_params: Any, *, seed: int, config: dict[str, Any],
               policy_meta: dict[str, Any], desc: str, warm_start: bool) -> Trained:
    """Train and write (module doc). ``config``: the producing config in each table's metadata;
    ``policy_meta``: what ``policy.msgpack`` records besides the network's sizes and bounds
    (``agent``, ``env``, ...); ``warm_start``: start from ``agent.init_policy``."""
    low, high = action_bounds(env, train_params)
    obs_dim = int(np.prod(env.observation_space(train_params).shape))
    action_dim = int(np.prod(low.shape))
    init_params = warm_start_params(agent, obs_dim, action_dim) if warm_start else None
    timings: dict[str, Any] = {}
    output = train_seeds(agent, env, train_params, eval_params, seed=seed, desc=desc,
                         timings=timings, init_params=init_params)
    trained = _tables(agent, train_params, output, timings)
    if agent.hold_tune_timesteps:
        output, trained = hold_tune(agent, env, train_params, eval_params, output.params,
                                    trained, seed=seed, desc=desc)
    write_results(trained.metrics, writer.file("metrics.parquet"), config, stage)
    write_results(trained.summary, writer.file("evaluation.parquet"), config, stage)
    write_results(trained.episodes, writer.file("episodes.parquet"), config, stage)
    save_policy(writer.file("policy.msgpack"), output.params, {
        **policy_meta, "env_name": env.name, "obs_dim": obs_dim, "action_dim": action_dim,
        "action_low": low.tolist(), "action_high": high.tolist(),
        "num_seeds": agent.num_seeds})
    return trained


def _tables(agent: AgentConfig, train_params: Any, output: Any, timings: dict[str, Any]
            ) -> Trained:
    """The tables of one ``train_seeds`` run of ``agent`` in ``train_params`` (its ``output``
    and ``timings``), and the timesteps per seed of the chunks it ran."""
    metrics = metrics_table({k: np.asarray(v) for k, v in output.metrics.items()},
                            int(train_params.max_steps_in_episode), agent.num_steps)
    summary, episodes = evaluation_tables(
        {k: np.asarray(v) for k, v in output.evaluation.items()})
    timesteps = len(timings["chunk_seconds"]) * agent.updates_per_eval * agent.steps_per_update
    return Trained(metrics, summary, episodes, timings, timesteps)


def hold_tune(agent: AgentConfig, env: Any, train_params: Any, eval_params: Any,
              params: Any, trained: Trained, *, seed: int, desc: str) -> tuple[Any, Trained]:
    """``agent.hold_tune``'s phase (:class:`~pipeline.schemas.HoldTune`): the policies
    ``params`` (stacked over seeds) fine-tuned by analytic policy gradients
    (:meth:`AgentConfig.hold_tuning`) in ``train_params`` with episodes that never end at the
    goal (``hold_periods`` = the training horizon), keys of their own (stream 1). Returns
    ``train_seeds``' output and ``trained`` (the trainer's) followed by the phase: rows marked
    ``phase`` ``train`` and ``hold_tune``, whose timesteps, updates and evaluations count on
    from the trainer's; the episodes the tuned policies'; times and timesteps summed."""
    tuning = agent.hold_tuning()
    holding = train_params.replace(hold_periods=jnp.asarray(
        int(train_params.max_steps_in_episode), jnp.int32))
    timings: dict[str, Any] = {}
    output = train_seeds(tuning, env, holding, eval_params, seed=seed, desc=f"{desc}, hold tune",
                         timings=timings, init_params=params, stream=1)
    tuned = _tables(tuning, holding, output, timings)
    metrics = tuned.metrics.assign(
        phase="hold_tune", timesteps=tuned.metrics["timesteps"] + trained.timesteps_per_seed,
        update=tuned.metrics["update"] + trained.metrics["update"].nunique())
    summary = tuned.summary.assign(
        phase="hold_tune", timesteps=tuned.summary["timesteps"] + trained.timesteps_per_seed,
        evaluation=tuned.summary["evaluation"] + trained.summary["evaluation"].nunique())
    both = {**trained.timings,
            **{name: trained.timings[name] + timings[name] for name in ("compile_s", "run_s")}}
    return output, Trained(
        pd.concat([trained.metrics.assign(phase="train"), metrics], ignore_index=True),
        pd.concat([trained.summary.assign(phase="train"), summary], ignore_index=True),
        tuned.episodes, both, trained.timesteps_per_seed + tuned.timesteps_per_seed)
