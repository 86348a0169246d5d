"""Stage ``train_ppo``: policies in the learned environment, many seeds at once: PPO, or
analytic policy gradients through the model (``agent.trainer=apg``, ``agent=apg``).

``env.name`` picks the environment (``pipeline.rl.envs.factory``):

- ``learned`` (default): the fitted recurrent model of the fit_model artifact of this config; goals
  (``goal_mode=data``) are the model's open-loop predictions along the training runs' commands
  (``env.goal_source=predicted``, reachable in the model's world) or their measured positions
  (``measured``); evaluation goals come from the held-out runs (the split recorded by fit_model);
  the rest pose is the mean measured first pose of the runs.
- ``sim``: the simulated arm itself (no model needed; the upper bound for the learned env).
- ``gymnax``: a standard gymnax environment (``env.gymnax_name``) to check the PPO.

Robustness (``env.ensemble_seeds``, ``env.models``, ``env.randomization``): training episodes run
in one of several fitted models (this config's and those of further model seeds, produced
upstream, or other fit_model artifacts) and/or with the plant randomized per episode; the
evaluations during training stay in this config's own model, nominal.

``agent.num_seeds`` seeds train in one jitted, vmapped program (``pipeline.rl.ppo.train_seeds``,
which runs ``agent.trainer``'s); with ``agent.stop_at`` training ends at the first evaluation chunk
that reaches it, and the summary records where (``stopped_at``).

Artifact: ``metrics.parquet`` (per seed and update: timesteps, mean episodic return, final
distance, success rate, losses), ``evaluation.parquet`` (per seed and evaluation on held-out
goals), ``episodes.parquet`` (the last evaluation's episodes), ``policy.msgpack`` (the policies of
all seeds, stacked; ``pipeline.rl.ppo.load_policy``) and ``figures/returns.png`` (mean ± std over
seeds).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.infra.artifacts import Artifact, ArtifactStore, produce
from pipeline.infra.tracking import tracking
from pipeline.rl.results import plot_returns
from pipeline.schemas import AgentConfig, EnvName
from pipeline.stages._environment import config_environment
from pipeline.stages._policies import train_into

log = logging.getLogger(__name__)
STAGE = "train_ppo"


def train_ppo(cfg: Any) -> Artifact:
    """Train ``agent.num_seeds`` policies with ``agent.trainer`` in this config's environment
    (see module doc)."""
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.train_ppo_spec(cfg)
    agent = AgentConfig.from_any(cfg.agent)
    model = aligned = None
    members = []
    if EnvName(cfg.env.name) is EnvName.learned:
        model = store.require("fit_model", inputs["fit_model"])
        aligned = store.require("align", keys.key("align", cfg))
        members = [store.resolve("fit_model", entry)
                   for entry in keys.ensemble_entries(cfg).values()]

    def build(writer):
        env, train_params, eval_params = config_environment(cfg, model, aligned, members)
        config = {"env": spec["env"], "agent": spec["agent"], "seed": spec["seed"],
                  "init_policy_sha256": spec.get("init_policy_sha256")}
        trained = train_into(
            writer, STAGE, agent, env, train_params, eval_params, seed=int(cfg.seed),
            config=config, desc=f"{STAGE} {agent.name} on {env.name}",
            warm_start=bool(agent.init_policy),
            policy_meta={"agent": spec["agent"], "env": spec["env"],
                         "init_policy_sha256": spec.get("init_policy_sha256")})
        metrics, summary, episodes = trained.metrics, trained.summary, trained.episodes
        timings, timesteps = trained.timings, trained.timesteps_per_seed
        steps = agent.num_seeds * timesteps
        plot_returns(writer.file("figures/returns.png"), metrics, summary,
                     f"{agent.name} on {env.name}")
        with tracking(OmegaConf.to_object(cfg.logger), Path(cfg.paths.output_dir), STAGE,
                      OmegaConf.to_container(cfg, resolve=True)) as tracker:
            per_update = (metrics.drop(columns=["seed", "phase"], errors="ignore")
                          .groupby("update").mean())
            tracker.log_table(per_update.reset_index().rename(columns={"update": "step"}))

        final = episodes["final_distance_m"].to_numpy()
        per_seed = episodes.groupby("seed")["final_distance_m"].median()
        writer.summary = {
            "env": env.name, "agent": agent.name, "num_seeds": agent.num_seeds,
            "trainer": str(agent.trainer),
            "timesteps_per_seed": timesteps,
            # where agent.stop_at was reached: evaluation, timesteps per seed, seconds of
            # training after compilation, its figures (None: not reached, or not asked for)
            "stopped_at": timings["stopped_at"],
            "compile_seconds": round(timings["compile_s"], 1),
            "train_seconds": round(timings["run_s"], 1),
            "devices": timings["devices"],
            "env_steps_per_second": round(steps / timings["run_s"], 1),
            "final_eval_mean_return": float(summary.groupby("seed")["mean_return"].last().mean()),
            "final_eval_success_rate": (float(episodes["success"].mean())
                                        if np.isfinite(final).any() else None),
            "final_eval_median_distance_mm": (float(np.nanmedian(final) * 1000)
                                              if np.isfinite(final).any() else None),
            "final_eval_median_distance_mm_per_seed": [
                None if not np.isfinite(v) else round(float(v) * 1000, 3) for v in per_seed],
        }
        log.info("train_ppo: %s", json.dumps(writer.summary))

    return produce(store, STAGE, spec, inputs, build, force=cfg.force)

