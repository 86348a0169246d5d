"""A finished artifact as a typed record: what a report or a library reads of it, loaded once by
the stage (:func:`artifact_record`), so that libraries receive tables and paths, not a folder
layout to open by name.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.infra.artifacts import Artifact

FIGURES = "figures"


@dataclass(frozen=True)
class ArtifactRecord:
    """What is read of one artifact.

    ``stage`` and ``key`` name it, ``path`` is its folder; ``summary`` is its manifest's summary
    (``{}`` where it has none) and ``build_seconds`` the wall seconds its build took (None where
    it was not recorded); ``figures`` maps a figure's file name to its path, for the requested
    figures that exist; ``tables`` maps a table's name (its Parquet file's stem) to the table.
    """

    stage: str
    key: str
    path: Path
    summary: Mapping[str, Any] = field(default_factory=dict)
    build_seconds: float | None = None
    figures: Mapping[str, Path] = field(default_factory=dict)
    tables: Mapping[str, pd.DataFrame] = field(default_factory=dict)


def artifact_record(artifact: Artifact, figures: Iterable[str] = (),
                    tables: Iterable[str] = ()) -> ArtifactRecord:
    """``artifact`` as an :class:`ArtifactRecord`: its manifest's summary and build time, the
    paths of those of ``figures`` (file names under ``figures/``) it holds, and its Parquet
    ``tables`` by name (``metrics`` reads ``metrics.parquet``; each must exist)."""
    manifest = artifact.manifest
    drawn = {name: artifact.file(f"{FIGURES}/{name}") for name in figures}
    return ArtifactRecord(
        stage=artifact.stage, key=artifact.key, path=artifact.path,
        summary=manifest.get("summary", {}), build_seconds=manifest.get("build_seconds"),
        figures={name: path for name, path in drawn.items() if path.is_file()},
        tables={name: pd.read_parquet(artifact.file(f"{name}.parquet")) for name in tables})
