"""Table schemas of the artifacts passed between stages, with units, validation and Parquet I/O.

Tables (one row per sample, runs stacked, times in seconds on the run's own clock):

- ``commands``: run_id, t [s], p_cmd_0..2 [kPa]                  (valve commands, ~2 Hz)
- ``mocap``:    run_id, t [s], x, y, z [m], valid                 (marker positions, ~100 Hz;
                                                                    x, y, z are NaN where not valid)
- ``aligned``:  run_id, t [s], p_0..2 [kPa], x, y, z [m], matched (mocap rows with the command in
                                                                    force; matched marks the row a
                                                                    command was matched to)
- ``runs``:     run_id, source, complete, n_commands, n_frames    (one row per recorded run)
- ``targets``:  run_id, t [s], goal_x, goal_y, goal_z [m]         (a control session's goal or
                                                                    reference point per period)

Every Parquet file carries its schema name, units and the producing config in its metadata.
Reading validates the columns, types, finiteness, time order and (given limits) the pressures, and
raises :class:`DataError` naming the file, column and row of the first problem.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.infra.parquet import METADATA_KEY, encode_metadata, write_parquet

N_VALVES = 3
CMD_COLUMNS = [f"p_cmd_{j}" for j in range(N_VALVES)]
P_COLUMNS = [f"p_{j}" for j in range(N_VALVES)]
XYZ = ["x", "y", "z"]


class DataError(ValueError):
    """Bad input data. The message names the file, column and row."""

    def __init__(self, source: str, message: str, column: str | None = None,
                 row: int | None = None):
        where = str(source)
        if column is not None:
            where += f", column '{column}'"
        if row is not None:
            where += f", row {row}"
        super().__init__(f"{where}: {message}")
        self.source, self.column, self.row = str(source), column, row
        self.problem = message


@dataclass(frozen=True)
class Column:
    name: str
    kind: str  # "str" | "float" | "bool"
    unit: str = ""
    description: str = ""


@dataclass(frozen=True)
class TableSchema:
    name: str
    columns: tuple[Column, ...]
    time_column: str | None = "t"
    run_column: str | None = "run_id"
    nan_allowed_unless: str | None = None  # NaN allowed in float columns where this is False

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.columns]

    @property
    def units(self) -> dict[str, str]:
        return {c.name: c.unit for c in self.columns if c.unit}

    def arrow_schema(self, metadata: Mapping[str, Any]) -> pa.Schema:
        types = {"str": pa.string(), "float": pa.float64(), "bool": pa.bool_(),
                 "int": pa.int64()}
        fields = [
            pa.field(c.name, types[c.kind],
                     metadata={"unit": c.unit, "description": c.description})
            for c in self.columns
        ]
        return pa.schema(fields, metadata=encode_metadata(metadata))


_RUN = Column("run_id", "str", "", "run identifier")
_T = Column("t", "float", "s", "time on the run's clock")

COMMANDS = TableSchema(
    "commands",
    (_RUN, _T, *(Column(c, "float", "kPa", f"commanded pressure of valve {j}")
                 for j, c in enumerate(CMD_COLUMNS))),
)
MOCAP = TableSchema(
    "mocap",
    (_RUN, _T, *(Column(c, "float", "m", f"marker position {c} (y vertical)") for c in XYZ),
     Column("valid", "bool", "", "frame was captured (False: dropped, x/y/z are NaN)")),
    nan_allowed_unless="valid",
)
ALIGNED = TableSchema(
    "aligned",
    (_RUN, _T, *(Column(c, "float", "kPa", f"pressure command in force on valve {j}")
                 for j, c in enumerate(P_COLUMNS)),
     *(Column(c, "float", "m", f"marker position {c} (y vertical)") for c in XYZ),
     Column("matched", "bool", "", "a command was matched to this row")),
)
RUNS = TableSchema(
    "runs",
    (_RUN, Column("source", "str", "", "where the run came from"),
     Column("complete", "bool", "", "False if the recording was interrupted"),
     Column("n_commands", "int", "count", "commands recorded"),
     Column("n_frames", "int", "count", "mocap frames recorded")),
    time_column=None,
)
MODEL_METRICS = TableSchema(
    "model_metrics",
    (_RUN,
     Column("split", "str", "", "cv: a fold model on its held-out run | cv_train: a fold model "
            "on one of its training runs | cv_context: a fold model calibrated on the first "
            "context_s of its held-out run, on the rest | train / test: the model later stages "
            "use, on its training runs / held-out runs (protocol split)"),
     Column("fold", "int", "", "index of the fold (-1: the model later stages use)"),
     Column("held_out", "str", "", "the fold's held-out run (empty: no fold)"),
     Column("seed", "int", "", "model seed"),
     Column("model", "str", "", "learned (the fitted model, GRU or LSTM) | mean_position | "
            "linear_lagged (baselines fitted on the same training runs)"),
     Column("steps", "int", "model steps", "length of the run at the model rate"),
     Column("context_s", "float", "s", "seconds of the run's start given to the model (and the "
            "linear baseline refitted on them) as session context; 0: none"),
     Column("from_s", "float", "s", "the error is over the run from here on (0: the entire run)"),
     Column("mean_mm", "float", "mm", "mean open-loop Euclidean error over the run from from_s"),
     Column("p95_mm", "float", "mm", "95th percentile of that error"),
     Column("loses_to_linear", "bool", "", "the learned model's mean error on this held-out "
            "run is not below the linear lagged baseline's (a warning)")),
    time_column=None,
)
TARGETS = TableSchema(
    "targets",
    (_RUN, _T, *(Column(f"goal_{c}", "float", "m", f"the goal (or the reference point) in force, "
                        f"{c}") for c in XYZ)),
)
SCHEMAS = {s.name: s for s in (COMMANDS, MOCAP, ALIGNED, RUNS, MODEL_METRICS, TARGETS)}


# --------------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------------
def validate(
    df: pd.DataFrame,
    schema: TableSchema,
    source: str,
    limits: Any | None = None,
) -> pd.DataFrame:
    """Check ``df`` against ``schema``; return it with canonical dtypes and column order.

    ``limits`` (with p_min, p_max, sum_max in kPa) adds a check of every pressure column.
    """
    missing = [c for c in schema.names if c not in df.columns]
    if missing:
        raise DataError(source, f"missing column(s) {missing}; expected {schema.names}",
                        column=missing[0])
    out = df[schema.names].copy()
    if schema.nan_allowed_unless is not None:
        # The flag column governs where NaN is allowed, so it is checked first.
        flag = schema.nan_allowed_unless
        _check_bool(out, flag, source)
        out[flag] = out[flag].astype(bool)
    for col in schema.columns:
        if col.kind == "str":
            out[col.name] = out[col.name].astype(str)
        elif col.kind == "bool":
            _check_bool(out, col.name, source)
            out[col.name] = out[col.name].astype(bool)
        elif col.kind == "int":
            out[col.name] = _numeric(out, col.name, source).astype(np.int64)
        else:
            values = _numeric(out, col.name, source)
            bad = ~np.isfinite(values)
            if schema.nan_allowed_unless is not None:
                bad &= out[schema.nan_allowed_unless].to_numpy()
            if bad.any():
                row = int(np.flatnonzero(bad)[0])
                raise DataError(source, f"non-finite value {values[row]!r}", col.name, row)
            out[col.name] = values
    if len(out) == 0:
        raise DataError(source, f"the {schema.name} table is empty")
    if schema.time_column is not None:
        _check_time(out, schema, source)
    if limits is not None:
        pcols = [c for c in out.columns if c in CMD_COLUMNS or c in P_COLUMNS]
        check_pressure_limits(out[pcols].to_numpy(), pcols, limits, source)
    return out.reset_index(drop=True)


def _numeric(df: pd.DataFrame, column: str, source: str) -> np.ndarray:
    values = pd.to_numeric(df[column], errors="coerce").to_numpy(dtype=np.float64)
    raw = df[column].to_numpy()
    not_numeric = np.isnan(values) & pd.notna(raw)
    if not_numeric.any():
        row = int(np.flatnonzero(not_numeric)[0])
        raise DataError(source, f"not a number: {raw[row]!r}", column, row)
    return values


def _check_bool(df: pd.DataFrame, column: str, source: str) -> None:
    values = df[column]
    ok = values.isin([True, False, 0, 1])
    if not ok.all():
        row = int(np.flatnonzero(~ok.to_numpy())[0])
        raise DataError(source, f"expected a boolean, got {values.iloc[row]!r}", column, row)


def _check_time(df: pd.DataFrame, schema: TableSchema, source: str) -> None:
    t = df[schema.time_column].to_numpy()
    runs = df[schema.run_column].to_numpy() if schema.run_column else np.zeros(len(df))
    same_run = runs[1:] == runs[:-1]
    dt = np.diff(t)
    for problem, mask in (("duplicate timestamp", (dt == 0) & same_run),
                          ("timestamp goes backwards", (dt < 0) & same_run)):
        if mask.any():
            row = int(np.flatnonzero(mask)[0]) + 1
            raise DataError(source, f"{problem}: t={t[row]:.6f} s after t={t[row - 1]:.6f} s",
                            schema.time_column, row)
    starts = np.flatnonzero(np.r_[True, ~same_run])
    seen = set()
    for row in starts:
        if runs[row] in seen:
            raise DataError(source, f"rows of run {runs[row]!r} are not contiguous",
                            schema.run_column, int(row))
        seen.add(runs[row])


def check_pressure_limits(pressures: np.ndarray, columns: list[str], limits: Any,
                          source: str, tol: float = 1e-9) -> None:
    """Raise :class:`DataError` at the first pressure outside the limits' safe set."""
    p = np.asarray(pressures, dtype=np.float64)
    for j, col in enumerate(columns):
        low = p[:, j] < limits.p_min - tol
        high = p[:, j] > limits.p_max + tol
        for mask, what in ((low, f"below p_min={limits.p_min}"),
                           (high, f"above p_max={limits.p_max}")):
            if mask.any():
                row = int(np.flatnonzero(mask)[0])
                raise DataError(source, f"pressure {p[row, j]:.4g} kPa is {what} kPa", col, row)
    over = p.sum(axis=1) > limits.sum_max + tol
    if over.any():
        row = int(np.flatnonzero(over)[0])
        raise DataError(source, f"summed pressure {p[row].sum():.4g} kPa exceeds "
                        f"sum_max={limits.sum_max} kPa", "+".join(columns), row)


def check_workspace(mocap: pd.DataFrame, workspace: Any, source: str) -> None:
    """Raise :class:`DataError` if a valid marker position [m] lies outside the workspace box,
    saying so when the positions look like millimetres (every one inside the box once / 1000)."""
    low = np.asarray(list(workspace.low_m), np.float64)
    high = np.asarray(list(workspace.high_m), np.float64)
    xyz = mocap[XYZ].to_numpy(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    outside = ((xyz < low) | (xyz > high)).any(axis=1)
    if not outside.any():
        return
    row = int(np.flatnonzero(outside)[0])
    largest = {a: float(np.abs(xyz[:, k]).max()) for k, a in enumerate(XYZ)}
    box = f"robot.workspace [{low.tolist()}, {high.tolist()}] m"
    scaled = xyz / 1000.0
    if ((scaled >= low) & (scaled <= high)).all():
        raise DataError(source, f"positions look like millimetres, not metres: largest |x|, |y|, "
                        f"|z| = {largest['x']:.4g}, {largest['y']:.4g}, {largest['z']:.4g}, "
                        f"outside {box}; convert the positions to metres")
    raise DataError(source, f"position {xyz[row].tolist()} m lies outside {box} (wrong units or "
                    f"frame?)")


# --------------------------------------------------------------------------------------------
# Parquet I/O
# --------------------------------------------------------------------------------------------
def write_table(
    df: pd.DataFrame,
    path: str | os.PathLike[str],
    schema: TableSchema,
    config: Mapping[str, Any] | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> Path:
    """Validate and write ``df`` as Parquet, atomically (temporary file, then rename)."""
    path = Path(path)
    df = validate(df, schema, source=f"{path} (being written)")
    metadata = {
        "schema": schema.name,
        "units": schema.units,
        "config": dict(config or {}),
        "provenance": dict(provenance or {}),
    }
    return write_parquet(df, path, metadata, schema.arrow_schema(metadata))


def read_table(
    path: str | os.PathLike[str], schema: TableSchema, limits: Any | None = None
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Read and validate a Parquet table; return it with its sorolearn metadata."""
    path = Path(path)
    if not path.is_file():
        raise DataError(str(path), f"no such {schema.name} table")
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as err:
        raise DataError(str(path), f"not a readable Parquet file ({err})") from err
    raw = (table.schema.metadata or {}).get(METADATA_KEY)
    metadata = json.loads(raw) if raw else {}
    if metadata.get("schema", schema.name) != schema.name:
        raise DataError(str(path), f"holds a '{metadata['schema']}' table, expected "
                        f"'{schema.name}'")
    return validate(table.to_pandas(), schema, str(path), limits), metadata
