"""Stage ``evaluate``: closed-loop results on the learned model and on the plant, and the report.

For every policy type in ``evaluation.policies`` (all seeds) and every baseline (``preload``: do
nothing; ``random``: random safe actions; ``mpc``: sampling-based MPC on the learned model, see
:mod:`pipeline.mpc`), on the same held-out goals and start states:

- on the **learned environment** (the fitted model the policies were trained in);
- on the **plant**: the simulated arm for ``robot=sim`` (its own hysteresis, creep and rest-pose
  spread; the model never saw its equations), with the policies observing it through the same
  normalization they were trained with;
- a **consecutive-goals** task: ``num_consecutive_goals`` targets one after another, no reset.

Episodes last ``env.max_steps`` control periods and, unlike in training, do not end when the goal is
first within ``env.goal_tolerance_m``: on an arm the controller has to get there and stay, so the
final distance is the distance after the last period (``steps_to_*`` tells when it first got
within 1 and 3 mm). Passing near a goal by chance, as random actions do, does not count. Tables (Parquet): one row
per episode (``episodes.parquet``), the summary per controller and plant (``summary.parquet``),
the learned-vs-plant gap per episode (``plant_gap.parquet``) and the consecutive-goals results.
Figures and ``report.md`` / ``report.html`` close the run.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import mpc, rollouts
from pipeline.artifacts import Artifact, ArtifactStore, artifact_key, produce
from pipeline.config import PROJECT_ROOT, RobotKind
from pipeline.envs.learned import EnvParams, SoftArmReachEnv, make_env_params
from pipeline.envs.plants import learned_plant, sim_plant
from pipeline.metrics import MM_PER_M, episode_metrics, plant_gap, summarize
from pipeline.report import Figure, Section, Table, write_report

log = logging.getLogger(__name__)
STAGE = "evaluate"


# --------------------------------------------------------------------------------------------
# configuration of the policies to evaluate
# --------------------------------------------------------------------------------------------
def agent_config(name: str, base: Any) -> Any:
    """``base`` (the composed ``agent``) with the settings of option ``name`` laid over it.

    The option file (conf/agent/<name>.yaml) says what makes the policy type (name, recurrent,
    ...); everything else, e.g. an experiment's seeds and budget, carries over from ``base``.
    """
    path = PROJECT_ROOT / "conf" / "agent" / f"{name}.yaml"
    if not path.is_file():
        options = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise ValueError(f"evaluation.policies: no agent config {name!r}; options: {options}")
    node = OmegaConf.load(path)
    node.pop("defaults", None)
    return OmegaConf.merge(base, node)


def policy_configs(cfg: Any) -> dict[str, Any]:
    """One full config per evaluated policy type: ``cfg`` with its ``agent`` replaced."""
    variants = {}
    for name in cfg.evaluation.policies:
        variant = cfg.copy()
        variant.agent = agent_config(name, cfg.agent)
        variants[name] = variant
    return variants


def evaluate_spec(cfg: Any) -> tuple[dict[str, Any], dict[str, str]]:
    from pipeline.train_ppo import train_ppo_key

    spec = {"evaluation": OmegaConf.to_container(cfg.evaluation, resolve=True),
            "env": OmegaConf.to_container(cfg.env, resolve=True)}
    inputs = {f"train_ppo/{name}": train_ppo_key(variant)
              for name, variant in policy_configs(cfg).items()}
    return spec, inputs


def evaluate_key(cfg: Any) -> str:
    return artifact_key(*evaluate_spec(cfg))


# --------------------------------------------------------------------------------------------
# the stage
# --------------------------------------------------------------------------------------------
def evaluate(cfg: Any, train_missing: bool = False) -> Artifact:
    """Evaluate the trained policies of this config; with ``train_missing`` (the ``all`` chain)
    policy types not trained yet are trained first."""
    from pipeline import train_ppo as train_stage

    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = evaluate_spec(cfg)
    policies = {}
    for name, variant in policy_configs(cfg).items():
        found = store.find("train_ppo", inputs[f"train_ppo/{name}"])
        if found is None and train_missing:
            found = train_stage.train_ppo(variant)
        if found is None:
            found = store.require("train_ppo", inputs[f"train_ppo/{name}"],
                                  hint=f" with agent={name}")
        policies[name] = found

    def build(writer):
        results = run_evaluation(cfg, policies)
        for name, frame in results["tables"].items():
            frame.to_parquet(writer.file(f"{name}.parquet"), index=False)
        figures = make_figures(writer.path / "figures", cfg, policies, results)
        sections = report_sections(cfg, store, policies, results, figures)
        write_report(writer.path, f"sorolearn run: robot={cfg.robot.name}", sections)
        writer.summary = results["headline"]
        log.info("evaluate: %s", json.dumps(results["headline"]))

    artifact = produce(store, STAGE, spec, inputs, build, force=cfg.force)
    log.info("evaluate: report at %s", artifact.file("report.html"))
    return artifact


# --------------------------------------------------------------------------------------------
# rollouts
# --------------------------------------------------------------------------------------------
def _plant_env(cfg: Any, learned_env: SoftArmReachEnv, learned_params: EnvParams,
               key: jax.Array) -> tuple[SoftArmReachEnv, EnvParams] | None:
    """The ground-truth plant as an environment observed like the learned one (same goals and
    normalization), or None when this robot has no simulator."""
    from pipeline.envs.factory import (
        _common_params,
        observation_options,
        sim_plant_params,
        sim_rest_pose,
    )

    if RobotKind(cfg.robot.kind) is not RobotKind.sim or not cfg.evaluation.plant:
        return None
    mocap_hz = float(cfg.robot.mocap.rate_hz)
    frames = round(mocap_hz / float(cfg.dataset.model_hz))
    # observed exactly like the learned env, which make_learned_env built from the same options
    env = SoftArmReachEnv(sim_plant(mocap_hz, frames), learned_env.control_hz,
                          **observation_options(cfg.env))
    plant = sim_plant_params(cfg)
    params = make_env_params(
        env, plant, key=key, safe_set=learned_params.safe_set, preload=plant.preload,
        rest_pose=sim_rest_pose(plant),
        rest_pose_std=jnp.asarray(cfg.robot.physics.rest_pose_std_m, jnp.float32),
        goal_set=learned_params.goal_set, obs_mean=learned_params.obs_mean,
        obs_scale=learned_params.obs_scale, **_common_params(cfg))
    return env, params


def _starts(params: EnvParams, count: int) -> tuple[Any, jax.Array]:
    index = jnp.arange(count) % params.reset_positions.shape[0]
    return (jax.tree.map(lambda leaf: leaf[index], params.reset_carries),
            params.reset_positions[index])


def _run(env, params, make_controller, carries, keys, starts, goals):
    """vmap a rollout over episodes: goals [E, T, 3] -> positions [E, T+1, 3], commands."""
    start_carries, start_positions = starts

    def one(carry, key, start_carry, start_position, goal_path):
        return rollouts.rollout(env, params, make_controller(), carry, key, start_carry,
                                start_position, goal_path)

    return jax.jit(jax.vmap(one))(carries, keys, start_carries, start_positions, goals)


def _controllers(cfg, env, params, learned_params, policies_loaded, num_episodes):
    """(name, seed) -> (controller factory, per-episode carries), every policy seed and baseline.

    ``learned_params`` are the learned environment's: the MPC's model starts from its settled
    states (the same ones the learned environment starts from).
    """
    from pipeline.networks import initial_hidden

    out = {}
    for name, (network, stacked, num_seeds) in policies_loaded.items():
        for seed in range(num_seeds):
            seed_params = jax.tree.map(lambda x, s=seed: x[s], stacked)
            hidden = initial_hidden(network, 1)
            carries = (jnp.broadcast_to(hidden, (num_episodes, *hidden.shape)),
                       jnp.ones((num_episodes,), bool))
            out[(name, seed)] = (lambda n=network, p=seed_params:
                                 rollouts.policy_controller(n, p), carries)
    dummy = jnp.zeros((num_episodes,))
    for baseline in cfg.evaluation.baselines:
        if baseline == "preload":
            out[(baseline, 0)] = (lambda: rollouts.preload_controller(env, params), dummy)
        elif baseline == "random":
            out[(baseline, 0)] = (rollouts.random_controller, dummy)
        elif baseline == "mpc":
            settings = mpc.CEMSettings(horizon=int(cfg.evaluation.mpc_horizon),
                                       num_samples=int(cfg.evaluation.mpc_samples),
                                       num_iterations=int(cfg.evaluation.mpc_iterations))
            model = learned_plant(float(cfg.dataset.model_hz))
            model_carries, model_starts = _starts(learned_params, num_episodes)
            carries = jax.vmap(mpc.initial_carry, in_axes=(0, 0, None))(
                model_carries, model_starts, params.preload)
            out[(baseline, 0)] = (lambda m=model, s=settings: mpc.mpc_controller(
                env, params, m, learned_params.plant, s), carries)
        else:
            raise ValueError(f"evaluation.baselines: unknown baseline {baseline!r}; "
                             "known: preload, random, mpc")
    return out


def run_evaluation(cfg: Any, policies: dict[str, Artifact]) -> dict[str, Any]:
    """Roll out every controller on the learned env and the plant; return tables and arrays."""
    from pipeline.ppo import load_policy
    from pipeline.train_ppo import learned_env_for

    env, _, eval_params = learned_env_for(cfg)
    evaluation = cfg.evaluation
    episodes, steps = int(evaluation.num_episodes), int(cfg.env.max_steps)
    key = jax.random.key(int(evaluation.seed))
    goal_key, plant_key, rollout_key, consecutive_key = jax.random.split(key, 4)

    goal_index = jax.random.randint(goal_key, (episodes,), 0, eval_params.goal_set.shape[0])
    goals = eval_params.goal_set[goal_index]
    goal_paths = jnp.broadcast_to(goals[:, None], (episodes, steps, 3))
    plants = {"learned": (env, eval_params)}
    plant_env = _plant_env(cfg, env, eval_params, plant_key)
    if plant_env is not None:
        plants["plant"] = plant_env

    loaded = {}
    for name, artifact in policies.items():
        network, stacked, _ = load_policy(artifact.file("policy.msgpack"))
        loaded[name] = (network, stacked, jax.tree.leaves(stacked)[0].shape[0])

    limits = cfg.robot.limits
    rows, finals, paths = [], {}, {}
    keys = jax.random.split(rollout_key, episodes)
    for plant_name, (plant_env_i, plant_params) in plants.items():
        controllers = _controllers(cfg, plant_env_i, plant_params, eval_params, loaded, episodes)
        starts = _starts(plant_params, episodes)
        for (controller, seed), (factory, carries) in controllers.items():
            positions, commands = _run(plant_env_i, plant_params, factory, carries, keys,
                                       starts, goal_paths)
            positions, commands = np.asarray(positions), np.asarray(commands)
            table = episode_metrics(positions, np.asarray(goals), commands, limits)
            table.insert(0, "episode", np.arange(episodes))
            table.insert(0, "seed", seed)
            table.insert(0, "controller", controller)
            table.insert(0, "plant", plant_name)
            rows.append(table)
            finals[(plant_name, controller, seed)] = positions[:, -1]
            paths[(plant_name, controller, seed)] = positions
    episodes_table = pd.concat(rows, ignore_index=True)
    summary = summarize(episodes_table, ["plant", "controller"])
    gaps = _gap_table(episodes_table, finals) if "plant" in plants else pd.DataFrame()
    consecutive = _consecutive(cfg, plants, loaded, consecutive_key, eval_params)
    headline = {
        f"{row.plant}/{row.controller}": {"median_final_mm": float(row.median_final_mm),
                                          "success_1mm": float(row.success_1mm),
                                          "success_3mm": float(row.success_3mm)}
        for row in summary.itertuples()}
    return {"tables": {"episodes": episodes_table, "summary": summary, "plant_gap": gaps,
                       "consecutive": consecutive},
            "paths": paths, "goals": np.asarray(goals), "headline": headline}


def _gap_table(episodes: pd.DataFrame, finals: dict) -> pd.DataFrame:
    rows = []
    for (plant, controller, seed), final in finals.items():
        if plant != "plant":
            continue
        learned = episodes[(episodes.plant == "learned") & (episodes.controller == controller)
                           & (episodes.seed == seed)]
        on_plant = episodes[(episodes.plant == "plant") & (episodes.controller == controller)
                            & (episodes.seed == seed)]
        gap = plant_gap(learned, on_plant, finals[("learned", controller, seed)], final)
        gap.insert(0, "seed", seed)
        gap.insert(0, "controller", controller)
        rows.append(gap)
    return pd.concat(rows, ignore_index=True)


def _consecutive(cfg, plants, loaded, key, eval_params) -> pd.DataFrame:
    """Reach ``num_consecutive_goals`` goals one after another (``max_steps`` each, no reset);
    the distance at the end of each goal's time is recorded."""
    count = int(cfg.evaluation.num_consecutive_goals)
    episodes = int(cfg.evaluation.consecutive_episodes)
    per_goal = int(cfg.env.max_steps)
    if count < 1 or episodes < 1:
        return pd.DataFrame()
    goal_key, rollout_key = jax.random.split(key)
    index = jax.random.randint(goal_key, (episodes, count), 0, eval_params.goal_set.shape[0])
    goals = np.repeat(np.asarray(eval_params.goal_set[index]), per_goal, axis=1)
    keys = jax.random.split(rollout_key, episodes)
    rows = []
    for plant_name, (env, params) in plants.items():
        controllers = _controllers(cfg, env, params, eval_params, loaded, episodes)
        for (controller, seed), (factory, carries) in controllers.items():
            if controller in ("preload", "random"):
                continue
            positions, _ = _run(env, params, factory, carries, keys, _starts(params, episodes),
                                jnp.asarray(goals))
            positions = np.asarray(positions)
            ends = positions[:, per_goal::per_goal]  # pose at the end of each goal's time
            targets = goals[:, per_goal - 1::per_goal]
            distance = np.linalg.norm(ends - targets, axis=-1) * MM_PER_M
            for goal_number in range(count):
                rows.append({"plant": plant_name, "controller": controller, "seed": seed,
                             "goal": goal_number,
                             "median_distance_mm": float(np.median(distance[:, goal_number])),
                             "success_3mm": float((distance[:, goal_number] <= 3).mean())})
    return pd.DataFrame(rows)


# --------------------------------------------------------------------------------------------
# figures and report
# --------------------------------------------------------------------------------------------
def make_figures(folder: Path, cfg, policies, results) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    figures = {}

    # ---- training curves: mean +- std over seeds per policy type (paper Fig. 7) ------------
    from pipeline.train_ppo import training_curves

    fig, ax = plt.subplots(figsize=(7.5, 4))
    for i, (name, artifact) in enumerate(policies.items()):
        curves = training_curves(artifact)  # columns: timesteps, seed, return
        stats = curves.groupby("timesteps")["return"].agg(["mean", "std"]).reset_index()
        ax.plot(stats["timesteps"], stats["mean"], color=f"C{i}", label=name)
        ax.fill_between(stats["timesteps"], stats["mean"] - stats["std"].fillna(0),
                        stats["mean"] + stats["std"].fillna(0), color=f"C{i}", alpha=0.25)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episodic return")
    ax.set_title("PPO in the learned environment (mean ± std over seeds)")
    ax.legend()
    fig.tight_layout()
    figures["returns"] = folder / "returns.png"
    fig.savefig(figures["returns"], dpi=100)
    plt.close(fig)

    # ---- distance to goal over time, per controller and plant -------------------------------
    goals = results["goals"]
    plants = sorted({key[0] for key in results["paths"]})
    controllers = list(dict.fromkeys(key[1] for key in results["paths"]))
    fig, axes = plt.subplots(1, len(plants), figsize=(6.5 * len(plants), 4), squeeze=False,
                             sharey=True)
    for ax, plant in zip(axes[0], plants):
        for i, controller in enumerate(controllers):
            seeds = [k for k in results["paths"] if k[0] == plant and k[1] == controller]
            distance = np.concatenate([
                np.linalg.norm(results["paths"][k] - goals[:, None], axis=-1) * MM_PER_M
                for k in seeds])
            t = np.arange(distance.shape[1]) / float(cfg.robot.control_hz)
            median = np.median(distance, axis=0)
            low, high = np.percentile(distance, [25, 75], axis=0)
            ax.semilogy(t, median, color=f"C{i}", label=controller)
            ax.fill_between(t, low, high, color=f"C{i}", alpha=0.15)
        ax.axhline(float(cfg.env.goal_tolerance_m) * MM_PER_M, color="k", ls=":", lw=0.8)
        ax.set_title(f"on the {plant} ({'fitted model' if plant == 'learned' else 'simulated arm'})")
        ax.set_xlabel("time [s]")
    axes[0, 0].set_ylabel("distance to goal [mm] (median, IQR)")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    figures["distance"] = folder / "distance.png"
    fig.savefig(figures["distance"], dpi=100)
    plt.close(fig)

    # ---- task-space trajectories against goals ------------------------------------------------
    shown = [c for c in controllers if c not in ("preload", "random")]
    fig, axes = plt.subplots(len(plants), len(shown), figsize=(4 * len(shown), 4 * len(plants)),
                             squeeze=False)
    for r, plant in enumerate(plants):
        for c, controller in enumerate(shown):
            ax = axes[r, c]
            path = results["paths"][(plant, controller, 0)]
            for e in range(min(6, len(path))):
                ax.plot(path[e, :, 0] * 1e3, path[e, :, 2] * 1e3, "-", color=f"C{e}", lw=1)
                ax.plot(path[e, 0, 0] * 1e3, path[e, 0, 2] * 1e3, "o", color=f"C{e}", ms=3)
                ax.plot(goals[e, 0] * 1e3, goals[e, 2] * 1e3, "x", color=f"C{e}", ms=8, mew=2)
            ax.set_title(f"{controller} on the {plant}", fontsize=9)
            ax.set_xlabel("x [mm]")
            ax.set_ylabel("z [mm]")
            ax.set_aspect("equal", adjustable="datalim")
    fig.suptitle("trajectories (o start, x goal), seed 0")
    fig.tight_layout()
    figures["trajectories"] = folder / "trajectories.png"
    fig.savefig(figures["trajectories"], dpi=100)
    plt.close(fig)
    return figures


def _summary_section(cfg, model, summary: pd.DataFrame, policies: list[str]) -> Section:
    """The headline: model accuracy, and each controller's median final distance."""
    section = Section("Summary")
    if model is not None:
        held_out = model.manifest["summary"]
        how = ("leave-one-run-out" if held_out.get("protocol") == "cv" else "on held-out runs")
        section.add(f"Dynamics model: **{held_out['lstm_mean_mm']:.2f} mm** mean open-loop error "
                    f"{how} (mean-position baseline {held_out['mean_position_mean_mm']:.2f}"
                    f" mm, linear lagged-pressure baseline {held_out['linear_lagged_mean_mm']:.2f} "
                    "mm).")
        for warning in held_out.get("warnings", []):
            section.add(f"**Warning:** {warning}.")
    wide = summary.pivot_table(index="controller", columns="plant",
                               values="median_final_mm").reset_index()
    wide.columns.name = None
    order = {name: i for i, name in enumerate(policies + list(cfg.evaluation.baselines))}
    wide = wide.sort_values("controller", key=lambda c: c.map(order))
    section.add(Table(wide.rename(columns={"learned": "learned env [mm]", "plant": "plant [mm]"}),
                      f"median final distance to held-out goals after {cfg.env.max_steps} control "
                      "periods"))
    return section


def report_sections(cfg, store, policies, results, figures) -> list[Section]:
    from pipeline.align import align_key
    from pipeline.collect import collect_key
    from pipeline.fit_model import fit_model_key

    collect = store.find("collect", collect_key(cfg))
    aligned = store.find("align", align_key(cfg))
    model = store.find("fit_model", fit_model_key(cfg))
    tables = results["tables"]
    summary = tables["summary"]
    sections = [_summary_section(cfg, model, summary, list(policies))]

    config = Section("Configuration")
    config.add(f"Robot `{cfg.robot.name}`; exploration alpha {cfg.exploration.alpha}, beta "
               f"{cfg.exploration.beta}, P_max {cfg.exploration.p_max} kPa; model "
               f"{cfg.model.hidden} units at {cfg.dataset.model_hz} Hz; policies "
               f"{', '.join(cfg.evaluation.policies)}; baselines "
               f"{', '.join(cfg.evaluation.baselines)}.")
    config.add("```yaml\n" + OmegaConf.to_yaml(cfg, resolve=True) + "```")
    sections.append(config)

    data = Section("Data")
    if collect is not None:
        collected = collect.manifest["summary"]
        data.add(f"{collected.get('runs')} runs, {collected.get('commands')} commands, "
                 f"{collected.get('frames')} motion-capture frames "
                 f"({collected.get('dropped_frames')} dropped). Artifact `{collect.path}`.")
        for name, caption in (("exploration_alphas.png", "exploration walk for several alpha"),
                              ("runs.png", "recorded commands and positions")):
            if collect.file(f"figures/{name}").is_file():
                data.add(Figure(collect.file(f"figures/{name}"), caption))
    if aligned is not None:
        counts = aligned.manifest["summary"]
        data.add(Table(pd.DataFrame([counts]), "alignment counts"))
    sections.append(data)

    accuracy = Section("Model accuracy")
    if model is not None:
        metrics = pd.read_parquet(model.file("metrics.parquet"))
        accuracy.add("Open-loop error over each entire run (mean and 95th percentile, mm).")
        if "cv" in set(metrics["split"]):
            from pipeline.model_cv import cv_summary

            accuracy.add("Leave-one-run-out cross-validation: each run predicted by the model "
                         "trained on the other runs, next to the baselines fitted on the same "
                         "runs and that fold model's error on its own training runs; the model "
                         "the policies use is trained on all runs.")
            accuracy.add(Table(cv_summary(metrics), "held-out error per run [mm]"))
        else:
            per_run = metrics.pivot_table(index=["split", "run_id"], columns="model",
                                          values="mean_mm").reset_index()
            per_run.columns.name = None
            accuracy.add(Table(per_run, "mean error [mm] per run"))
        for warning in model.manifest.get("summary", {}).get("warnings", []):
            accuracy.add(f"**Warning:** {warning}.")
        for name, caption in (("loss.png", "loss curves (EMA-smoothed)"),
                              ("reconstruction.png", "reconstruction of a training and an "
                                                     "unseen run")):
            accuracy.add(Figure(model.file(f"figures/{name}"), caption))
    sections.append(accuracy)

    is_policy = summary["controller"].isin(list(policies))
    sections.append(Section("Policy results", [
        f"Final distance to held-out goals after {cfg.env.max_steps} control periods (the "
        "controller must reach the goal and stay; steps_to_3mm: when it first got within 3 mm), "
        "all seeds pooled.",
        Table(summary[is_policy]), Figure(figures["returns"], "training return, mean ± std "
                                                              "over seeds"),
        Figure(figures["distance"], "distance to goal over time"),
        Figure(figures["trajectories"], "task-space trajectories against goals")]))
    sections.append(Section("Baselines", [
        "Preload (do nothing), random safe actions, and sampling-based MPC on the learned model "
        "(offset-corrected on the plant), on the same goals and starts.",
        Table(summary[~is_policy])]))
    gap_section = Section("Plant gap")
    if len(tables["plant_gap"]):
        gap = tables["plant_gap"].groupby("controller").agg(
            median_final_gap_mm=("final_gap_mm", "median"),
            median_position_gap_mm=("final_position_gap_mm", "median")).reset_index()
        gap_section.add("Learned environment vs the simulated arm for the same goals: "
                        "plant final distance minus learned final distance, and the distance "
                        "between the two final poses.")
        gap_section.add(Table(gap))
    else:
        gap_section.add(f"No plant for robot `{cfg.robot.name}`: evaluated on the learned "
                        "environment only.")
    sections.append(gap_section)
    consecutive = tables["consecutive"]
    if len(consecutive):
        sections.append(Section("Consecutive goals", [
            f"{cfg.evaluation.num_consecutive_goals} goals in a row, {cfg.env.max_steps} "
            "control periods each, no reset: distance at the end of each goal's time.",
            Table(consecutive.groupby(["plant", "controller", "goal"])
                  ["median_distance_mm"].median().unstack("goal").reset_index())]))
    return sections
