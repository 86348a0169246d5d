"""The ROS 2 path end to end: the digital twin and collect as separate rclpy processes.

Each test runs ``python -m pipeline stage=twin`` and ``python -m pipeline stage=collect
robot=ros2`` with the arm's time 4x faster than the wall clock, on its own ROS_DOMAIN_ID and with
discovery limited to localhost, so parallel tests (pytest -n 2) never hear each other.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.arm.exploration import exploration_plan
from pipeline.data.schemas import CMD_COLUMNS, DataError
from pipeline.infra.artifacts import ArtifactStore
from pipeline.keys import key
from pipeline.stages.align import align
from pipeline.stages.collect import STAGE
from tests.conftest import compose_config
from tests.ros_required import require_ros

require_ros("rclpy")
pytestmark = pytest.mark.ros

TIME_SCALE = 4.0
LIMITS = {"p_min": 0.0, "p_max": 4.5, "sum_max": 10.0, "preload": 2.0}  # the walk hits p_max
OVERRIDES = [
    "robot=ros2", "robot.rehearsal=true", f"robot.time_scale={TIME_SCALE}", "robot.watchdog_s=4.0",
    "robot.stop_timeout_s=0.5", "robot.flush_every_s=0.5", "robot.startup_timeout_s=60",
    "exploration.pad_steps=2",
    *(f"robot.limits.{k}={v}" for k, v in LIMITS.items()),
]
class Pipeline:
    """Starts pipeline stages as subprocesses in one ROS domain, writing under ``tmp_path``."""

    def __init__(self, tmp_path: Path, domain: int, *overrides: str):
        self.out = tmp_path / "outputs"
        self.overrides = [*OVERRIDES, *overrides]
        self.domain = domain  # the twin's (rehearsal) domain and the arm's
        self.env = {**os.environ, "ROS_DOMAIN_ID": str(domain),
                    "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "HYDRA_FULL_ERROR": "1"}
        self.logs = tmp_path

    def start(self, stage: str, *overrides: str, name: str | None = None) -> subprocess.Popen:
        """``stage`` as a process, its output in ``<name or stage>.log``."""
        with open(self.logs / f"{name or stage}.log", "w") as log:  # the child keeps its own
            return subprocess.Popen(
                [sys.executable, "-m", "pipeline", f"stage={stage}",
                 f"paths.output_dir={self.out}", f"robot.rehearsal_domain_id={self.domain}",
                 *self.overrides, *overrides],
                env=self.env, stdout=log, stderr=subprocess.STDOUT)

    def log(self, stage: str) -> str:
        return (self.logs / f"{stage}.log").read_text()

    def wait_for_log(self, stage: str, text: str, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while text not in self.log(stage):
            assert time.monotonic() < deadline, f"no {text!r} in {stage}.log:\n{self.log(stage)}"
            time.sleep(0.05)

    def cfg(self, *overrides: str):
        return compose_config(self.out, *self.overrides, *overrides)

    def start_twin(self, record: Path, max_duration_s: float = 90) -> subprocess.Popen:
        return self.start("twin", f"robot.twin.record_path={record}",
                          f"robot.twin.max_duration_s={max_duration_s}")

    @contextlib.contextmanager
    def twin(self, record: Path, max_duration_s: float = 90) -> Iterator[subprocess.Popen]:
        """The digital twin, recording what it receives to ``record``, for the ``with`` block;
        stopped after it (Ctrl-C), which it must survive with exit code 0."""
        process = self.start_twin(record, max_duration_s)
        try:
            yield process
        except BaseException:
            stop(process)
            raise
        assert stop(process) == 0, self.log("twin")


def stop(process: subprocess.Popen, timeout_s: float = 30.0) -> int:
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    return process.wait(timeout=timeout_s)


def received(record: Path) -> pd.DataFrame:
    """The commands the twin received on the wire (its JSON-lines record, deadman lines aside)."""
    rows = [row for line in record.read_text().splitlines()
            if not (row := json.loads(line)).get("deadman")]
    return pd.DataFrame({"receipt_ns": [r["receipt_ns"] for r in rows],
                         **{c: [r["pressures"][j] for r in rows]
                            for j, c in enumerate(CMD_COLUMNS)}})


def assert_within_limits(pressures: np.ndarray) -> None:
    assert np.isfinite(pressures).all()
    assert pressures.min() >= LIMITS["p_min"]
    assert pressures.max() <= LIMITS["p_max"]
    assert pressures.sum(axis=1).max() <= LIMITS["sum_max"]


# two processes over ROS 2; fast: collect's loop on a fake link (test_ros2_faults.py)
@pytest.mark.slow
def test_twin_collect_align_end_to_end(tmp_path, ros_domain):
    pipe = Pipeline(tmp_path, ros_domain, "exploration.num_steps=8")
    record = tmp_path / "twin_received.jsonl"
    with pipe.twin(record):
        collect = pipe.start("collect")
        assert collect.wait(timeout=120) == 0, pipe.log("collect")

    cfg = pipe.cfg()
    artifact = ArtifactStore(cfg.paths.artifact_dir).require(STAGE, key("collect", cfg))
    commands = pd.read_parquet(artifact.file("commands.parquet"))
    mocap = pd.read_parquet(artifact.file("mocap.parquet"))
    runs = pd.read_parquet(artifact.file("runs.parquet"))
    summary = artifact.manifest["summary"]

    # the commands: the exploration walk, projected onto the limits, at 2 Hz of the arm's time
    (planned,) = exploration_plan(cfg.exploration, cfg.robot.limits, cfg.robot.n_valves,
                                  cfg.robot.num_runs).commands
    run_id = "ros2-000"
    assert runs.to_dict("records") == [{
        "run_id": run_id, "source": f"{cfg.robot.pose_topic} [sorolearn_twin]", "complete": True,
        "n_commands": len(planned), "n_frames": len(mocap)}]
    np.testing.assert_allclose(commands[CMD_COLUMNS], planned, atol=1e-6)
    assert np.isclose(planned, LIMITS["p_max"], atol=1e-6).any()  # the limit was reached
    # on schedule, give or take the scheduling delays of a busy machine (0.4 s arm = 100 ms wall)
    lateness = commands["t"] - np.arange(len(planned)) * 0.5
    assert lateness.abs().max() < 1.0 and lateness.abs().median() < 0.05

    # the poses: header stamps at 100 Hz of the arm's time, the twin's few dropped frames aside
    duration = len(planned) * 0.5
    dt = np.diff(mocap["t"])
    assert np.median(dt) == pytest.approx(0.01, abs=1e-3)
    assert (dt > 0).all() and dt.max() < 0.5
    assert 0.9 * duration * 100 <= len(mocap) <= duration * 100 + 1
    assert mocap[["x", "y", "z"]].notna().all().all() and mocap["valid"].all()
    assert abs(mocap["y"].mean() - 0.353) < 0.01  # the simulated arm's markers hang near y = 353 mm
    assert summary["ros2"]["pose_receipt_rate_hz_wall"] == pytest.approx(100 * TIME_SCALE, rel=0.4)

    # on the wire: every command the twin received, in order, within the limits, then the preload
    wire = received(record)
    pressures = wire[CMD_COLUMNS].to_numpy()
    assert_within_limits(pressures)
    np.testing.assert_allclose(pressures[:len(planned)], planned, atol=1e-6)
    np.testing.assert_allclose(pressures[len(planned):], [[LIMITS["preload"]] * 3])

    # align: every command matched to a mocap frame
    aligned = align(cfg)
    report = pd.read_parquet(aligned.file("align_report.parquet"))
    assert report.loc[0, "matched"] == len(planned) and report.loc[0, "unmatched"] == 0


def _interrupted_collect(pipe: Pipeline, interrupt) -> tuple[int, str]:
    """Start collect, let it record a few commands, ``interrupt(collect)``; exit code and log."""
    collect = pipe.start("collect")
    try:
        pipe.wait_for_log("collect", "run ros2-000 started")
        time.sleep(1.0)  # 4 s of the arm's time: 8 commands
        interrupt(collect)
        code = collect.wait(timeout=60)
    finally:
        if collect.poll() is None:
            collect.kill()
    return code, pipe.log("collect")


def _partial_artifact(pipe: Pipeline):
    """The collect artifact of this config: one run, cut short, every chunk in it."""
    cfg = pipe.cfg()
    artifact = ArtifactStore(cfg.paths.artifact_dir).require(STAGE, key("collect", cfg))
    runs = pd.read_parquet(artifact.file("runs.parquet"))
    commands = pd.read_parquet(artifact.file("commands.parquet"))
    assert not runs.loc[0, "complete"]
    assert 4 <= len(commands) < 44 and runs.loc[0, "n_frames"] > 100
    assert artifact.manifest["summary"]["incomplete_runs"] == ["ros2-000"]
    assert not list((pipe.out / "recovery").glob("*/*"))  # the artifact holds every chunk
    return artifact, commands


@pytest.mark.slow  # two processes; fast: collect on a stop signal and a stall (test_ros2_faults.py)
def test_sigint_and_watchdog_stop_collect_safely_and_keep_the_data(tmp_path, ros_domain):
    """One twin, two interrupted collects with the same config: Ctrl-C, then the twin dies."""
    pipe = Pipeline(tmp_path, ros_domain, "exploration.num_steps=40")
    record = tmp_path / "twin_received.jsonl"
    twin = pipe.start_twin(record)
    try:
        # ---- 1. SIGINT: the preload goes out on the wire, the partial data is kept -------------
        code, log = _interrupted_collect(pipe, lambda c: c.send_signal(signal.SIGINT))
        assert code != 0, log
        assert "SIGINT received: stopping safely" in log
        assert "CollectionInterrupted: collect interrupted: SIGINT received" in log
        assert "marked incomplete" in log
        first, commands = _partial_artifact(pipe)
        time.sleep(0.2)  # the twin writes what it received as it arrives
        wire = received(record)[CMD_COLUMNS].to_numpy()
        assert_within_limits(wire)
        assert len(wire) == len(commands) + 1
        np.testing.assert_allclose(wire[:-1], commands[CMD_COLUMNS], atol=1e-9)
        np.testing.assert_allclose(wire[-1], [LIMITS["preload"]] * 3)

        # ---- 2. same config again: the incomplete artifact is set aside, not reused; then the
        # twin dies mid-run: the watchdog stops collect, which again keeps what it recorded -----
        code, log = _interrupted_collect(pipe, lambda _: twin.kill())
    finally:
        if twin.poll() is None:
            twin.kill()
        twin.wait(timeout=30)
    assert code != 0, log
    assert "the artifact for this config is incomplete (interrupted); moved it to" in log
    (aside,) = first.path.parent.glob(f"{first.key}.incomplete-*")
    pd.testing.assert_frame_equal(pd.read_parquet(aside / "commands.parquet"), commands)
    assert "mocap watchdog: no pose on /mocap_rigid_bodies/rigid_bodies_1/pose" in log
    assert "commanded the preload [2.0, 2.0, 2.0] kPa" in log
    assert "CollectionInterrupted: collect interrupted: mocap watchdog" in log
    _partial_artifact(pipe)
    assert_within_limits(received(record)[CMD_COLUMNS].to_numpy())

    # ---- align refuses the interrupted run unless told to accept it ----------------------------
    with pytest.raises(DataError, match="interrupted"):
        align(pipe.cfg())
    accepted = align(pipe.cfg("dataset.align.accept_incomplete=true"))
    assert pd.read_parquet(accepted.file("aligned.parquet"))["matched"].sum() >= 4
