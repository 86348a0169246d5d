"""Stage ``collect``: drive the configured robot with the exploration walk, record raw streams.

- ``robot=sim``: ``robot.num_runs`` sessions of the simulated arm (each with its own rest pose),
  all simulated at once with ``vmap``.
- ``robot=sorolex_csv`` / ``robot=plotjuggler_csv`` / ``robot=rosbag``: recorded real runs are
  imported instead.
- ``robot=ros2``: the real arm (or its digital twin) over ROS 2 (``pipeline.ros2``). An
  interrupted recording (Ctrl-C, SIGTERM, mocap watchdog, error) still becomes an artifact, its
  last run marked incomplete, and then ``collect`` fails with :class:`CollectionInterrupted`.
  A later ``collect`` with the same config sets such an artifact aside (renamed
  ``<key>.incomplete-<time>``) and records anew, unless ``robot.reuse_incomplete=true``.

Artifact: ``commands.parquet``, ``mocap.parquet``, ``runs.parquet`` and figures of the exploration
(several alpha values, paper Fig. 4) and of the recorded trajectories.
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import sim_arm
from pipeline.artifacts import Artifact, ArtifactStore, ArtifactWriter, artifact_key, produce
from pipeline.config import RobotKind
from pipeline.exploration import exploration_run, plot_walks
from pipeline.importers import READERS, list_recordings, recording_digest, recording_id
from pipeline.safety import validate_limits
from pipeline.schemas import CMD_COLUMNS, COMMANDS, MOCAP, RUNS, XYZ, write_table

log = logging.getLogger(__name__)
STAGE = "collect"
_IMPORT_KINDS = (RobotKind.sorolex_csv, RobotKind.plotjuggler_csv, RobotKind.rosbag)


# How a ROS 2 session runs, not what it records: kept out of the key (so that, e.g.,
# robot.reuse_incomplete=true finds the interrupted artifact it is meant to reuse).
_ROS2_OPERATIONAL = ("node_name", "domain_id", "startup_timeout_s", "flush_every_s",
                     "stop_timeout_s", "reuse_incomplete")


class CollectionInterrupted(RuntimeError):
    """A recording was cut short; what was recorded is in an artifact, marked incomplete."""


def collect_spec(cfg: Any) -> tuple[dict[str, Any], dict[str, str]]:
    """What determines the raw data: the robot and, where it is driven, the exploration."""
    robot = OmegaConf.to_container(cfg.robot, resolve=True)
    kind = RobotKind(cfg.robot.kind)
    if kind in _IMPORT_KINDS:
        # Imported data is keyed by its content, not by where it lies.
        for where in ("data_dir", "pattern", "files"):
            robot.pop(where, None)
        files = {p.name: recording_digest(p) for p in list_recordings(cfg.robot)}
        return {"robot": robot, "files": files}, {}
    if kind is RobotKind.ros2:
        for setting in _ROS2_OPERATIONAL:
            robot.pop(setting, None)
    exploration = OmegaConf.to_container(cfg.exploration, resolve=True)
    return {"robot": robot, "exploration": exploration}, {}


def collect_key(cfg: Any) -> str:
    return artifact_key(*collect_spec(cfg))


def collect(cfg: Any) -> Artifact:
    validate_limits(cfg.robot.limits, cfg.robot.n_valves)
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = collect_spec(cfg)
    kind = RobotKind(cfg.robot.kind)
    if kind is RobotKind.sim:
        build = lambda writer: _collect_sim(cfg, writer, spec)  # noqa: E731
    elif kind in _IMPORT_KINDS:
        build = lambda writer: _import_recordings(cfg, writer, spec)  # noqa: E731
    else:
        return _collect_ros2(cfg, store, spec, inputs)
    return produce(store, STAGE, spec, inputs, build, force=cfg.force)


def _collect_ros2(cfg: Any, store: ArtifactStore, spec: dict[str, Any],
                  inputs: dict[str, str]) -> Artifact:
    from pipeline.ros2 import collect_ros2  # optional extra: imported only for robot=ros2

    _set_aside_incomplete(store, artifact_key(spec, inputs), bool(cfg.robot.reuse_incomplete))
    interruptions = []

    def build(writer: ArtifactWriter) -> None:
        interruptions.append(collect_ros2(cfg, writer, spec))

    artifact = produce(store, STAGE, spec, inputs, build, force=cfg.force)
    interruption = interruptions[0] if interruptions else None
    if interruption is not None:
        raise CollectionInterrupted(
            f"collect interrupted: {interruption.reason}. The preload was commanded. The runs "
            f"recorded so far are in {artifact.path}, the last marked incomplete (align them with "
            f"dataset.align.accept_incomplete=true); the next collect with this config sets them "
            f"aside and records anew unless robot.reuse_incomplete=true") from interruption.error
    return artifact


def _set_aside_incomplete(store: ArtifactStore, key: str, reuse: bool) -> None:
    """Rename an interrupted artifact of ``key`` out of the way, so it is never reused silently.

    Its data stays on disk (``<key>.incomplete-<created>``), it just no longer answers to the key.
    """
    with store.lock(STAGE, key):
        existing = store.find(STAGE, key)
        if existing is None or not existing.manifest.get("summary", {}).get("incomplete_runs"):
            return
        if reuse:
            log.warning("collect: reusing the INCOMPLETE artifact %s (robot.reuse_incomplete=true)",
                        existing.path)
            return
        stamp = _dt.datetime.fromisoformat(existing.manifest["created"]).strftime("%Y%m%dT%H%M%S")
        aside = existing.path.with_name(f"{key}.incomplete-{stamp}")
        os.rename(existing.path, aside)
        log.warning("collect: the artifact for this config is incomplete (interrupted); moved it to "
                    "%s and recording anew (robot.reuse_incomplete=true would reuse it)", aside)


def _collect_sim(cfg: Any, writer: ArtifactWriter, spec: dict[str, Any]) -> None:
    robot, exploration = cfg.robot, cfg.exploration
    params = sim_arm.SimParams.from_config(robot)
    preload = np.full(robot.n_valves, float(robot.limits.preload))
    walk_key, session_key, figure_key = jax.random.split(
        jax.random.key(int(exploration.seed)), 3)
    walk_keys = jax.random.split(walk_key, robot.num_runs)
    commands = np.stack([exploration_run(k, exploration, robot.limits, robot.n_valves)
                         for k in walk_keys])  # [runs, N, valves]
    frame_command = sim_arm.frame_command_index(commands.shape[1], robot.control_hz,
                                                params.mocap_hz)
    simulate = jax.jit(jax.vmap(sim_arm.simulate_run, in_axes=(None, 0, 0, None, None)))
    recorded = jax.device_get(simulate(params, jax.random.split(session_key, robot.num_runs),
                                       commands, frame_command, preload))

    run_ids = [f"sim-{i:03d}" for i in range(robot.num_runs)]
    command_t = np.arange(commands.shape[1]) / float(robot.control_hz)
    commands_df = pd.concat([
        pd.DataFrame({"run_id": rid, "t": command_t,
                      **{c: commands[i, :, j] for j, c in enumerate(CMD_COLUMNS)}})
        for i, rid in enumerate(run_ids)], ignore_index=True)
    mocap_df = pd.concat([
        pd.DataFrame({"run_id": rid, "t": recorded["t"][i],
                      **{a: recorded["position"][i, :, k] for k, a in enumerate(XYZ)},
                      "valid": recorded["valid"][i]})
        for i, rid in enumerate(run_ids)], ignore_index=True)
    runs_df = pd.DataFrame({"run_id": run_ids, "source": "sim", "complete": True,
                            "n_commands": commands.shape[1],
                            "n_frames": len(frame_command)})
    write_raw(writer, cfg, spec, commands_df, mocap_df, runs_df)
    plot_walks(writer.file("figures/exploration_alphas.png"), figure_key, exploration,
               robot.limits, robot.control_hz, robot.n_valves)
    writer.summary["true_position_range_mm"] = {
        a: [float(np.nanmin(recorded["true_position"][..., k]) * 1e3),
            float(np.nanmax(recorded["true_position"][..., k]) * 1e3)] for k, a in enumerate(XYZ)}


def _import_recordings(cfg: Any, writer: ArtifactWriter, spec: dict[str, Any]) -> None:
    read = READERS[RobotKind(cfg.robot.kind).value]
    commands, mocap, runs = [], [], []
    for path in list_recordings(cfg.robot):
        run_commands, run_mocap = read(path, cfg.robot)
        commands.append(run_commands)
        mocap.append(run_mocap)
        runs.append({"run_id": recording_id(path), "source": path.name, "complete": True,
                     "n_commands": len(run_commands), "n_frames": len(run_mocap)})
        log.info("collect: imported %s (%d commands, %d frames)", path.name, len(run_commands),
                 len(run_mocap))
    write_raw(writer, cfg, spec, pd.concat(commands, ignore_index=True),
              pd.concat(mocap, ignore_index=True), pd.DataFrame(runs))


def write_raw(writer: ArtifactWriter, cfg: Any, spec: dict[str, Any], commands: pd.DataFrame,
               mocap: pd.DataFrame, runs: pd.DataFrame) -> None:
    provenance = {"stage": STAGE, "robot": cfg.robot.name}
    write_table(commands, writer.file("commands.parquet"), COMMANDS, spec, provenance)
    write_table(mocap, writer.file("mocap.parquet"), MOCAP, spec, provenance)
    write_table(runs, writer.file("runs.parquet"), RUNS, spec, provenance)
    plot_runs(writer.file("figures/runs.png"), commands, mocap)
    writer.summary = {
        "runs": len(runs), "commands": len(commands), "frames": len(mocap),
        "dropped_frames": int((~mocap["valid"]).sum()),
        "incomplete_runs": runs.loc[~runs["complete"], "run_id"].tolist(),
    }
    log.info("collect: %d runs, %d commands, %d mocap frames (%d dropped)", len(runs),
             len(commands), len(mocap), writer.summary["dropped_frames"])


def plot_runs(path: Path, commands: pd.DataFrame, mocap: pd.DataFrame) -> Path:
    """Commands and positions of the first run over time, and every run's x-z footprint."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = commands["run_id"].iloc[0]
    cmd = commands[commands["run_id"] == first]
    pos = mocap[mocap["run_id"] == first]
    t0 = cmd["t"].iloc[0]
    fig = plt.figure(figsize=(12, 6.5))
    grid = fig.add_gridspec(4, 2, width_ratios=[2.2, 1])
    ax = fig.add_subplot(grid[0, 0])
    for j, column in enumerate(CMD_COLUMNS):
        ax.step(cmd["t"] - t0, cmd[column], where="post", lw=0.9, label=f"valve {j}")
    ax.set_ylabel("p_cmd [kPa]")
    ax.legend(fontsize=7, ncol=3, loc="upper right")
    ax.set_title(f"run {first}: commands and motion capture", fontsize=10)
    for k, axis in enumerate(XYZ):
        ax_k = fig.add_subplot(grid[k + 1, 0], sharex=ax)
        ax_k.plot(pos["t"] - t0, pos[axis] * 1e3, lw=0.6, color=f"C{k + 3}")
        ax_k.set_ylabel(f"{axis} [mm]")
    ax_k.set_xlabel("time [s]")
    ax_xz = fig.add_subplot(grid[:, 1])
    for i, (run_id, run) in enumerate(mocap.groupby("run_id", sort=False)):
        ax_xz.plot(run["x"] * 1e3, run["z"] * 1e3, lw=0.3, alpha=0.7, color=f"C{i % 10}",
                   label=str(run_id))
        ax_xz.plot(run["x"].iloc[:20].mean() * 1e3, run["z"].iloc[:20].mean() * 1e3, "k+", ms=8)
    ax_xz.set_xlabel("x [mm]")
    ax_xz.set_ylabel("z [mm]")
    ax_xz.set_aspect("equal", adjustable="datalim")
    ax_xz.set_title("footprint of every run (+: rest pose)", fontsize=10)
    ax_xz.legend(fontsize=6, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
