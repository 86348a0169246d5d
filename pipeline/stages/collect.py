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

import logging
from typing import Any

import jax
import numpy as np
import pandas as pd

from pipeline import keys
from pipeline.arm import sim_arm
from pipeline.arm.exploration import exploration_plan, plot_walks
from pipeline.arm.safety import validate_limits
from pipeline.config import RobotKind
from pipeline.data.importers import READERS, list_recordings, recording_id
from pipeline.data.raw import CollectionInterrupted, write_raw
from pipeline.data.schemas import CMD_COLUMNS, XYZ
from pipeline.infra.artifacts import Artifact, ArtifactStore, ArtifactWriter, artifact_key, produce

log = logging.getLogger(__name__)
STAGE = "collect"


def collect(cfg: Any) -> Artifact:
    validate_limits(cfg.robot.limits, cfg.robot.n_valves)
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.collect_spec(cfg)
    kind = RobotKind(cfg.robot.kind)
    if kind is RobotKind.sim:
        build = lambda writer: _collect_sim(cfg, writer, spec)  # noqa: E731
    elif kind in keys.IMPORT_KINDS:
        build = lambda writer: _import_recordings(cfg, writer, spec)  # noqa: E731
    else:
        return _collect_ros2(cfg, store, spec, inputs)
    return produce(store, STAGE, spec, inputs, build, force=cfg.force)


def _collect_ros2(cfg: Any, store: ArtifactStore, spec: dict[str, Any],
                  inputs: dict[str, str]) -> Artifact:
    from pipeline.ros2.collector import collect_ros2  # the optional ros extra

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
        aside = store.set_aside(existing, "incomplete")
        log.warning("collect: the artifact for this config is incomplete (interrupted); moved it to "
                    "%s and recording anew (robot.reuse_incomplete=true would reuse it)", aside)


def _collect_sim(cfg: Any, writer: ArtifactWriter, spec: dict[str, Any]) -> None:
    robot, exploration = cfg.robot, cfg.exploration
    params = sim_arm.SimParams.from_config(robot)
    preload = np.full(robot.n_valves, float(robot.limits.preload))
    plan = exploration_plan(exploration, robot.limits, robot.n_valves, robot.num_runs)
    commands = plan.commands  # [runs, N, valves]
    frame_command = sim_arm.frame_command_index(commands.shape[1], robot.control_hz,
                                                params.mocap_hz)
    simulate = jax.jit(jax.vmap(sim_arm.simulate_run, in_axes=(None, 0, 0, None, None)))
    recorded = jax.device_get(simulate(params, jax.random.split(plan.session_key, robot.num_runs),
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
    plot_walks(writer.file("figures/exploration_alphas.png"), plan.figure_key, exploration,
               robot.limits, robot.control_hz, robot.n_valves)
    writer.summary["true_position_range_mm"] = {
        a: [float(np.nanmin(recorded["true_position"][..., k]) * 1e3),
            float(np.nanmax(recorded["true_position"][..., k]) * 1e3)] for k, a in enumerate(XYZ)}


def _import_recordings(cfg: Any, writer: ArtifactWriter, spec: dict[str, Any]) -> None:
    read = READERS[RobotKind(cfg.robot.kind).value]
    commands, mocap, runs, incomplete = [], [], [], {}
    for path in list_recordings(cfg.robot):
        notes: dict[str, Any] = {}
        run_commands, run_mocap = read(path, cfg.robot, notes)
        commands.append(run_commands)
        mocap.append(run_mocap)
        runs.append({"run_id": recording_id(path), "source": path.name, "complete": True,
                     "n_commands": len(run_commands), "n_frames": len(run_mocap)})
        if notes.get("incomplete_last_line"):
            incomplete[recording_id(path)] = int(notes["incomplete_last_line"])
        log.info("collect: imported %s (%d commands, %d frames)", path.name, len(run_commands),
                 len(run_mocap))
    write_raw(writer, cfg, spec, pd.concat(commands, ignore_index=True),
              pd.concat(mocap, ignore_index=True), pd.DataFrame(runs))
    # lines dropped because a file ended inside them (no final newline), per run
    writer.summary["incomplete_lines_dropped"] = incomplete
