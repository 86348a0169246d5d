"""Stage ``train_ppo``: PPO policies in the learned environment, many seeds at once.

``env.name`` picks the environment (``pipeline.envs.factory``):

- ``learned`` (default): the fitted LSTM of the fit_model artifact of this config; goals
  (``goal_mode=data``) are the model's open-loop predictions along the training runs' commands
  (``env.goal_source=predicted``, reachable in the model's world) or their measured positions
  (``measured``); evaluation goals come from the held-out runs: with fit_model's ``cv``
  protocol the measured positions of every run as it was held out by its fold (so all runs,
  measured, while the model trained on all of them), with ``split`` the runs of the split
  recorded by fit_model; the rest pose is the mean measured first pose of the runs.
- ``sim``: the simulated arm itself (no model needed; the upper bound for the learned env).
- ``gymnax``: a standard gymnax environment (``env.gymnax_name``) to check the PPO.

``agent.num_seeds`` seeds train in one jitted, vmapped program (``pipeline.ppo.train_seeds``).

Artifact: ``metrics.parquet`` (per seed and update: timesteps, mean episodic return, final
distance, success rate, losses), ``evaluation.parquet`` (per seed and evaluation on held-out
goals), ``episodes.parquet`` (the last evaluation's episodes), ``policy.msgpack`` (the policies of
all seeds, stacked; ``pipeline.ppo.load_policy``) and ``figures/returns.png`` (mean ± std over
seeds).
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from omegaconf import OmegaConf

from pipeline.artifacts import Artifact, ArtifactStore, artifact_key, produce
from pipeline.envs.factory import (
    data_goals_and_rest_pose,
    make_gymnax_env,
    make_learned_env,
    make_sim_env,
)
from pipeline.ppo import (
    PPOConfig,
    action_bounds,
    init_policy_file,
    save_policy,
    train_seeds,
    warm_start_params,
)
from pipeline.schemas import METADATA_KEY
from pipeline.tracking import tracking

log = logging.getLogger(__name__)
STAGE = "train_ppo"
ENV_NAMES = ("learned", "sim", "gymnax")
# agent fields that do not change the result (display only)
_NON_DETERMINING_AGENT_KEYS = ("progress",)
UNITS = {
    "timesteps": "environment steps per seed",
    "mean_return": "sum of rewards (env=learned/sim: -mm per control period)",
    "final_distance_m": "m",
    "median_final_distance_m": "m",
    "episode_final_distance_m": "m",
}


# --------------------------------------------------------------------------------------------
# keys
# --------------------------------------------------------------------------------------------
def train_ppo_spec(cfg: Any) -> tuple[dict[str, Any], dict[str, str]]:
    """What determines the policies: env, agent, seed and, by env, the robot or the model."""
    env_name = str(cfg.env.name)
    if env_name not in ENV_NAMES:
        raise ValueError(f"env.name must be one of {ENV_NAMES}, got {env_name!r}")
    agent = OmegaConf.to_container(cfg.agent, resolve=True)
    for name in _NON_DETERMINING_AGENT_KEYS:
        agent.pop(name, None)
    for name in ("init_policy", "init_policy_seed", "init_policy_log_std"):
        if agent.get(name) is None:  # cold starts keep the keys they had before warm starts
            agent.pop(name, None)
    spec: dict[str, Any] = {"env": OmegaConf.to_container(cfg.env, resolve=True), "agent": agent,
                            "seed": int(cfg.seed)}
    if agent.get("init_policy"):  # a warm start: the starting policy's content decides too
        path = init_policy_file(agent["init_policy"])
        spec["init_policy_sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    inputs: dict[str, str] = {}
    if env_name == "sim":
        spec["robot"] = OmegaConf.to_container(cfg.robot, resolve=True)
        spec["model_hz"] = float(cfg.dataset.model_hz)
    elif env_name == "learned":
        from pipeline.fit_model import fit_model_key

        spec["limits"] = OmegaConf.to_container(cfg.robot.limits, resolve=True)
        spec["control_hz"] = float(cfg.robot.control_hz)
        inputs["fit_model"] = fit_model_key(cfg)
    return spec, inputs


def train_ppo_key(cfg: Any) -> str:
    return artifact_key(*train_ppo_spec(cfg))


# --------------------------------------------------------------------------------------------
# environments
# --------------------------------------------------------------------------------------------
def learned_env_for(cfg: Any) -> tuple[Any, Any, Any]:
    """``(env, train_params, eval_params)`` of this config's environment.

    ``env=learned`` reads the fit_model artifact (model, run split) and its aligned data.
    """
    env_name = str(cfg.env.name)
    if env_name == "gymnax":
        return make_gymnax_env(cfg)
    if env_name == "sim":
        return make_sim_env(cfg)
    from pipeline import fit_model as fit_stage
    from pipeline.align import align_key
    from pipeline.schemas import ALIGNED, read_table

    store = ArtifactStore(cfg.paths.artifact_dir)
    model_artifact = store.require("fit_model", fit_stage.fit_model_key(cfg))
    aligned_artifact = store.require("align", align_key(cfg))
    dynamics_params = fit_stage.load_model(model_artifact)
    split = json.loads(model_artifact.file("split.json").read_text())
    aligned, _ = read_table(aligned_artifact.file("aligned.parquet"), ALIGNED)
    runs = fit_stage.runs_at_model_rate(aligned, float(cfg.dataset.model_hz),
                                        str(cfg.dataset.model_grid))
    goal_source = str(cfg.env.goal_source)
    if goal_source not in ("predicted", "measured"):
        raise ValueError(f"env.goal_source must be predicted or measured, got {goal_source!r}")
    if goal_source == "predicted":
        # the model's open-loop predictions along the recorded commands: reachable in its world
        from pipeline.train_model import predict_run

        goal_paths = {run["run_id"]: predict_run(dynamics_params, run) for run in runs}
    else:
        goal_paths = {run["run_id"]: run["pos"] for run in runs}
    at_model_rate = pd.concat(
        [pd.DataFrame({"run_id": run["run_id"], "x": goal_paths[run["run_id"]][:, 0],
                       "y": goal_paths[run["run_id"]][:, 1],
                       "z": goal_paths[run["run_id"]][:, 2]}) for run in runs],
        ignore_index=True)
    first_poses = pd.DataFrame([{"run_id": run["run_id"], "x": run["pos"][0, 0],
                                 "y": run["pos"][0, 1], "z": run["pos"][0, 2]} for run in runs])
    every = int(cfg.env.goal_every)
    rest = data_goals_and_rest_pose(first_poses, [])  # rest pose from the measured first poses
    if split.get("protocol") == "cv":
        # training goals along every run (the model trained on all of them); evaluation goals
        # the measured positions of each run as recorded when its fold held it out
        held_out_ids = [fold["held_out"] for fold in split["folds"]]
        measured = pd.concat(
            [pd.DataFrame({"run_id": run["run_id"], "x": run["pos"][:, 0],
                           "y": run["pos"][:, 1], "z": run["pos"][:, 2]})
             for run in runs if run["run_id"] in held_out_ids], ignore_index=True)
        data = {"train_goals": data_goals_and_rest_pose(at_model_rate, [], every)["train_goals"],
                "held_out_goals": data_goals_and_rest_pose(measured, held_out_ids,
                                                           every)["held_out_goals"]}
    else:
        test_ids = list(split["test"]) or list(split["train"])  # one run only: evaluate on it
        data = data_goals_and_rest_pose(at_model_rate, test_ids, every=every)
        if not split["test"]:
            data["train_goals"] = data["held_out_goals"]
    data["rest_pose"], data["rest_pose_std"] = rest["rest_pose"], rest["rest_pose_std"]
    return make_learned_env(cfg, dynamics_params, data["train_goals"], data["held_out_goals"],
                            data["rest_pose"], data["rest_pose_std"])


# --------------------------------------------------------------------------------------------
# tables and figures
# --------------------------------------------------------------------------------------------
def _write_parquet(frame: pd.DataFrame, path: Path, config: dict[str, Any]) -> Path:
    table = pa.Table.from_pandas(frame, preserve_index=False)
    metadata = {"schema": path.stem, "units": {k: v for k, v in UNITS.items() if k in frame},
                "config": config, "provenance": {"stage": STAGE}}
    table = table.replace_schema_metadata({METADATA_KEY: json.dumps(metadata, default=str)})
    pq.write_table(table, path)
    return path


def metrics_table(metrics: dict[str, np.ndarray]) -> pd.DataFrame:
    """Per seed and update: the [num_seeds, num_updates] arrays of ``TrainOutput.metrics``."""
    num_seeds, num_updates = np.asarray(metrics["timesteps"]).shape
    frame = pd.DataFrame({
        "seed": np.repeat(np.arange(num_seeds), num_updates),
        "update": np.tile(np.arange(num_updates), num_seeds),
    })
    for name, values in metrics.items():
        frame[name] = np.asarray(values).reshape(-1)
    return frame


def evaluation_tables(evaluation: dict[str, np.ndarray]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per seed and evaluation, the last evaluation's episodes per seed)."""
    summary_names = ["timesteps", "mean_return", "median_final_distance_m", "success_rate"]
    num_seeds, num_evals = np.asarray(evaluation["timesteps"]).shape
    summary = pd.DataFrame({"seed": np.repeat(np.arange(num_seeds), num_evals),
                            "evaluation": np.tile(np.arange(num_evals), num_seeds)})
    for name in summary_names:
        summary[name] = np.asarray(evaluation[name]).reshape(-1)
    last = {name: np.asarray(values)[:, -1] for name, values in evaluation.items()
            if name.startswith("episode_")}
    num_episodes = last["episode_return"].shape[-1]
    episodes = pd.DataFrame({"seed": np.repeat(np.arange(num_seeds), num_episodes),
                             "episode": np.tile(np.arange(num_episodes), num_seeds)})
    for name, values in last.items():
        episodes[name.removeprefix("episode_")] = values.reshape(-1)
    return summary, episodes


def training_curves(artifact: Artifact) -> pd.DataFrame:
    """Columns timesteps, seed, return: the training return curve of every seed."""
    frame = pd.read_parquet(artifact.file("metrics.parquet"),
                            columns=["timesteps", "seed", "mean_return"])
    return frame.rename(columns={"mean_return": "return"})


def plot_returns(path: Path, metrics: pd.DataFrame, evaluation: pd.DataFrame, title: str
                 ) -> Path:
    """Training return (mean ± std over seeds) and held-out final distance per evaluation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import ticker

    path.parent.mkdir(parents=True, exist_ok=True)
    has_distance = evaluation["median_final_distance_m"].notna().any()
    fig, axes = plt.subplots(1, 2 if has_distance else 1, figsize=(11 if has_distance else 6, 4),
                             squeeze=False)
    # episodes end only now and then: carry each seed's last finished-episode return forward
    filled = metrics.assign(mean_return=metrics.groupby("seed")["mean_return"].ffill())
    stats = filled.groupby("timesteps")["mean_return"].agg(["mean", "std"]).reset_index()
    ax = axes[0, 0]
    ax.plot(stats["timesteps"], stats["mean"], color="C0",
            label=f"training, mean ± std over {metrics['seed'].nunique()} seeds")
    ax.fill_between(stats["timesteps"], stats["mean"] - stats["std"].fillna(0),
                    stats["mean"] + stats["std"].fillna(0), color="C0", alpha=0.25)
    held_out = evaluation.groupby("timesteps")["mean_return"].mean()
    ax.plot(held_out.index, held_out.to_numpy(), "o-", color="C1", label="evaluation (mean)")
    ax.set(xlabel="environment steps per seed", ylabel="episodic return", title=title)
    ax.legend()
    if has_distance:
        ax = axes[0, 1]
        many = evaluation["seed"].nunique() > 6  # then one thin grey line per seed, no legend
        style = {"color": "0.6", "lw": 0.8} if many else {"marker": "o"}
        for seed, rows in evaluation.groupby("seed"):
            ax.plot(rows["timesteps"], 1000 * rows["median_final_distance_m"], alpha=0.7,
                    label=None if many else f"seed {seed}", **style)
        if many:
            across = evaluation.groupby("timesteps")["median_final_distance_m"].median()
            ax.plot(across.index, 1000 * across.to_numpy(), "o-", color="C3",
                    label=f"median over {evaluation['seed'].nunique()} seeds")
        ax.axhline(1.0, color="k", ls="--", lw=1, label="1 mm")
        distances = 1000 * evaluation["median_final_distance_m"].dropna()
        if distances.max() > 10 * max(distances.min(), 1e-6):  # a log axis only where needed
            ax.set_yscale("log")
            ax.yaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
        ax.set(xlabel="environment steps per seed", ylabel="median final distance [mm]",
               title="held-out goals (deterministic policy)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------------
# the stage
# --------------------------------------------------------------------------------------------
def train_ppo(cfg: Any) -> Artifact:
    """Train ``agent.num_seeds`` PPO policies in this config's environment (see module doc)."""
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = train_ppo_spec(cfg)
    agent = PPOConfig.from_any(cfg.agent)

    def build(writer):
        env, train_params, eval_params = learned_env_for(cfg)
        low, high = action_bounds(env, train_params)
        obs_dim = int(np.prod(env.observation_space(train_params).shape))
        action_dim = int(np.prod(low.shape))
        init_params = (warm_start_params(agent, obs_dim, action_dim)
                       if agent.init_policy else None)
        timings: dict[str, float] = {}
        output = train_seeds(agent, env, train_params, eval_params, seed=int(cfg.seed),
                             desc=f"{STAGE} {agent.name} on {env.name}", timings=timings,
                             init_params=init_params)
        steps = agent.num_seeds * agent.num_updates * agent.steps_per_update
        config = {"env": spec["env"], "agent": spec["agent"], "seed": spec["seed"],
                  "init_policy_sha256": spec.get("init_policy_sha256")}

        metrics = metrics_table({k: np.asarray(v) for k, v in output.metrics.items()})
        summary, episodes = evaluation_tables(
            {k: np.asarray(v) for k, v in output.evaluation.items()})
        _write_parquet(metrics, writer.file("metrics.parquet"), config)
        _write_parquet(summary, writer.file("evaluation.parquet"), config)
        _write_parquet(episodes, writer.file("episodes.parquet"), config)

        save_policy(writer.file("policy.msgpack"), output.params, {
            "agent": spec["agent"], "env": spec["env"], "env_name": env.name,
            "obs_dim": obs_dim, "init_policy_sha256": spec.get("init_policy_sha256"),
            "action_dim": action_dim, "action_low": low.tolist(),
            "action_high": high.tolist(), "num_seeds": agent.num_seeds,
        })
        plot_returns(writer.file("figures/returns.png"), metrics, summary,
                     f"{agent.name} on {env.name}")
        with tracking(cfg, STAGE) as tracker:
            per_update = metrics.drop(columns=["seed"]).groupby("update").mean()
            tracker.log_table(per_update.reset_index().rename(columns={"update": "step"}))

        final = episodes["final_distance_m"].to_numpy()
        per_seed = episodes.groupby("seed")["final_distance_m"].median()
        writer.summary = {
            "env": env.name, "agent": agent.name, "num_seeds": agent.num_seeds,
            "timesteps_per_seed": agent.num_updates * agent.steps_per_update,
            "compile_seconds": round(timings["compile_s"], 1),
            "train_seconds": round(timings["run_s"], 1),
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

