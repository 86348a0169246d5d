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

import datetime as _dt
import logging
import shutil
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.arm.limits import validate_limits
from pipeline.data.importers import READERS, list_recordings, recording_id
from pipeline.data.raw import CollectionInterrupted, check_positions, plot_runs, raw_summary
from pipeline.data.schemas import CMD_COLUMNS, COMMANDS, MOCAP, RUNS, XYZ, write_table
from pipeline.infra.artifacts import Artifact, ArtifactStore, ArtifactWriter, artifact_key, produce
from pipeline.schemas import ImportRobotConfig, RobotKind
from pipeline.stages._rehearsal import refuse_twin_artifact

log = logging.getLogger(__name__)
STAGE = "collect"


def collect(cfg: Any) -> Artifact:
    robot = OmegaConf.to_object(cfg.robot)
    validate_limits(robot.limits, robot.n_valves)
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.collect_spec(cfg)
    kind = RobotKind(robot.kind)
    if kind is RobotKind.sim:
        exploration = OmegaConf.to_object(cfg.exploration)
        build = lambda writer: _collect_sim(robot, exploration, writer, spec)  # noqa: E731
    elif kind in keys.IMPORT_KINDS:
        build = lambda writer: _import_recordings(robot, writer, spec)  # noqa: E731
    else:
        return _collect_ros2(cfg, robot, store, spec, inputs)
    return produce(store, STAGE, spec, inputs, build, force=cfg.force)


def write_raw(writer: ArtifactWriter, robot: Any, spec: dict[str, Any], commands: pd.DataFrame,
              mocap: pd.DataFrame, runs: pd.DataFrame) -> None:
    """The three tables and a figure; the positions must lie in ``robot.workspace``."""
    check_positions(mocap, runs, robot.workspace)
    provenance = {"stage": STAGE, "robot": robot.name}
    write_table(commands, writer.file("commands.parquet"), COMMANDS, spec, provenance)
    write_table(mocap, writer.file("mocap.parquet"), MOCAP, spec, provenance)
    write_table(runs, writer.file("runs.parquet"), RUNS, spec, provenance)
    plot_runs(writer.file("figures/runs.png"), commands, mocap)
    writer.summary = raw_summary(commands, mocap, runs)


def _collect_ros2(cfg: Any, robot: Any, store: ArtifactStore, spec: dict[str, Any],
                  inputs: dict[str, str]) -> Artifact:
    from pipeline.arm.exploration import plot_walks
    from pipeline.ros2.collector import collect_ros2  # the optional ros extra

    key = artifact_key(spec, inputs)
    _refuse_rehearsal_data(store, key, bool(robot.rehearsal), bool(cfg.force))
    _set_aside_incomplete(store, key, bool(robot.reuse_incomplete))
    exploration = OmegaConf.to_object(cfg.exploration)
    interruptions = []

    def build(writer: ArtifactWriter) -> None:
        started = _dt.datetime.now().strftime("%Y%m%dT%H%M%S")
        recovery = Path(cfg.paths.output_dir) / "recovery" / f"{STAGE}-{writer.key}-{started}"
        recorded = collect_ros2(robot, exploration, recovery, spec)
        write_raw(writer, robot, spec, recorded.commands, recorded.mocap, recorded.runs)
        plot_walks(writer.file("figures/exploration_alphas.png"), recorded.figure_key,
                   exploration, robot.limits, robot.control_hz, robot.n_valves)
        writer.summary["ros2"] = recorded.link
        writer.summary["rehearsal"] = bool(robot.rehearsal)  # recorded on the twin
        if recorded.interruption is not None:
            writer.summary["interrupted"] = recorded.interruption.reason
        shutil.rmtree(recorded.recovery)  # the artifact's temporary folder now holds every row
        interruptions.append(recorded.interruption)

    artifact = produce(store, STAGE, spec, inputs, build, force=cfg.force)
    interruption = interruptions[0] if interruptions else None
    if interruption is not None:
        raise CollectionInterrupted(
            f"collect interrupted: {interruption.reason}. The preload was commanded. The runs "
            f"recorded so far are in {artifact.path}, the last marked incomplete (align them with "
            f"dataset.align.accept_incomplete=true); the next collect with this config sets them "
            f"aside and records anew unless robot.reuse_incomplete=true") from interruption.error
    return artifact


def _refuse_rehearsal_data(store: ArtifactStore, key: str, rehearsal: bool, force: bool) -> None:
    """A real-arm collect never answers with a rehearsal's data: a rehearsal recorded with the
    same ``robot.session`` holds this key, so refuse instead of reusing the twin's runs as the
    arm's."""
    refuse_twin_artifact(
        store, STAGE, key, rehearsal, force,
        "collect: {path} holds a rehearsal recorded on the digital twin under this config's "
        "key; a real-arm collect would reuse the twin's runs as the arm's. Name this session "
        "anew (robot.session=...), or force=true to record over it")


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


def walk_sessions(robot: Any, exploration: Any, mocap_hz: float) -> SimSessions:
    """``robot.num_runs`` exploration walks at ``robot.control_hz``."""
    from pipeline.arm import sim_arm
    from pipeline.arm.exploration import exploration_plan

    plan = exploration_plan(exploration, robot.limits, robot.n_valves, robot.num_runs)
    runs, n = plan.commands.shape[:2]
    frames = sim_arm.frame_command_index(n, robot.control_hz, mocap_hz)
    return SimSessions([f"sim-{i:03d}" for i in range(runs)], ["sim"] * runs,
                       list(plan.commands), [np.arange(n) / float(robot.control_hz)] * runs,
                       [frames] * runs)


def replay_sessions(robot: Any, exploration: Any, mocap_hz: float) -> SimSessions:
    """The valve commands of the recordings of ``robot.replay`` at their recorded times (from
    the recording's first mocap frame), each session as long as its recording."""
    replay = robot.replay
    read = READERS[RobotKind(replay.kind).value]
    reader = ImportRobotConfig(name=f"replay:{replay.kind}", kind=replay.kind,
                               data_dir=replay.data_dir, limits=robot.limits)
    sessions = SimSessions([], [], [], [], [])
    for path in list_recordings(replay):
        commands, mocap = read(path, reader, {})
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


def _collect_sim(robot: Any, exploration: Any, writer: ArtifactWriter, spec: dict[str, Any]
                 ) -> None:
    # JAX only for the simulated arm: importing recordings, and every stage that reuses this
    # one's artifact, start without it
    import jax

    from pipeline.arm import sim_arm
    from pipeline.arm.exploration import plan_keys, plot_walks

    params = sim_arm.SimParams.from_config(robot)
    preload = np.full(robot.n_valves, float(robot.limits.preload))
    _, session_key, figure_key = plan_keys(exploration)
    sessions = (replay_sessions if robot.replay else walk_sessions)(robot, exploration,
                                                                    params.mocap_hz)
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
    write_raw(writer, robot, spec, commands_df, mocap_df, runs_df)
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


def _import_recordings(robot: Any, writer: ArtifactWriter, spec: dict[str, Any]) -> None:
    read = READERS[RobotKind(robot.kind).value]
    commands, mocap, runs, incomplete = [], [], [], {}
    for path in list_recordings(robot):
        notes: dict[str, Any] = {}
        run_commands, run_mocap = read(path, robot, notes)
        commands.append(run_commands)
        mocap.append(run_mocap)
        runs.append({"run_id": recording_id(path), "source": path.name, "complete": True,
                     "n_commands": len(run_commands), "n_frames": len(run_mocap)})
        if notes.get("incomplete_last_line"):
            incomplete[recording_id(path)] = int(notes["incomplete_last_line"])
        log.info("collect: imported %s (%d commands, %d frames)", path.name, len(run_commands),
                 len(run_mocap))
    write_raw(writer, robot, spec, pd.concat(commands, ignore_index=True),
              pd.concat(mocap, ignore_index=True), pd.DataFrame(runs))
    # lines dropped because a file ended inside them (no final newline), per run
    writer.summary["incomplete_lines_dropped"] = incomplete
