"""Per-period records of a control session, written to Parquet chunks while it runs.

As collect's recovery chunks (:mod:`pipeline.ros2.recorder`): rows are buffered and
:meth:`PeriodRecorder.flush` writes the new ones as the next numbered chunk
(``periods-00000.parquet``, ...) into a recovery folder, so a killed session keeps everything up
to the last flush; :meth:`PeriodRecorder.read_all` reads them back as one table.

Columns (one row per control period, and a last row with the pose at the end of the session):
``period``, ``t`` (the period's tick, arm s from the start), ``publish_t`` (arm s),
``pose_t`` (the pose's stamp, arm s), ``pose_age_s`` (at command time), ``x, y, z`` (m),
``goal_index`` (-1 on the last row), ``goal_x, goal_y, goal_z`` (m: the period's goal; following a
reference, the reference at the period's end), ``ref_x, ref_y, ref_z`` (m: following a reference,
the reference at the period's tick, the point the pose of that tick is scored against; NaN with
goals), ``obs_<i>``, ``action_<j>``
([-1, 1]), ``p_cmd_<j>`` (kPa, the command sent after the gate), ``latency_ms`` (wall: pose
taken to command published), ``cpu_ms`` (the CPU time this process spent on it: the compute
itself, without the waits for cores that other processes hold), ``event`` (empty; ``late``: the
loop woke after a stall and held the last command, ``missed_periods`` periods before it got no
command; ``stale_pose``: held while waiting for a pose stamped after the stall) and
``missed_periods``. A held period has no observation or action (NaN) and, before the first goal,
``goal_index`` -2.

Every pose frame the loop takes is kept too (:meth:`PeriodRecorder.add_frames`, chunks
``frames-00000.parquet``, ...; :meth:`PeriodRecorder.read_frames`): ``t`` (the frame's stamp,
arm s), ``x, y, z`` (m; NaN where the marker was lost) and ``valid``, so that a session is also a
run at the mocap rate (:mod:`pipeline.control.session_run`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.data.schemas import CMD_COLUMNS, XYZ
from pipeline.infra.parquet import write_parquet

SCHEMA = "control_periods"
UNITS = {"t": "s", "publish_t": "s", "pose_t": "s", "pose_age_s": "s", "x": "m", "y": "m",
         "z": "m", "goal_x": "m", "goal_y": "m", "goal_z": "m", "ref_x": "m", "ref_y": "m",
         "ref_z": "m", "latency_ms": "ms", "cpu_ms": "ms",
         **{c: "kPa" for c in CMD_COLUMNS}}
FRAMES_SCHEMA = "control_frames"
FRAME_UNITS = {"t": "s", "x": "m", "y": "m", "z": "m"}
GOAL_COLUMNS = [f"goal_{a}" for a in XYZ]
REFERENCE_COLUMNS = [f"ref_{a}" for a in XYZ]


class PeriodRecorder:
    def __init__(self, folder: Path, obs_dim: int, config: Mapping[str, Any],
                 provenance: Mapping[str, Any]):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.obs_dim = int(obs_dim)
        self._metadata = {"schema": SCHEMA, "units": UNITS, "config": dict(config),
                          "provenance": dict(provenance)}
        self._rows: list[dict[str, Any]] = []
        self._frames: list[tuple[float, float, float, float]] = []
        self._chunks = 0
        self._frame_chunks = 0
        self.periods = 0

    def add(self, *, period: int, t: float, publish_t: float, pose_t: float, pose_age_s: float,
            position: np.ndarray, goal_index: int, goal: np.ndarray, observation: Any,
            action: np.ndarray, command: np.ndarray, latency_ms: float, cpu_ms: float,
            event: str = "", missed_periods: int = 0, reference: Any = None) -> None:
        reference = np.full(3, np.nan) if reference is None else reference
        obs = (np.full(self.obs_dim, np.nan) if observation is None
               else np.asarray(observation, np.float64))
        row = {"period": int(period), "t": float(t), "publish_t": float(publish_t),
               "pose_t": float(pose_t), "pose_age_s": float(pose_age_s),
               **dict(zip(XYZ, map(float, position))), "goal_index": int(goal_index),
               **dict(zip(GOAL_COLUMNS, map(float, goal))),
               **dict(zip(REFERENCE_COLUMNS, map(float, reference))),
               **{f"obs_{i}": float(v) for i, v in enumerate(obs)},
               **{f"action_{j}": float(v) for j, v in enumerate(action)},
               **dict(zip(CMD_COLUMNS, map(float, command))), "latency_ms": float(latency_ms),
               "cpu_ms": float(cpu_ms), "event": str(event),
               "missed_periods": int(missed_periods)}
        self._rows.append(row)
        if goal_index >= 0:
            self.periods += 1

    def add_frames(self, frames: list[tuple[float, float, np.ndarray]]) -> None:
        """Keep pose frames ``(stamp, receipt, position [3] m)`` as they were taken (stamps in
        arm s; a non-finite position is a lost marker, kept as an invalid frame)."""
        for stamp, _, position in frames:
            self._frames.append((float(stamp), *map(float, position)))

    def flush(self) -> None:
        """Write the rows and frames added since the last flush as the next chunks (nothing if
        none)."""
        if self._rows:
            write_parquet(pd.DataFrame(self._rows),
                          self.folder / f"periods-{self._chunks:05d}.parquet", self._metadata)
            self._rows = []  # cleared once on disk: no row is written twice or lost
            self._chunks += 1
        if self._frames:
            frames = pd.DataFrame(self._frames, columns=["t", *XYZ])
            frames["valid"] = np.isfinite(frames[XYZ].to_numpy()).all(axis=1)
            write_parquet(frames, self.folder / f"frames-{self._frame_chunks:05d}.parquet",
                          {**self._metadata, "schema": FRAMES_SCHEMA, "units": FRAME_UNITS})
            self._frames = []
            self._frame_chunks += 1

    def read_all(self) -> pd.DataFrame:
        """Flush, then every chunk read back as one table (possibly empty)."""
        self.flush()
        return _read_chunks(self.folder, "periods")

    def read_frames(self) -> pd.DataFrame:
        """Flush, then every pose frame taken, in order (columns ``t, x, y, z, valid``)."""
        self.flush()
        frames = _read_chunks(self.folder, "frames")
        return frames if len(frames) else pd.DataFrame(columns=["t", *XYZ, "valid"])

    def write(self, path: Path, table: pd.DataFrame) -> Path:
        return write_parquet(table, path, self._metadata)


def _read_chunks(folder: Path, name: str) -> pd.DataFrame:
    parts = [pd.read_parquet(p) for p in sorted(folder.glob(f"{name}-*.parquet"))]
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
