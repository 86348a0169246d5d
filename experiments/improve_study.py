"""Rounds on the arm against what the same arm seconds buy otherwise.

From the deployed policy of a config (``control.policy``, trained first) and the arm
``improve.plant`` (a simulated arm with other physics than the data's, e.g. the twin
``sim_sorolex``), for each seed (``improve.seed``: the rounds' goals and sessions):

- ``rounds``: ``stage=improve`` (the policy drives, the models are refitted on its sessions, the
  policy retrained, ``--rounds`` times ``--arm-s`` arm seconds);
- ``walk``: the same rounds with the exploration walk driven instead of the policy
  (``improve.explore_share=1 improve.explore=walk``): more of the walk, refit, retrain;
- ``adapt``: ``stage=adapt`` with a calibration walk of all those arm seconds;
- ``deployed``: the policy as it was.

Each final policy then drives the same held-out goals on the same arm (``stage=control``, a
session per seed): median final distance, share within 1 mm, p90. Writes ``study.csv``,
``study.md``, the rounds' tables (``rounds_<arm>_<seed>.parquet``) and ``rounds.png`` to
``--out``.

    python -m experiments.improve_study --config experiment=real_arm agent.num_seeds=4 \\
        improve.plant=sim_sorolex --rounds 3 --arm-s 300 --seeds 0 1 --out outputs/improve_study
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import chain, keys
from pipeline.config import compose
from pipeline.infra.artifacts import ArtifactStore
from pipeline.schemas import Stage
from pipeline.stages._deployed import training_config
from pipeline.stages._environment import config_environment
from pipeline.stages.improve import goal_seconds, improve_settings, plant_robot

ARMS = ("deployed", "rounds", "walk", "adapt")


def held_out_goals_mm(cfg, count: int, seed: int) -> list[list[float]]:
    """``count`` of the deployed policy's held-out goals (mm), drawn with ``seed``."""
    store = ArtifactStore(cfg.paths.artifact_dir)
    deployed = store.require("train_ppo", keys.key("train_ppo", chain.control_policy_config(cfg)))
    train_cfg, model, aligned = training_config(deployed, store, int(cfg.robot.n_valves))
    _, _, eval_params = config_environment(train_cfg, model, aligned)
    goals = np.asarray(eval_params.goal_set, np.float64)
    chosen = np.random.default_rng(seed).choice(len(goals), count, replace=False)
    return np.round(goals[chosen] * 1000.0, 3).tolist()


def policy_file(cfg, artifact) -> str:
    """The policy a stage left: a round's (its train_ppo input) or an adapt artifact's."""
    if artifact.stage == "adapt":
        return str(artifact.file("policy.msgpack"))
    store = ArtifactStore(cfg.paths.artifact_dir)
    return str(store.path("train_ppo", artifact.manifest["inputs"]["train_ppo"]) /
               "policy.msgpack")


def score(cfg, policy: str, goals_mm: list, seed: int) -> dict[str, float]:
    """The policy on the plant toward ``goals_mm``: one control session (session ``seed``)."""
    settings = improve_settings(cfg)
    drive = OmegaConf.merge(cfg, {"stage": "control", "control": {
        "policy_file": policy, "goals": goals_mm, "hold_s": goal_seconds(cfg, settings),
        "arm_seed": 50_000 + seed}})
    drive.robot = plant_robot(cfg, settings)
    artifact = chain.stage_function(Stage.control)(drive)
    final = pd.read_parquet(artifact.file("goals.parquet"))["final_distance_mm"].to_numpy()
    return {"median_mm": float(np.median(final)), "within_1mm": float(np.mean(final <= 1.0)),
            "p90_mm": float(np.percentile(final, 90)), "goals": len(final)}


def run_arm(arm: str, base: list[str], seed: int, rounds: int, arm_s: float, out: Path):
    """The final policy of ``arm`` for ``seed`` (and the rounds' table where there is one)."""
    overrides = [*base, f"improve.seed={seed}", f"improve.rounds={rounds}",
                 f"improve.arm_s={arm_s}"]
    if arm == "walk":
        overrides += ["improve.explore_share=1", "improve.explore=walk"]
    cfg = compose(*overrides)
    if arm == "deployed":
        store = ArtifactStore(cfg.paths.artifact_dir)
        return cfg, str(store.path("train_ppo", keys.key(
            "train_ppo", chain.control_policy_config(cfg))) / "policy.msgpack")
    if arm == "adapt":
        deployed = run_arm("deployed", base, seed, rounds, arm_s, out)[1]
        adapt = OmegaConf.merge(cfg, {"stage": "adapt", "control": {
            "policy_file": deployed, "arm_seed": 1000 * seed + 1},
            "adapt": {"walk_s": rounds * arm_s}})
        adapt.robot = plant_robot(cfg, improve_settings(cfg))
        return cfg, policy_file(cfg, chain.stage_function(Stage.adapt)(adapt))
    last = chain.stage_function(Stage.improve)(OmegaConf.merge(cfg, {"stage": "improve"}))
    pd.read_parquet(last.file("rounds.parquet")).to_parquet(
        out / f"rounds_{arm}_{seed}.parquet")
    return cfg, policy_file(cfg, last)


def markdown(table: pd.DataFrame) -> str:
    """``table`` as a markdown table, numbers to three digits."""
    cells = [[f"{v:.3g}" if isinstance(v, float) else str(v) for v in row]
             for row in table.itertuples(index=False)]
    lines = ["| " + " | ".join(map(str, table.columns)) + " |",
             "| " + " | ".join("---" for _ in table.columns) + " |"]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in cells]) + "\n"


def plot(out: Path, arms: list[str], seeds: list[int]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
    for arm in arms:
        for seed in seeds:
            path = out / f"rounds_{arm}_{seed}.parquet"
            if not path.is_file():
                continue
            table = pd.read_parquet(path)
            label = f"{arm} (seed {seed})"
            axes[0].plot(table["arm_s_total"] / 60, table["plant_median_mm"], marker="o",
                         label=label)
            axes[1].plot(table["arm_s_total"] / 60, 100 * table["plant_within_1mm"],
                         marker="o", label=label)
    axes[0].set(xlabel="arm minutes", ylabel="median final distance on the arm [mm]",
                yscale="log")
    axes[1].set(xlabel="arm minutes", ylabel="goals within 1 mm on the arm [%]", ylim=(0, 105))
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "rounds.png", dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", nargs="*", default=[])
    parser.add_argument("--arms", nargs="*", default=list(ARMS), choices=ARMS)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--arm-s", type=float, default=300.0)
    parser.add_argument("--seeds", type=int, nargs="*", default=[0])
    parser.add_argument("--goals", type=int, default=32)
    parser.add_argument("--out", type=Path, default=Path("outputs/improve_study"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.seeds:
        goals = held_out_goals_mm(compose(*args.config), args.goals, seed)
        for arm in args.arms:
            cfg, policy = run_arm(arm, args.config, seed, args.rounds, args.arm_s, args.out)
            rows.append({"arm": arm, "seed": seed,
                         "arm_s": 0.0 if arm == "deployed" else args.rounds * args.arm_s,
                         **score(cfg, policy, goals, seed)})
            print(pd.DataFrame(rows).to_string(index=False), flush=True)
    table = pd.DataFrame(rows)
    table.to_csv(args.out / "study.csv", index=False)
    summary = table.groupby("arm", sort=False)[["median_mm", "within_1mm", "p90_mm"]].median()
    (args.out / "study.md").write_text(
        f"config: `{' '.join(args.config)}`, {args.rounds} x {args.arm_s:g} arm s, seeds "
        f"{args.seeds}, {args.goals} held-out goals a seed\n\n"
        + markdown(table) + "\n\nmedian over seeds:\n\n" + markdown(summary.reset_index()))
    plot(args.out, ["rounds", "walk"], args.seeds)
    print(summary.to_string(), flush=True)


if __name__ == "__main__":
    main()
