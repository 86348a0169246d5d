"""Control-loop latency: compute per period for both policy types, and pose age at command time.

    python -m bench control_latency
    python -m bench.control_latency [--periods 200] [--policy-file ff=PATH --policy-file rnn=PATH]
    python -m bench.control_latency --ros [...]   # against a running digital twin (robot=ros2)

Compute latency is wall time from the pose taken to the command published, as the loop records
it (``latency_ms`` in ``periods.parquet``): the observation, the policy's deterministic action
with its carry, the action mapping (one jitted call) and the command gate. By default the
policies are freshly initialized networks of the default agent sizes (latency does not depend on
the weights) and the loop runs on the in-process simulated arm in simulated time, where the pose
age is only the mocap frame's (10 ms); with ``--ros`` it runs over ROS 2 in real time
(``robot=ros2 robot.rehearsal=true``; start ``python -m pipeline stage=twin robot=ros2`` first),
where the pose age includes the transport and the wait for the next period. It never drives a
real arm: over ROS 2 it runs as a rehearsal, on the twin's ROS domain, and starts only when the
arm side answers as a twin (a guard's answer is refused).
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.config import compose, register_configs
from pipeline.control.results import latency_summary
from pipeline.stages.control import control, load_deployment

POLICIES = {"ppo_ff": "ff", "ppo_rnn": "rnn"}


def _compose(output_dir: Path, *overrides: str):
    return compose(f"paths.output_dir={output_dir}", *overrides)


def measure(policy: str, periods: int, policy_file: str | None, ros: bool, out: Path
            ) -> dict[str, float]:
    from tests.control_fixtures import goals_mm, write_policy

    sim = ["env=sim", "env.num_goals=64", "env.reset_bank_size=2", "agent.num_seeds=1",
           f"control.policy={policy}", "stage=control"]
    cfg = _compose(out / "sim", *sim)
    if policy_file is None:
        artifact, train_params = write_policy(cfg, medians_mm=(2.0,))
        policy_file = str(artifact.file("policy.msgpack"))
        goals = goals_mm(train_params, 5)
    else:
        goals = None
    run_cfg = _compose(out / ("ros" if ros else "sim"), "stage=control",
                       f"control.policy_file={policy_file}",
                       *(["robot=ros2", "robot.rehearsal=true"] if ros else []))
    if goals is None:  # a trained policy: goals from its own workspace
        from pipeline.infra.artifacts import ArtifactStore

        deployment = load_deployment(run_cfg, ArtifactStore(run_cfg.paths.artifact_dir))
        goal_set = np.asarray(deployment.env_params.goal_set)
        goals = np.round(goal_set[:: max(1, len(goal_set) // 5)][:5] * 1e3, 2).tolist()
    run_cfg.control.goals = goals
    run_cfg.control.hold_s = periods / len(goals) / float(run_cfg.robot.control_hz)
    artifact = control(run_cfg)
    table = pd.read_parquet(artifact.file("periods.parquet"))
    summary = latency_summary(table)
    return {"policy": policy, "periods": int((table["goal_index"] >= 0).sum()),
            "compute_p50_ms": summary["compute_latency_ms"]["p50"],
            "compute_p99_ms": summary["compute_latency_ms"]["p99"],
            "compute_max_ms": summary["compute_latency_ms"]["max"],
            "cpu_p50_ms": summary["compute_cpu_ms"]["p50"],
            "cpu_p99_ms": summary["compute_cpu_ms"]["p99"],
            "pose_age_p50_ms": summary["pose_age_ms"]["p50"],
            "pose_age_p99_ms": summary["pose_age_ms"]["p99"]}


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--periods", type=int, default=200)
    parser.add_argument("--policy-file", action="append", default=[],
                        help="ff=PATH or rnn=PATH: a trained policy.msgpack instead of a random one")
    parser.add_argument("--ros", action="store_true", help="over ROS 2 (a twin must be running)")
    args = parser.parse_args(argv)
    files = dict(item.split("=", 1) for item in args.policy_file)
    logging.basicConfig(level=logging.WARNING)
    register_configs()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for policy, short in POLICIES.items():
            rows.append(measure(policy, args.periods, files.get(short), args.ros, Path(tmp)))
    frame = pd.DataFrame(rows)
    where = "ROS 2 (real time)" if args.ros else "the simulated arm (simulated time)"
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"control loop on {where}; compute: wall ms, cpu: CPU ms of this process in the same "
          f"span, pose age: arm ms; {os.cpu_count()} CPUs, load average {load} (other processes "
          f"share the cores: wall times grow with it)")
    print(frame.to_string(index=False, float_format=lambda v: f"{v:.2f}"))


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
