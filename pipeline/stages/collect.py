"""Stage ``collect``: drive the configured robot with the exploration walk, record raw streams.

- ``robot=sim``: ``robot.num_runs`` sessions of the simulated arm (each with its own rest pose,
  and its own physics where ``robot.physics.session_std`` spreads them), all simulated at once
  with ``vmap``. With ``robot.replay`` the sessions replay the valve commands of recorded runs
  at their recorded times instead of the exploration walk, one session per recording
  (``robot=sim_sorolex``: the paper's 7 runs).
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
from typing import Any, NamedTuple

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.arm.limits import validate_limits
from pipeline.data.importers import READERS, list_recordings, recording_id
from pipeline.data.raw import CollectionInterrupted, write_raw
from pipeline.data.schemas import CMD_COLUMNS, XYZ
from pipeline.infra.artifacts import Artifact, ArtifactStore, ArtifactWriter, artifact_key, produce
from pipeline.schemas import RobotKind

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


class SimSessions(NamedTuple):
    """What the simulated sessions are driven with: per run ``commands [N_r, valves]`` kPa sent
    at ``times [N_r]`` s and, per mocap frame, the index of the command in force
    (``frame_command [K_r]``, see :func:`pipeline.arm.sim_arm.simulate_run`)."""

    run_ids: list[str]
    sources: list[str]
    commands: list[np.ndarray]
    times: list[np.ndarray]
    frame_command: list[np.ndarray]


def walk_sessions(cfg: Any, mocap_hz: float) -> SimSessions:
    """``robot.num_runs`` exploration walks at ``robot.control_hz``."""
    from pipeline.arm import sim_arm
    from pipeline.arm.exploration import exploration_plan

    robot = cfg.robot
    plan = exploration_plan(cfg.exploration, robot.limits, robot.n_valves, robot.num_runs)
    runs, n = plan.commands.shape[:2]
    frames = sim_arm.frame_command_index(n, robot.control_hz, mocap_hz)
    return SimSessions([f"sim-{i:03d}" for i in range(runs)], ["sim"] * runs,
                       list(plan.commands), [np.arange(n) / float(robot.control_hz)] * runs,
                       [frames] * runs)


def replay_sessions(cfg: Any, mocap_hz: float) -> SimSessions:
    """The valve commands of the recordings of ``robot.replay`` at their recorded times (from
    the recording's first mocap frame), each session as long as its recording."""
    replay = cfg.robot.replay
    read = READERS[RobotKind(replay.kind).value]
    reader_cfg = OmegaConf.create({"limits": OmegaConf.to_container(cfg.robot.limits)})
    sessions = SimSessions([], [], [], [], [])
    for path in list_recordings(replay):
        commands, mocap = read(path, reader_cfg, {})
        start = float(mocap["t"].iloc[0])
        sessions.run_ids.append(f"sim-{recording_id(path)}")
        sessions.sources.append(f"replay:{path.name}")
        sessions.commands.append(commands[CMD_COLUMNS].to_numpy(np.float64))
        times = commands["t"].to_numpy(np.float64) - start
        sessions.times.append(times)
        num_frames = int(np.floor((float(mocap["t"].iloc[-1]) - start) * mocap_hz + 0.5)) + 1
        sessions.frame_command.append(frame_commands(times, num_frames, mocap_hz))
    return sessions


def frame_commands(times: np.ndarray, num_frames: int, mocap_hz: float) -> np.ndarray:
    """Index of the command in force in each mocap frame (frame k starts at ``k / mocap_hz``;
    frames before the first command hold the first)."""
    frame_t = np.arange(num_frames) / mocap_hz
    index = np.searchsorted(np.asarray(times) - 1e-9, frame_t, side="right") - 1
    return np.clip(index, 0, len(times) - 1).astype(np.int32)


def _collect_sim(cfg: Any, writer: ArtifactWriter, spec: dict[str, Any]) -> None:
    # JAX only for the simulated arm: importing recordings, and every stage that reuses this
    # one's artifact, start without it
    import jax

    from pipeline.arm import sim_arm
    from pipeline.arm.exploration import plan_keys, plot_walks

    robot, exploration = cfg.robot, cfg.exploration
    params = sim_arm.SimParams.from_config(robot)
    preload = np.full(robot.n_valves, float(robot.limits.preload))
    _, session_key, figure_key = plan_keys(exploration)
    sessions = (replay_sessions if robot.get("replay") else walk_sessions)(cfg, params.mocap_hz)
    runs = len(sessions.run_ids)
    num_frames = [len(f) for f in sessions.frame_command]
    # padded to the longest session (holding its last command), cut back after simulating
    longest_commands = max(len(c) for c in sessions.commands)
    commands = np.stack([np.concatenate([c, np.repeat(c[-1:], longest_commands - len(c), 0)])
                         for c in sessions.commands])
    frame_command = np.stack([np.pad(f, (0, max(num_frames) - len(f)), mode="edge")
                              for f in sessions.frame_command])
    simulate = jax.jit(jax.vmap(sim_arm.simulate_run, in_axes=(None, 0, 0, 0, None)))
    recorded = jax.device_get(simulate(params, jax.random.split(session_key, runs),
                                       commands, frame_command, preload))

    commands_df = pd.concat([
        pd.DataFrame({"run_id": rid, "t": sessions.times[i],
                      **{c: sessions.commands[i][:, j] for j, c in enumerate(CMD_COLUMNS)}})
        for i, rid in enumerate(sessions.run_ids)], ignore_index=True)
    mocap_df = pd.concat([
        pd.DataFrame({"run_id": rid, "t": recorded["t"][i, :n],
                      **{a: recorded["position"][i, :n, k] for k, a in enumerate(XYZ)},
                      "valid": recorded["valid"][i, :n]})
        for i, (rid, n) in enumerate(zip(sessions.run_ids, num_frames))],
        ignore_index=True)
    runs_df = pd.DataFrame({"run_id": sessions.run_ids, "source": sessions.sources,
                            "complete": True,
                            "n_commands": [len(c) for c in sessions.commands],
                            "n_frames": num_frames})
    write_raw(writer, cfg, spec, commands_df, mocap_df, runs_df)
    plot_walks(writer.file("figures/exploration_alphas.png"), figure_key, exploration,
               robot.limits, robot.control_hz, robot.n_valves)
    true = [recorded["true_position"][i, :n] for i, n in enumerate(num_frames)]
    writer.summary["true_position_range_mm"] = {
        a: [float(min(np.nanmin(p[:, k]) for p in true) * 1e3),
            float(max(np.nanmax(p[:, k]) for p in true) * 1e3)] for k, a in enumerate(XYZ)}
    if recorded["physics"]:  # the physics each session drew (robot.physics.session_std)
        writer.summary["session_physics"] = {
            name: {rid: np.atleast_1d(np.asarray(values[i], np.float64)).round(6).tolist()
                   for i, rid in enumerate(sessions.run_ids)}
            for name, values in recorded["physics"].items()}


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
