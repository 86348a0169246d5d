"""Importers of recorded real-arm data into the raw ``commands`` and ``mocap`` schemas.

- **sorolex CSV** (the paper's files, ``shared/data/sorolex``): ``time,1_x,1_y,1_z,
  control_pressure_0..2``, already aligned by the authors (each command held on the mocap rows
  until the next). Commands are recovered as the rows where the pressure changes (plus the first
  row); consecutive commands of identical value are therefore merged into one, which ``align``
  reproduces identically. Every row is a valid mocap frame.
- **PlotJuggler CSV** exports of the ROS topics: a ``__time`` column and one column per message
  field, merged on a common time axis, empty where a topic had no message at that time. Position
  columns end in ``/pose/position/x`` (``y``, ``z``); pressure columns end in ``p_d.<j>`` or
  ``data.<j>``.
- **ROS 2 bags** (``robot=rosbag``): a recording is a bag *folder* (``metadata.yaml`` plus sqlite3
  or MCAP storage) holding the command and pose topics (``pipeline/data/rosbag.py``).

Rows in errors are 0-based data rows; the CSV line is ``row + 2`` (the header is line 1). A file
whose last line has no newline was cut while being written: that line is dropped and counted.
"""

from __future__ import annotations

import hashlib
import io
import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.data.schemas import (
    CMD_COLUMNS,
    COMMANDS,
    MOCAP,
    N_VALVES,
    XYZ,
    DataError,
    check_pressure_limits,
    validate,
)

log = logging.getLogger(__name__)
SOROLEX_TIME = "time"
SOROLEX_POSITION = ["1_x", "1_y", "1_z"]
SOROLEX_PRESSURE = [f"control_pressure_{j}" for j in range(N_VALVES)]
PLOTJUGGLER_TIME = "__time"
_PJ_POSITION = re.compile(r"^(?P<body>.*)/pose/position/(?P<axis>[xyz])$")
_PJ_PRESSURE = re.compile(r"^(?P<topic>.*)/(?P<field>p_d|data)[.\[/](?P<index>\d+)\]?$")
_SOROLEX_ANY_PRESSURE = re.compile(r"^control_pressure_\d+$")


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes (artifact keys of imported data follow the data, not its path)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def recording_digest(path: Path) -> str:
    """:func:`file_digest` of a recording file, or of every file in a recording folder (a bag)."""
    if not path.is_dir():
        return file_digest(path)
    digest = hashlib.sha256()
    for member in sorted(p for p in path.rglob("*") if p.is_file()):
        digest.update(f"{member.relative_to(path)}\0{file_digest(member)}\0".encode())
    return digest.hexdigest()


def recording_id(path: Path) -> str:
    """Run id of a recording: the file name without suffix, or the folder name."""
    return path.name if path.is_dir() else path.stem


class RecordingNotFoundError(FileNotFoundError):
    """robot.data_dir, robot.files or robot.pattern name no recording."""


# Import kinds whose recordings are folders, with the file that marks one.
FOLDER_RECORDINGS = {"rosbag": "metadata.yaml"}


def list_recordings(robot: Any) -> list[Path]:
    """The recordings an import robot reads (files, or bag folders), sorted; an error if none."""
    data_dir = Path(robot.data_dir).expanduser()
    if not data_dir.is_dir():
        raise RecordingNotFoundError(
            f"robot.data_dir={data_dir} is not a folder (set robot.data_dir=... or SOROLEX_DIR)"
        )
    marker = FOLDER_RECORDINGS.get(getattr(robot.kind, "value", str(robot.kind)))
    what = f"folders with a {marker}" if marker else "files"

    def is_recording(path: Path) -> bool:
        return (path / marker).is_file() if marker else path.is_file()

    if robot.files:
        paths = [data_dir / name for name in robot.files]
        missing = [str(p) for p in paths if not is_recording(p)]
        if missing:
            raise RecordingNotFoundError(f"robot.files not found (expected {what}): {missing}")
    else:
        paths = [p for p in sorted(data_dir.glob(robot.pattern)) if is_recording(p)]
    if getattr(robot, "num_runs", None) is not None:
        paths = paths[:int(robot.num_runs)]
    if not paths:
        raise RecordingNotFoundError(f"no {what} match {robot.pattern!r} in {data_dir}")
    return paths


def _read_csv(path: Path, notes: dict[str, Any] | None = None) -> pd.DataFrame:
    """The CSV's rows. A file that does not end in a newline was cut off while being written:
    its last line (perhaps cut inside a number) is dropped, logged and counted in ``notes``
    (``incomplete_last_line``)."""
    raw = path.read_bytes()
    if not raw:
        raise DataError(str(path), "the file is empty")
    if b"\0" in raw[:65536]:
        raise DataError(str(path), "a binary file, not a CSV text file (it holds NUL bytes)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise DataError(str(path), f"not a UTF-8 text file: byte 0x{raw[err.start]:02x} at "
                        f"offset {err.start} is not UTF-8 (a CSV export is expected)") from err
    dropped = 0
    if not text.endswith("\n"):
        last_start = text.rfind("\n") + 1
        if last_start > 0 and text[:last_start].count("\n") >= 2:  # a header and a row remain
            dropped = 1
            log.warning("%s: no newline at the end: the last line (line %d, %r) is incomplete "
                        "and dropped", path, text.count("\n") + 1, text[last_start:][:80])
            text = text[:last_start]
    if notes is not None:
        notes["incomplete_last_line"] = dropped
    try:
        df = pd.read_csv(io.StringIO(text), skipinitialspace=True)
    except pd.errors.EmptyDataError as err:
        raise DataError(str(path), "the file has no header or no data") from err
    except pd.errors.ParserError as err:
        raise DataError(str(path), f"not a well-formed CSV ({err})") from err
    if len(df) == 0:
        raise DataError(str(path), "the file has a header but no data rows")
    return df


def _require(df: pd.DataFrame, columns: list[str], path: Path) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise DataError(str(path), f"missing column(s) {missing}; found {list(df.columns)}",
                        column=missing[0])


def read_sorolex_csv(path: Path, limits: Any, run_id: str | None = None,
                     notes: dict[str, Any] | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """One paper CSV as ``(commands, mocap)`` tables, validated (limits checked); ``notes``
    receives what was dropped (see :func:`_read_csv`)."""
    path = Path(path)
    df = _read_csv(path, notes)
    _require(df, [SOROLEX_TIME, *SOROLEX_POSITION, *SOROLEX_PRESSURE], path)
    pressure_columns = [c for c in df.columns if _SOROLEX_ANY_PRESSURE.match(str(c))]
    if pressure_columns != SOROLEX_PRESSURE:
        raise DataError(str(path), f"found pressure columns {pressure_columns}; expected exactly "
                        f"{SOROLEX_PRESSURE} ({N_VALVES} valves)")
    run_id = run_id or path.stem
    mocap = pd.DataFrame({"run_id": run_id, "t": df[SOROLEX_TIME]})
    for axis, column in zip(XYZ, SOROLEX_POSITION):
        mocap[axis] = df[column]
    mocap["valid"] = True
    # Validate against the file's own column names first, so errors name them.
    renamed = {SOROLEX_TIME: "t", **dict(zip(SOROLEX_POSITION, XYZ)),
               **dict(zip(SOROLEX_PRESSURE, CMD_COLUMNS))}
    _validate_named(df, renamed, path, limits)
    mocap = validate(mocap, MOCAP, str(path))

    pressures = df[SOROLEX_PRESSURE].to_numpy(np.float64)
    changed = np.r_[True, np.any(pressures[1:] != pressures[:-1], axis=1)]
    commands = pd.DataFrame({"run_id": run_id, "t": mocap["t"].to_numpy()[changed]})
    for j, column in enumerate(CMD_COLUMNS):
        commands[column] = pressures[changed, j]
    return validate(commands, COMMANDS, str(path), limits), mocap


def _validate_named(df: pd.DataFrame, renamed: dict[str, str], path: Path, limits: Any) -> None:
    """Run the schema checks on the CSV's columns but report the CSV's own column names."""
    for original in renamed:
        values = pd.to_numeric(df[original], errors="coerce").to_numpy(np.float64)
        bad = ~np.isfinite(values)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            hint = "; a truncated last line looks like this" if row == len(df) - 1 else ""
            raise DataError(str(path), f"not a finite number: {str(df[original].iloc[row])!r} "
                            f"(line {row + 2}{hint})", original, row)
    t = df[SOROLEX_TIME].to_numpy(np.float64)
    dt = np.diff(t)
    for problem, mask in (("duplicate timestamp", dt == 0), ("timestamp goes backwards", dt < 0)):
        if mask.any():
            row = int(np.flatnonzero(mask)[0]) + 1
            raise DataError(str(path), f"{problem}: {t[row]:.6f} s after {t[row - 1]:.6f} s "
                            f"(line {row + 2})", SOROLEX_TIME, row)
    pressure_cols = [k for k, v in renamed.items() if v in CMD_COLUMNS]
    check_pressure_limits(df[pressure_cols].to_numpy(np.float64), pressure_cols, limits,
                          str(path))


def read_plotjuggler_csv(path: Path, limits: Any, run_id: str | None = None,
                         notes: dict[str, Any] | None = None
                         ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """A PlotJuggler CSV export as ``(commands, mocap)`` tables, validated (limits checked);
    errors name the CSV line; ``notes`` receives what was dropped (see :func:`_read_csv`)."""
    path = Path(path)
    df = _read_csv(path, notes)
    _require(df, [PLOTJUGGLER_TIME], path)
    bodies: dict[str, dict[str, str]] = {}
    pressure_topics: dict[tuple[str, str], dict[int, str]] = {}
    for column in df.columns:
        if m := _PJ_POSITION.match(column):
            bodies.setdefault(m["body"], {})[m["axis"]] = column
        elif m := _PJ_PRESSURE.match(column):
            pressure_topics.setdefault((m["topic"], m["field"]), {})[int(m["index"])] = column
    bodies = {b: axes for b, axes in bodies.items() if set(axes) == set(XYZ)}
    if len(bodies) != 1:
        raise DataError(str(path), f"expected one rigid body with .../pose/position/x,y,z "
                        f"columns, found {sorted(bodies) or 'none'}")
    expected = f"p_d.0..{N_VALVES - 1} (or data.0..{N_VALVES - 1})"
    found = {f"{topic}/{name}": [columns[i] for i in sorted(columns)]
             for (topic, name), columns in pressure_topics.items()}
    if len(pressure_topics) != 1:
        raise DataError(str(path), f"expected one pressure topic with fields {expected}, found "
                        f"{found or 'none'}")
    (axes,) = bodies.values()
    (fields,) = pressure_topics.values()
    if sorted(fields) != list(range(N_VALVES)):
        (columns,) = found.values()
        raise DataError(str(path), f"the pressure topic has {len(fields)} field(s) {columns}; "
                        f"expected {expected}: {N_VALVES} valves")
    position_cols = [axes[a] for a in XYZ]
    pressure_cols = [fields[j] for j in range(N_VALVES)]
    run_id = run_id or path.stem

    t = pd.to_numeric(df[PLOTJUGGLER_TIME], errors="coerce")
    if t.isna().any():
        row = int(np.flatnonzero(t.isna().to_numpy())[0])
        raise DataError(str(path), f"not a number (line {row + 2})", PLOTJUGGLER_TIME, row)

    def stream(columns: list[str], what: str) -> pd.DataFrame:
        present = df[columns].notna()
        partial = present.any(axis=1) & ~present.all(axis=1)
        if partial.any():
            row = int(np.flatnonzero(partial.to_numpy())[0])
            missing = next(c for c in columns if pd.isna(df[c].iloc[row]))
            raise DataError(str(path), f"{what} sample with an empty field (line {row + 2})",
                            missing, row)
        rows = present.all(axis=1).to_numpy()
        if not rows.any():
            raise DataError(str(path), f"no {what} samples", columns[0])
        return df.loc[rows, [PLOTJUGGLER_TIME, *columns]]

    pose = stream(position_cols, "pose")
    mocap = pd.DataFrame({"run_id": run_id, "t": pose[PLOTJUGGLER_TIME].to_numpy()})
    for axis, column in zip(XYZ, position_cols):
        mocap[axis] = pose[column].to_numpy()
    mocap["valid"] = True
    command = stream(pressure_cols, "pressure command")
    check_pressure_limits(command[pressure_cols].to_numpy(np.float64), pressure_cols, limits,
                          str(path))
    commands = pd.DataFrame({"run_id": run_id, "t": command[PLOTJUGGLER_TIME].to_numpy()})
    for j, column in enumerate(CMD_COLUMNS):
        commands[column] = command[pressure_cols[j]].to_numpy()
    return (_validate_stream(commands, COMMANDS, path, "pressure", command.index, limits),
            _validate_stream(mocap, MOCAP, path, "pose", pose.index))


def _validate_stream(table: pd.DataFrame, schema: Any, path: Path, what: str, rows: pd.Index,
                     limits: Any = None) -> pd.DataFrame:
    """:func:`validate` one stream of a PlotJuggler export; an error names the CSV line."""
    try:
        return validate(table, schema, f"{path} ({what} topic)", limits)
    except DataError as err:
        if err.row is None:
            raise
        row = int(rows[err.row])
        raise DataError(str(path), f"{what} topic: {err.problem} (line {row + 2})", err.column,
                        row) from err


def _read_rosbag(path: Path, robot: Any) -> tuple[pd.DataFrame, pd.DataFrame]:
    from pipeline.data.rosbag import read_rosbag  # rosbags loads only for bags

    return read_rosbag(path, robot)


# kind -> reader(path, robot config, notes) -> (commands, mocap), both validated; notes (a dict)
# receives what the reader dropped (incomplete_last_line)
READERS = {
    "sorolex_csv": lambda path, robot, notes: read_sorolex_csv(path, robot.limits, notes=notes),
    "plotjuggler_csv": lambda path, robot, notes: read_plotjuggler_csv(path, robot.limits,
                                                                       notes=notes),
    "rosbag": lambda path, robot, notes: _read_rosbag(path, robot),
}
