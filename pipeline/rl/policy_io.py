"""Trained policies: acting deterministically, and the checkpoint file (``policy.msgpack``).

A checkpoint holds the network variables (any pytree, e.g. stacked over seeds) and a JSON ``meta``
(the agent config, observation and action sizes, ...), so that the network can be rebuilt.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from flax import serialization

from pipeline.infra.parquet import atomic_write
from pipeline.rl.networks import make_network
from pipeline.schemas import AgentConfig


# ---------------------------------------------------------------------------------------------
def deterministic_action(network, params, hidden, obs, reset):
    """Mean action (``[-1, 1]`` units, clipped) for a batch: returns (hidden, action [B, A])."""
    hidden, pi, _ = network.apply(params, hidden, obs[None], reset[None])
    return hidden, jnp.clip(pi.mode()[0], -1.0, 1.0)


def save_policy(path: str | Path, params: Any, meta: Mapping[str, Any]) -> Path:
    """Write network variables (any pytree, e.g. stacked over seeds) and ``meta`` (JSON-able:
    the agent config, observation and action sizes...) to one msgpack file, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = serialization.msgpack_serialize({
        "meta": json.dumps(dict(meta), default=str),
        "params": serialization.to_state_dict(jax.device_get(params)),
    })
    with atomic_write(path) as tmp:
        tmp.write_bytes(payload)
    return path


def load_policy(path: str | Path, seed_index: int | None = None) -> tuple[Any, Any, dict]:
    """Read :func:`save_policy`'s file: ``(network, params, meta)``.

    With ``seed_index`` the parameters of that seed are taken from a stack over seeds.
    """
    state = serialization.msgpack_restore(Path(path).read_bytes())
    meta = json.loads(state["meta"])
    params = jax.tree.map(jnp.asarray, state["params"])
    if seed_index is not None:
        params = jax.tree.map(lambda x: x[seed_index], params)
    network = make_network(AgentConfig.from_any(meta["agent"]), int(meta["action_dim"]))
    return network, params, meta


# network fields a warm-start policy must share with the agent (the shapes do not show them all)
NETWORK_FIELDS = ("recurrent", "hidden", "num_layers", "rnn_hidden", "rnn_skip", "activation",
                   "state_dependent_std")


def init_policy_file(init_policy: str | Path) -> Path:
    """``agent.init_policy`` as a path; a clear error where no file is there."""
    path = Path(str(init_policy))
    if not path.is_file():
        raise FileNotFoundError(f"agent.init_policy: no policy file at {path}")
    return path


def warm_start_params(agent: Any, obs_dim: int, action_dim: int) -> Any:
    """Starting variables for ``agent.num_seeds`` seeds from ``agent.init_policy`` (a
    :func:`save_policy` file), stacked over seeds: seed i takes the file's seed i, or every seed
    ``agent.init_policy_seed``, or the file's only seed. ``agent.init_policy_log_std`` replaces
    the learned log std (e.g. to explore less when fine-tuning). Errors name the file and the
    mismatch."""
    config = AgentConfig.from_any(agent)
    path = init_policy_file(config.init_policy)
    _, params, meta = load_policy(path)
    theirs = AgentConfig.from_any(meta["agent"])
    differing = {name: (getattr(theirs, name), getattr(config, name)) for name in NETWORK_FIELDS
                 if getattr(theirs, name) != getattr(config, name)}
    if differing:
        raise ValueError(f"agent.init_policy {path}: its network differs from the agent's "
                         f"(field: (file, agent)): {differing}")
    dims = {"obs_dim": (int(meta["obs_dim"]), obs_dim),
            "action_dim": (int(meta["action_dim"]), action_dim)}
    if any(a != b for a, b in dims.values()):
        raise ValueError(f"agent.init_policy {path}: trained for another environment "
                         f"(field: (file, this env)): {dims}")
    available = int(meta.get("num_seeds", 1))
    if config.init_policy_seed is not None:
        if not 0 <= config.init_policy_seed < available:
            raise ValueError(f"agent.init_policy_seed={config.init_policy_seed}: {path} holds "
                             f"seeds 0..{available - 1}")
        chosen = np.full(config.num_seeds, config.init_policy_seed)
    elif available == config.num_seeds:
        chosen = np.arange(config.num_seeds)
    elif available == 1:
        chosen = np.zeros(config.num_seeds, int)
    else:
        raise ValueError(f"agent.init_policy {path} holds {available} seeds, the agent trains "
                         f"{config.num_seeds}: set agent.init_policy_seed to start every seed "
                         f"from one of them")
    params = jax.tree.map(lambda x: x[jnp.asarray(chosen)], params)
    if config.init_policy_log_std is not None:
        if config.state_dependent_std:
            raise ValueError("agent.init_policy_log_std needs the learned log-std vector; with "
                             "agent.state_dependent_std the actor outputs it")
        params = jax.tree_util.tree_map_with_path(
            lambda key, x: jnp.full_like(x, config.init_policy_log_std)
            if jax.tree_util.keystr(key).endswith("['log_std']") else x, params)
    return params


def best_seed(evaluation: pd.DataFrame, source: str | Path) -> int:
    """The seed with the lowest held-out median final distance in the last evaluation during
    training of ``evaluation`` (a train_ppo artifact's ``evaluation.parquet`` table, read from
    ``source``, which errors name)."""
    last = evaluation.sort_values("evaluation").groupby("seed").last()
    medians = last["median_final_distance_m"]
    if not np.isfinite(medians).any():
        raise ValueError(f"{source}: no finite held-out median per seed; choose one with "
                         f"control.seed")
    return int(medians.idxmin())
