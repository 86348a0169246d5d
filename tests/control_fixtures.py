"""Policy artifacts for the control tests, without training: a train_ppo artifact on ``env=sim``
(no upstream artifacts) holding freshly initialized networks, under the key the config gives."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from pipeline import chain, keys
from pipeline.infra.artifacts import ArtifactStore
from pipeline.rl.networks import initial_hidden, make_network
from pipeline.rl.policy_io import save_policy
from pipeline.schemas import AgentConfig
from pipeline.stages._environment import config_environment

# a small simulated-arm environment and network: seconds to build
SMALL = ["env=sim", "env.num_goals=64", "env.reset_bank_size=2", "env.include_error=true",
         "agent.hidden=8", "agent.num_layers=1", "agent.rnn_hidden=8", "agent.num_seeds=2",
         "control.flush_every_s=0.2"]


def write_policy(cfg, medians_mm=(3.0, 2.0), scale: float = 1.0):
    """A train_ppo artifact for ``cfg`` (its control.policy as the agent): random networks of
    ``agent.num_seeds`` seeds (parameters times ``scale``: NaN makes a broken policy) and an
    evaluation.parquet whose last held-out medians are ``medians_mm``."""
    variant = chain.control_policy_config(cfg)
    spec, inputs = keys.train_ppo_spec(variant)
    store = ArtifactStore(cfg.paths.artifact_dir)
    env, train_params, _ = config_environment(variant)
    agent = AgentConfig.from_any(variant.agent)
    network = make_network(agent, 3)
    obs_dim = int(env.obs_dim)

    def init(key):
        return network.init(key, initial_hidden(network, 1), jnp.zeros((1, 1, obs_dim)),
                            jnp.zeros((1, 1), bool))

    params = jax.vmap(init)(jax.random.split(jax.random.key(0), agent.num_seeds))
    params = jax.tree.map(lambda x: x * scale, params)
    with store.writing("train_ppo", keys.artifact_key(spec, inputs), spec, inputs) as writer:
        save_policy(writer.file("policy.msgpack"), params, {
            "agent": spec["agent"], "env": spec["env"], "env_name": env.name, "obs_dim": obs_dim,
            "action_dim": 3, "num_seeds": agent.num_seeds})
        evaluation = pd.DataFrame({
            "seed": np.repeat(np.arange(agent.num_seeds), 2), "evaluation": [0, 1] * agent.num_seeds,
            "median_final_distance_m": np.repeat(np.asarray(medians_mm) / 1e3, 2)})
        evaluation.loc[evaluation["evaluation"] == 0, "median_final_distance_m"] = 0.05
        evaluation.to_parquet(writer.file("evaluation.parquet"))
    return store.require("train_ppo", keys.artifact_key(spec, inputs)), train_params


def goals_mm(train_params, count: int = 3) -> list[list[float]]:
    """``count`` training goals (inside the workspace) in mm."""
    goals = np.asarray(train_params.goal_set, np.float64)[:count] * 1e3
    return np.round(goals, 2).tolist()
