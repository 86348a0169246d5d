"""Raw streams recorded while collecting, written to Parquet chunks as they come in.

Rows are buffered in memory and :meth:`ChunkedRecorder.flush` writes the new ones as numbered
chunk files (``commands-00000.parquet``, ``mocap-00000.parquet``, ... in the raw schemas of
``pipeline/data/schemas.py``) into a recovery folder. A crash or a kill (SIGKILL, power loss) loses at
most the rows since the last flush; the chunks are plain Parquet tables readable with pandas.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.data.schemas import CMD_COLUMNS, COMMANDS, MOCAP, XYZ, read_table, write_table


class ChunkedRecorder:
    def __init__(self, folder: Path, config: Mapping[str, Any], provenance: Mapping[str, Any]):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._config, self._provenance = dict(config), dict(provenance)
        self._commands: list[tuple] = []
        self._frames: list[tuple] = []
        self._chunks = 0

    def add_command(self, run_id: str, t: float, pressures: Any) -> None:
        """A command sent at ``t`` [s on the run's clock], ``pressures`` [kPa]."""
        self._commands.append((run_id, t, *(float(p) for p in pressures)))

    def add_frame(self, run_id: str, t: float, xyz: tuple[float, float, float],
                  valid: bool) -> None:
        """A mocap frame stamped ``t`` [s], position [m]."""
        self._frames.append((run_id, t, *xyz, valid))

    def flush(self) -> None:
        """Write the rows added since the last flush as the next chunk (nothing if none)."""
        if not self._commands and not self._frames:
            return
        for name, rows, columns, schema in (
                ("commands", self._commands, ["run_id", "t", *CMD_COLUMNS], COMMANDS),
                ("mocap", self._frames, ["run_id", "t", *XYZ, "valid"], MOCAP)):
            if rows:
                write_table(pd.DataFrame(rows, columns=columns),
                            self.folder / f"{name}-{self._chunks:05d}.parquet", schema,
                            self._config, self._provenance)
        # Cleared only once both chunks are on disk, so no row is written twice or lost.
        self._commands, self._frames = [], []
        self._chunks += 1

    def read_all(self) -> tuple[pd.DataFrame, pd.DataFrame]:
        """Flush, then every chunk read back: ``(commands, mocap)`` (possibly empty)."""
        self.flush()
        tables = []
        for name, schema in (("commands", COMMANDS), ("mocap", MOCAP)):
            parts = [read_table(path, schema)[0]
                     for path in sorted(self.folder.glob(f"{name}-*.parquet"))]
            tables.append(pd.concat(parts, ignore_index=True) if parts
                          else pd.DataFrame(columns=schema.names))
        return tables[0], tables[1]
