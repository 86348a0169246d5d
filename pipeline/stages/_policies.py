"""Train policies in an environment and write them into an artifact: what ``train_ppo`` and
``adapt`` (its policy fine-tune) share.

``train_into`` trains ``agent.num_seeds`` seeds with ``agent.trainer``
(``pipeline.rl.ppo.train_seeds``), optionally warm started from ``agent.init_policy``, and
writes ``metrics.parquet`` (per seed and update), ``evaluation.parquet`` (per seed and held-out
evaluation), ``episodes.parquet`` (the last evaluation's episodes) and ``policy.msgpack`` (the
seeds' parameters stacked, with what ``evaluate`` and ``control`` need to rebuild the network
and its environment).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

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
    metrics = metrics_table({k: np.asarray(v) for k, v in output.metrics.items()},
                            int(train_params.max_steps_in_episode), agent.num_steps)
    summary, episodes = evaluation_tables(
        {k: np.asarray(v) for k, v in output.evaluation.items()})
    write_results(metrics, writer.file("metrics.parquet"), config, stage)
    write_results(summary, writer.file("evaluation.parquet"), config, stage)
    write_results(episodes, writer.file("episodes.parquet"), config, stage)
    save_policy(writer.file("policy.msgpack"), output.params, {
        **policy_meta, "env_name": env.name, "obs_dim": obs_dim, "action_dim": action_dim,
        "action_low": low.tolist(), "action_high": high.tolist(),
        "num_seeds": agent.num_seeds})
    timesteps = len(timings["chunk_seconds"]) * agent.updates_per_eval * agent.steps_per_update
    return Trained(metrics, summary, episodes, timings, timesteps)
