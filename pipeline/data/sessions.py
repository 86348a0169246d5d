"""Sessions as data: what a controller did on the arm, as a run in collect's format.

A control session (``stage=control``) and an exploration walk of ``stage=improve`` keep, beside
their own records, one run in a ``run/`` folder of their artifact: ``commands.parquet`` (every
command sent, at its publish time), ``mocap.parquet`` (every pose frame taken, at the mocap
rate), ``runs.parquet`` (one row: the run, its controller as ``source``, whether it ended as
planned) and ``targets.parquet`` (the goal or reference point in force each period; an
exploration walk has none). The tables' metadata name the session's artifact, robot, rates and
controller (its provenance).

``dataset.sessions`` names such artifacts: ``align`` joins their runs to the collected ones
(:func:`join_sessions`), after checking they come from the same arm at the same rates
(:func:`check_session`), and ``fit_model`` weighs their windows by ``dataset.session_weight``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.data.schemas import (
    CMD_COLUMNS,
    COMMANDS,
    MOCAP,
    RUNS,
    TARGETS,
    XYZ,
    DataError,
    read_table,
    write_table,
)

RUN_FOLDER = "run"
SESSION_PREFIX = "session-"  # run ids of joined sessions start with this
# a session's mocap rate may differ from the data's by this fraction (jitter, dropped frames)
RATE_TOLERANCE = 0.2


@dataclass(frozen=True)
class SessionRun:
    """One session's run: collect's tables (``commands``, ``mocap``, ``runs``), the
    ``targets`` table (possibly empty) and the provenance from the tables' metadata."""

    commands: pd.DataFrame
    mocap: pd.DataFrame
    runs: pd.DataFrame
    targets: pd.DataFrame
    provenance: dict[str, Any]

    @property
    def run_id(self) -> str:
        return str(self.runs["run_id"].iloc[0])


def session_run_id(kind: str, key: str) -> str:
    """The run id of a session artifact's run: ``session-<kind>-<first 10 of its key>``."""
    return f"{SESSION_PREFIX}{kind}-{key[:10]}"


def session_tables(periods: pd.DataFrame, frames: pd.DataFrame, run_id: str, source: str,
                   complete: bool, n_valves: int) -> SessionRun:
    """A control session's rows as one run.

    ``periods``: the loop's rows (:mod:`pipeline.control.records`: ``publish_t``, ``p_cmd_<j>``,
    ``goal_index``, ``goal_*``, ``ref_*``); ``frames``: every pose frame (``t, x, y, z,
    valid``). Commands are the periods that published one (held ones included), mocap every
    frame whose stamp comes after the earlier ones' (a jittered stamp that does not is
    dropped, as a lost frame), targets the reference point in force each period where the
    session followed one, else its goal.
    """
    sent = periods[np.isfinite(periods["publish_t"].to_numpy(np.float64))
                   & (periods["goal_index"].to_numpy() != -1)]
    sent = sent.loc[increasing(sent["publish_t"].to_numpy(np.float64))]
    commands = pd.DataFrame({"run_id": run_id, "t": sent["publish_t"].to_numpy(np.float64),
                             **{c: sent[c].to_numpy(np.float64) for c in CMD_COLUMNS[:n_valves]}})
    stamps = frames["t"].to_numpy(np.float64)
    kept = frames.loc[increasing(stamps)]
    valid = kept["valid"].to_numpy(bool)
    mocap = pd.DataFrame({"run_id": run_id, "t": kept["t"].to_numpy(np.float64),
                          **{a: np.where(valid, kept[a].to_numpy(np.float64), np.nan)
                             for a in XYZ}, "valid": valid})
    served = periods[periods["goal_index"].to_numpy() >= 0]
    reference = served[[f"ref_{a}" for a in XYZ]].to_numpy(np.float64)
    goal = served[[f"goal_{a}" for a in XYZ]].to_numpy(np.float64)
    target = np.where(np.isfinite(reference).all(axis=1, keepdims=True), reference, goal)
    targets = pd.DataFrame({"run_id": run_id, "t": served["t"].to_numpy(np.float64),
                            **{f"goal_{a}": target[:, k] for k, a in enumerate(XYZ)}})
    targets = targets[np.isfinite(target).all(axis=1)]
    runs = pd.DataFrame({"run_id": [run_id], "source": [source], "complete": [bool(complete)],
                         "n_commands": [len(commands)], "n_frames": [len(mocap)]})
    return SessionRun(commands, mocap, runs, targets, {})


def walk_tables(commands: pd.DataFrame, mocap: pd.DataFrame, run_id: str, source: str
                ) -> SessionRun:
    """A walk driven on an arm (:func:`pipeline.control.walk.drive_walk`'s tables) as one run."""
    commands = commands.assign(run_id=run_id)
    mocap = mocap.assign(run_id=run_id)
    runs = pd.DataFrame({"run_id": [run_id], "source": [source], "complete": [True],
                         "n_commands": [len(commands)], "n_frames": [len(mocap)]})
    empty = pd.DataFrame({c: pd.Series(dtype=object if c == "run_id" else np.float64)
                          for c in TARGETS.names})
    return SessionRun(commands, mocap, runs, empty, {})


def increasing(values: np.ndarray) -> np.ndarray:
    """Mask of the entries greater than every earlier one."""
    previous = np.maximum.accumulate(np.concatenate([[-np.inf], values[:-1]]))
    return values > previous


def write_session(folder: Path, run: SessionRun, config: dict[str, Any],
                  provenance: dict[str, Any]) -> None:
    """The run's tables into ``folder/run/`` with ``provenance`` (the session's artifact,
    robot, rates, controller) in each table's metadata."""
    where = Path(folder) / RUN_FOLDER
    write_table(run.commands, where / "commands.parquet", COMMANDS, config, provenance)
    write_table(run.mocap, where / "mocap.parquet", MOCAP, config, provenance)
    write_table(run.runs, where / "runs.parquet", RUNS, config, provenance)
    if len(run.targets):
        write_table(run.targets, where / "targets.parquet", TARGETS, config, provenance)


def read_session(folder: Path, limits: Any = None) -> SessionRun:
    """The run kept in a session artifact ``folder`` (:func:`write_session`); a
    :class:`DataError` naming the folder where it holds none."""
    where = Path(folder) / RUN_FOLDER
    if not (where / "runs.parquet").is_file():
        raise DataError(str(folder), f"holds no session run ({RUN_FOLDER}/runs.parquet): "
                        f"dataset.sessions names artifacts of stage=control or stage=improve")
    commands, metadata = read_table(where / "commands.parquet", COMMANDS, limits)
    mocap, _ = read_table(where / "mocap.parquet", MOCAP)
    runs, _ = read_table(where / "runs.parquet", RUNS)
    targets = (read_table(where / "targets.parquet", TARGETS)[0]
               if (where / "targets.parquet").is_file() else pd.DataFrame(columns=TARGETS.names))
    return SessionRun(commands, mocap, runs, targets, dict(metadata.get("provenance", {})))


def mocap_rate_hz(mocap: pd.DataFrame) -> float:
    """The median frame rate of ``mocap`` over its runs [Hz] (nan with too few frames)."""
    steps = [np.diff(run["t"].to_numpy(np.float64)) for _, run in mocap.groupby("run_id")]
    steps = np.concatenate(steps) if steps else np.array([])
    return float(1.0 / np.median(steps)) if len(steps) else float("nan")


def check_session(session: SessionRun, source: str, *, n_valves: int, control_hz: float,
                  mocap_hz: float, arm: str) -> None:
    """A :class:`DataError` naming ``source`` unless the session comes from an arm of
    ``n_valves`` valves commanded at ``control_hz`` (its provenance) with frames at about
    ``mocap_hz`` (within :data:`RATE_TOLERANCE`), of the arm named ``arm`` (its provenance's
    ``arm``: the rating it was driven under, :func:`arm_identity`)."""
    provenance = session.provenance
    valves = [c for c in CMD_COLUMNS if c in session.commands.columns]
    if len(valves) != n_valves:
        raise DataError(source, f"commands {len(valves)} valves; the data has {n_valves}",
                        "p_cmd")
    rate = provenance.get("control_hz")
    if rate is None or abs(float(rate) - float(control_hz)) > 1e-9:
        raise DataError(source, f"was commanded at {rate} Hz; the data at robot.control_hz="
                        f"{control_hz:g} Hz", "control_hz")
    own = mocap_rate_hz(session.mocap)
    if np.isfinite(mocap_hz) and not abs(own - mocap_hz) <= RATE_TOLERANCE * mocap_hz:
        raise DataError(source, f"mocap at {own:.1f} Hz; the data's is {mocap_hz:.1f} Hz "
                        f"(within {RATE_TOLERANCE:.0%})", "t")
    if provenance.get("arm") != arm:
        raise DataError(source, f"was driven on another arm ({provenance.get('arm')}); the "
                        f"data's arm is {arm}", "arm")


def arm_identity(rating: Any) -> str:
    """What names an arm in a session's provenance: its rating (valves, pressures), as JSON."""
    fields = ("n_valves", "p_min", "p_max", "sum_max", "preload")
    return json.dumps({name: float(getattr(rating, name)) for name in fields}, sort_keys=True)


def join_sessions(commands: pd.DataFrame, mocap: pd.DataFrame, runs: pd.DataFrame,
                  sessions: list[SessionRun]) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """The collected tables with each session's run appended; a :class:`DataError` where a
    run id is taken twice."""
    taken = set(runs["run_id"].astype(str))
    for session in sessions:
        if session.run_id in taken:
            raise DataError(str(session.provenance.get("artifact", session.run_id)),
                            f"run {session.run_id!r} is joined twice (named twice in "
                            f"dataset.sessions?)", "run_id")
        taken.add(session.run_id)
    return (pd.concat([commands, *(s.commands for s in sessions)], ignore_index=True),
            pd.concat([mocap, *(s.mocap for s in sessions)], ignore_index=True),
            pd.concat([runs, *(s.runs for s in sessions)], ignore_index=True))
