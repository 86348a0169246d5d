"""The deployed policy against its session-adapted versions on simulated sessions whose physics
differ from the training runs'.

For each session (a physics change of the simulated arm and ``control.arm_seed``): ``stage=adapt``
with ``adapt.mechanism=none`` (the policy fine-tuned in the deployed model: what the extra training
alone gives) and with the calibrated model (``adapt.mechanism``), then ``stage=control`` on the
same session and goals with the deployed policy (the seed the fine-tunes start from) and with each
adapted one. Prints per session and over all sessions the median final distance, the share of
goals within 1 mm and the p90, and the adapt step's wall time. With ``--trajectory``, each
session follows that reference instead (``control.trajectory``): per session the RMSE, lag and
share of the commands on the limits, where the session's arm rests, and over all sessions the
median RMSE.

    python experiments/adapt_session.py [--sessions 11 12] [--goals 8] [--hold-s 20]
    python experiments/adapt_session.py --change rest --trajectory circle --sessions 0 1 2 \
        --config experiment=real_arm_tracking agent=apg_rnn robot=sim_sorolex

Runs on the deployed policy of the config (``control.policy``, default chain unless ``--config``
says otherwise; trained first, e.g. ``python -m pipeline stage=train_ppo``), or ``--policy-file``.
``--change rest``: the sessions differ only where the arm rests and in the mocap's noise (the
robot's ``physics.session_std`` set to zero).
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import pandas as pd

from pipeline import keys
from pipeline.__main__ import run
from pipeline.config import compose
from pipeline.infra.artifacts import ArtifactStore
from pipeline.stages._deployed import training_config
from pipeline.stages._environment import config_environment

# physics changes of the simulated arm (robot=sim): what a session of the day may differ by
CHANGES = {
    "gains": ["robot.physics.chamber_gains=[0.85,1.15,1.0]"],
    # the calibrated twin's spread between sessions (conf/robot/sim_sorolex.yaml), drawn per
    # control.arm_seed on the default arm
    "twin_spread": ["+robot.physics.session_std={chamber_angles_deg:[2.6,1.75,3.8],"
                    "chamber_gains:[0.087,0.14,0.105],pressure_tau_s:0.041,natural_freq_hz:0.24,"
                    "damping_ratio:0.2,hysteresis_kpa:0.081,elong_gain:0.00033}"],
}


def change_overrides(change: str, config: list[str]) -> list[str]:
    """The overrides of ``change``; ``rest``: every spread of the robot's
    ``physics.session_std`` (composed with ``config``) set to zero."""
    if change != "rest":
        return CHANGES[change]
    spread = compose(*config).robot.physics.get("session_std") or {}
    return [f"robot.physics.session_std.{name}=0" for name in spread]


def held_out_goals_mm(policy_file: str, count: int, config: list[str]) -> list[list[float]]:
    """``count`` goals spread over the deployed policy's held-out goals, in mm."""
    cfg = compose(*config, f"control.policy_file={policy_file}")
    stage, key = keys.control_policy(cfg)
    store = ArtifactStore(cfg.paths.artifact_dir)
    artifact = store.require(stage, key)
    train_cfg, model, aligned = training_config(artifact, store, 3)
    _, _, eval_params = config_environment(train_cfg, model, aligned)
    goals = np.asarray(eval_params.goal_set, np.float64)
    chosen = goals[np.linspace(0, len(goals) - 1, count).round().astype(int)]
    return np.round(chosen * 1000, 2).tolist()


def final_distances(overrides: list[str]) -> np.ndarray:
    """The control session's final distance per goal [mm]."""
    artifact = run(compose("stage=control", *overrides))["control"]
    goals = pd.read_parquet(artifact.file("goals.parquet"))
    return goals["final_distance_mm"].to_numpy(np.float64)


def tracking_scores(overrides: list[str]) -> np.ndarray:
    """The control session following its reference: ``[rmse_mm, lag_s, at_limits]`` after the
    settle time and where the arm rested at the start, ``[x, y, z]`` mm."""
    artifact = run(compose("stage=control", *overrides))["control"]
    row = pd.read_parquet(artifact.file("tracking.parquet")).iloc[0]
    start = pd.read_parquet(artifact.file("periods.parquet")).sort_values("period").iloc[0]
    return np.array([row["rmse_mm"], row["lag_s"], row["at_limits"],
                     *(1000 * start[list("xyz")].to_numpy(np.float64))])


def stats(distances: np.ndarray) -> dict[str, float]:
    return {"median_mm": round(float(np.median(distances)), 3),
            "within_1mm": round(float(np.mean(distances < 1.0)), 3),
            "p90_mm": round(float(np.percentile(distances, 90)), 3), "goals": len(distances)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--change", choices=sorted([*CHANGES, "rest"]), default="gains")
    parser.add_argument("--sessions", type=int, nargs="+", default=[11, 12])
    parser.add_argument("--goals", type=int, default=8)
    parser.add_argument("--hold-s", type=float, default=20.0)
    parser.add_argument("--trajectory", default=None,
                        help="follow this reference (control.trajectory) instead of goals")
    parser.add_argument("--config", nargs="*", default=[],
                        help="overrides of every stage's config, e.g. experiment=...")
    parser.add_argument("--policy-file", default=None,
                        help="the deployed policy.msgpack (default: the config's control.policy)")
    parser.add_argument("--deployed-only", action="store_true",
                        help="no stage=adapt: the deployed policy on each session alone")
    parser.add_argument("--mechanism", default="fine_tune")
    parser.add_argument("--policy-timesteps", type=int, default=131072)
    args = parser.parse_args()
    config = list(args.config)
    policy = args.policy_file
    if policy is None:
        deployed_cfg = compose(*config)
        policy = str(ArtifactStore(deployed_cfg.paths.artifact_dir).require(
            "train_ppo", keys.control_policy_key(deployed_cfg)).file("policy.msgpack"))
    change = change_overrides(args.change, config)
    if args.trajectory is not None:
        task, score = [f"control.trajectory={args.trajectory}"], tracking_scores
    else:
        goals = held_out_goals_mm(policy, args.goals, config)
        task = [f"control.goals={json.dumps(goals)}", f"control.hold_s={args.hold_s}"]
        score = final_distances
    results: dict[str, list[float]] = {}
    for session in args.sessions:
        common = [*config, *change, f"control.arm_seed={session}"]
        arms, seed = {}, None
        for mechanism in () if args.deployed_only else ("none", args.mechanism):
            adapted = run(compose("stage=adapt", f"control.policy_file={policy}", *common,
                                  f"adapt.mechanism={mechanism}",
                                  f"adapt.policy_timesteps={args.policy_timesteps}"))["adapt"]
            summary = adapted.manifest["summary"]
            print(f"session {session} adapt mechanism={mechanism}: "
                  f"{json.dumps(summary['open_loop_mm'])}, build {adapted.manifest['build_seconds']} s")
            arms[f"adapted_{mechanism}"] = score(
                [*common, *task, f"control.policy_file={adapted.file('policy.msgpack')}"])
            seed = summary["policy_seed"]
        arms["deployed"] = score([*common, *task, f"control.policy_file={policy}",
                                  *([] if seed is None else [f"control.seed={seed}"])])
        for name, values in arms.items():
            if args.trajectory is not None:
                print(f"session {session} {name}: RMSE {values[0]:.2f} mm, lag {values[1]:.2f} "
                      f"s, commands on the limits {100 * values[2]:.0f} %, rest "
                      f"{np.round(values[3:], 2).tolist()} mm")
                results.setdefault(name, []).append(float(values[0]))
            else:
                print(f"session {session} {name}: {stats(values)} {np.round(values, 2)}")
                results.setdefault(name, []).extend(values.tolist())
    for name, values in results.items():
        if args.trajectory is not None:
            print(f"all sessions ({args.change}) {name}: median RMSE "
                  f"{np.median(values):.2f} mm, sessions {min(values):.2f} .. {max(values):.2f} "
                  f"mm, {len(values)} sessions")
        else:
            print(f"all sessions ({args.change}) {name}: {stats(np.asarray(values))}")


if __name__ == "__main__":
    main()
