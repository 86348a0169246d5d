"""Writing files atomically, and Parquet tables with the project's metadata.

Every file a stage writes appears whole or not at all: it is written to a temporary file beside
its destination, flushed to disk and renamed into place (:func:`atomic_write`). Every Parquet
table carries a JSON blob under :data:`METADATA_KEY`: its schema name, the units of its columns,
the config that produced it and its provenance (:func:`write_parquet`).
"""

from __future__ import annotations

import contextlib
import json
import os
import uuid
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

METADATA_KEY = b"sorolearn"


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path to write; on success it is fsynced and renamed to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        yield tmp
        with open(tmp, "rb") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


# unit of a column by the end of its name (the project's naming convention)
_SUFFIX_UNITS = (("_mm", "mm"), ("_m", "m"), ("_kpa", "kPa"), ("_s", "s"), ("_hz", "Hz"))
_PREFIX_UNITS = (("steps_", "control periods"), ("success_", "fraction of episodes"),
                 ("time_above_", "fraction of control periods"))


def column_units(columns: Any) -> dict[str, str]:
    """Units read off column names: ``*_mm`` mm, ``*_m`` m, ``*_kpa`` kPa, ``*_s`` s,
    ``steps_*`` control periods, ``success_*`` a fraction; columns without one are left out."""
    units = {}
    for column in map(str, columns):
        lower = column.lower()
        for suffix, unit in _SUFFIX_UNITS:
            if lower.endswith(suffix):
                units[column] = unit
        for prefix, unit in _PREFIX_UNITS:
            if lower.startswith(prefix):
                units[column] = unit
    return units


def table_metadata(frame: pd.DataFrame, name: str, config: Mapping[str, Any] | None = None,
                   provenance: Mapping[str, Any] | None = None,
                   units: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The metadata every table carries: its name, its columns' units (read off the names,
    ``units`` overriding), the producing config and its provenance."""
    return {"schema": name, "units": {**column_units(frame.columns), **dict(units or {})},
            "config": dict(config or {}), "provenance": dict(provenance or {})}


def encode_metadata(metadata: Mapping[str, Any]) -> dict[bytes, str]:
    return {METADATA_KEY: json.dumps(dict(metadata), default=str)}


def write_parquet(frame: pd.DataFrame, path: str | os.PathLike[str], metadata: Mapping[str, Any],
                  schema: pa.Schema | None = None) -> Path:
    """``frame`` as Parquet at ``path`` (atomically) with ``metadata`` (schema name, units,
    config, provenance); ``schema`` fixes the Arrow types where given."""
    path = Path(path)
    table = pa.Table.from_pandas(frame, schema=schema, preserve_index=False)
    table = table.replace_schema_metadata({**(table.schema.metadata or {}),
                                           **encode_metadata(metadata)})
    with atomic_write(path) as tmp:
        pq.write_table(table, tmp)
    return path


def read_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The project's metadata of a Parquet file ({} where it has none)."""
    raw = (pq.read_schema(path).metadata or {}).get(METADATA_KEY)
    return json.loads(raw) if raw else {}
