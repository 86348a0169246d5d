"""Rates and latencies of the ROS 2 link between the digital twin and collect.

Starts ``python -m pipeline stage=twin`` and ``python -m pipeline stage=collect robot=ros2`` as
two processes (localhost only, their own ROS domain), then prints, from collect's artifact and
the twin's record of what it received:

- command publish -> twin receipt latency [ms] (collect's publish stamp vs the twin's receipt
  stamp, both on this machine's clock),
- how late collect published each command against its schedule [ms],
- the pose rate collect received (wall Hz) and the jitter of the intervals [ms],
- pose latency: twin header stamp -> collect receipt [ms] (includes the twin running late),
- the pose rate in the recorded data (arm Hz, from the header stamps).

Usage (about 10 s of arm time plus ~15 s of start-up)::

    .venv/bin/python -m experiments.ros2_link                    # real time, 20 steps
    .venv/bin/python -m experiments.ros2_link --time-scale 4 --steps 40
    .venv/bin/python -m experiments.ros2_link --mocap-faults     # with simulated dropouts
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parent.parent


def run_link(out: Path, time_scale: float, steps: int, domain: int, mocap_faults: bool
             ) -> tuple[Path, Path]:
    """Run twin + collect once; return the collect artifact folder and the twin's record."""
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    common = ["robot=ros2", "robot.rehearsal=true", f"robot.rehearsal_domain_id={domain}",
              f"robot.time_scale={time_scale}", f"paths.output_dir={out}",
              f"exploration.num_steps={steps}", "robot.startup_timeout_s=60"]
    if not mocap_faults:  # measure the link, not the simulated mocap's dropouts and stamp jitter
        common += ["robot.twin.mocap.drop_prob=0", "robot.twin.mocap.burst_prob=0",
                   "robot.twin.mocap.jitter_std_s=0"]
    record = out / "twin_received.jsonl"
    pipeline = [sys.executable, "-m", "pipeline"]
    with open(out / "twin.log", "w") as twin_log:
        twin = subprocess.Popen([*pipeline, "stage=twin", *common,
                                 f"robot.twin.record_path={record}",
                                 "robot.twin.max_duration_s=600"],
                                cwd=ROOT, env=env, stdout=twin_log, stderr=subprocess.STDOUT)
    try:
        with open(out / "collect.log", "w") as collect_log:
            subprocess.run([*pipeline, "stage=collect", *common], cwd=ROOT, env=env, check=True,
                           stdout=collect_log, stderr=subprocess.STDOUT)
    finally:
        twin.send_signal(signal.SIGINT)
        twin.wait(timeout=60)
    (manifest,) = (out / "artifacts" / "collect").glob("*/artifact.json")
    return manifest.parent, record


def describe(values: np.ndarray) -> str:
    return (f"median {np.median(values):7.3f}  p95 {np.percentile(values, 95):7.3f}  "
            f"p99 {np.percentile(values, 99):7.3f}  max {values.max():7.3f}  (n={len(values)})")


def report(artifact: Path, record: Path) -> None:
    summary = json.loads((artifact / "artifact.json").read_text())["summary"]
    link = summary["ros2"]
    scale = link["time_scale"]
    commands = pd.read_parquet(artifact / "commands.parquet")
    mocap = pd.read_parquet(artifact / "mocap.parquet")
    (run,) = link["runs"]
    published_ns = run["start_ns"] + np.round(commands["t"].to_numpy() / scale * 1e9)
    receipts = np.array([json.loads(line)["receipt_ns"]
                         for line in record.read_text().splitlines()], np.float64)
    latency_ms = (receipts[:len(published_ns)] - published_ns) / 1e6
    intervals = link["pose_receipt_interval_ms"]
    lateness = link["command_lateness_ms"]
    pose_latency = link["pose_latency_ms"]
    print(f"time_scale {scale:g} (arm s per wall s); {len(commands)} commands, "
          f"{len(mocap)} poses recorded")
    print(f"command publish -> twin receipt [ms]   {describe(latency_ms)}")
    print(f"command publish lateness [ms]          median {lateness['median']:7.3f}  "
          f"p99 {lateness['p99']:7.3f}  max {lateness['max']:7.3f}")
    print(f"pose rate received by collect [Hz wall] {link['pose_receipt_rate_hz_wall']:.1f} "
          f"(expected {100 * scale:g})")
    print(f"pose receipt interval [ms wall]        mean {intervals['mean']:7.3f}  "
          f"std {intervals['std']:7.3f}  p99 {intervals['p99']:7.3f}  max {intervals['max']:7.3f}")
    print(f"pose stamp -> collect receipt [ms]     median {pose_latency['median']:7.3f}  "
          f"p99 {pose_latency['p99']:7.3f}  max {pose_latency['max']:7.3f}")
    dt = np.diff(mocap["t"].to_numpy())
    print(f"pose rate in the data [Hz arm]          {1 / np.median(dt):.1f} "
          f"(median interval {np.median(dt) * 1e3:.2f} ms, std {dt.std() * 1e3:.2f} ms)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--time-scale", type=float, default=1.0)
    parser.add_argument("--steps", type=int, default=20, help="exploration.num_steps")
    parser.add_argument("--domain", type=int, default=77, help="ROS_DOMAIN_ID to use")
    parser.add_argument("--out", type=Path, help="output folder (default: a temporary one)")
    parser.add_argument("--mocap-faults", action="store_true",
                        help="keep the twin's dropped frames and stamp jitter")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        report(*run_link(out, args.time_scale, args.steps, args.domain, args.mocap_faults))


if __name__ == "__main__":
    main()
