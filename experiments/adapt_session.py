"""The deployed policy against its session-adapted versions on simulated sessions whose physics
differ from the training runs'.

For each session (a physics change of the simulated arm and ``control.arm_seed``): ``stage=adapt``
with ``adapt.mechanism=none`` (the policy fine-tuned in the deployed model: what the extra training
alone gives) and with the calibrated model (``adapt.mechanism``), then ``stage=control`` on the
same session and goals with the deployed policy (the seed the fine-tunes start from) and with each
adapted one. Prints per session and over all sessions the median final distance, the share of
goals within 1 mm and the p90, and the adapt step's wall time.

    python experiments/adapt_session.py [--sessions 11 12] [--goals 8] [--hold-s 20]

Runs on the default chain's deployed policy (``control.policy``; ``python -m pipeline
stage=train_ppo`` first).
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


def held_out_goals_mm(policy_file: str, count: int) -> list[list[float]]:
    """``count`` goals spread over the deployed policy's held-out goals, in mm."""
    cfg = compose(f"control.policy_file={policy_file}")
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


def stats(distances: np.ndarray) -> dict[str, float]:
    return {"median_mm": round(float(np.median(distances)), 3),
            "within_1mm": round(float(np.mean(distances < 1.0)), 3),
            "p90_mm": round(float(np.percentile(distances, 90)), 3), "goals": len(distances)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--change", choices=sorted(CHANGES), default="gains")
    parser.add_argument("--sessions", type=int, nargs="+", default=[11, 12])
    parser.add_argument("--goals", type=int, default=8)
    parser.add_argument("--hold-s", type=float, default=20.0)
    parser.add_argument("--mechanism", default="fine_tune")
    parser.add_argument("--policy-timesteps", type=int, default=131072)
    args = parser.parse_args()
    deployed_cfg = compose()
    deployed = ArtifactStore(deployed_cfg.paths.artifact_dir).require(
        "train_ppo", keys.control_policy_key(deployed_cfg))
    policy = str(deployed.file("policy.msgpack"))
    goals = held_out_goals_mm(policy, args.goals)
    results: dict[str, list[float]] = {}
    for session in args.sessions:
        common = [*CHANGES[args.change], f"control.arm_seed={session}"]
        control = [*common, f"control.goals={json.dumps(goals)}", f"control.hold_s={args.hold_s}"]
        arms = {}
        for mechanism in ("none", args.mechanism):
            adapted = run(compose("stage=adapt", f"control.policy_file={policy}", *common,
                                  f"adapt.mechanism={mechanism}",
                                  f"adapt.policy_timesteps={args.policy_timesteps}"))["adapt"]
            summary = adapted.manifest["summary"]
            print(f"session {session} adapt mechanism={mechanism}: "
                  f"{json.dumps(summary['open_loop_mm'])}, build {adapted.manifest['build_seconds']} s")
            arms[f"adapted_{mechanism}"] = final_distances(
                [*control, f"control.policy_file={adapted.file('policy.msgpack')}"])
            seed = summary["policy_seed"]
        arms["deployed"] = final_distances([*control, f"control.policy_file={policy}",
                                            f"control.seed={seed}"])
        for name, distances in arms.items():
            print(f"session {session} {name}: {stats(distances)} {np.round(distances, 2)}")
            results.setdefault(name, []).extend(distances.tolist())
    for name, distances in results.items():
        print(f"all sessions ({args.change}) {name}: {stats(np.asarray(distances))}")


if __name__ == "__main__":
    main()
