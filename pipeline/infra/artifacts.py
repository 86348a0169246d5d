"""Content-keyed, atomically written stage artifacts.

An artifact is a folder ``<artifact_dir>/<stage>/<key>/`` holding Parquet tables, figures,
checkpoints and ``artifact.json`` (the manifest). Its key hashes the part of the config that
determines the stage's output together with the keys of its inputs, so

- a later stage finds its inputs from the composed config alone (no paths),
- re-running with an identical config reuses the artifact, and sweeps share upstream artifacts,
- changing any upstream setting changes every downstream key.

Writes go to a hidden sibling folder that is renamed into place only when complete: a stage killed
at any moment leaves at worst a ``.tmp-*`` folder, which no reader ever looks at. A per-key file
lock stops parallel sweep jobs from computing the same artifact twice.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import hashlib
import json
import logging
import os
import shutil
import time
import uuid
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

MANIFEST = "artifact.json"
KEY_LENGTH = 12


def artifact_key(spec: Mapping[str, Any], inputs: Mapping[str, str]) -> str:
    """Stable short hash of a stage's determining config and its input keys (order-free)."""
    blob = json.dumps(
        {"spec": spec, "inputs": dict(inputs)}, sort_keys=True, default=str, separators=(",", ":")
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:KEY_LENGTH]


@dataclass(frozen=True)
class Artifact:
    """A finished artifact on disk."""

    stage: str
    key: str
    path: Path

    @property
    def manifest(self) -> dict[str, Any]:
        return json.loads((self.path / MANIFEST).read_text())

    def file(self, name: str) -> Path:
        return self.path / name


class MissingArtifactError(FileNotFoundError):
    """An input artifact a stage needs has not been produced with this config."""


class ArtifactStore:
    def __init__(self, root: str | os.PathLike[str]):
        self.root = Path(root).resolve()

    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def find(self, stage: str, key: str) -> Artifact | None:
        path = self.path(stage, key)
        if (path / MANIFEST).is_file():
            return Artifact(stage, key, path)
        return None

    def set_aside(self, artifact: Artifact, label: str) -> Path:
        """Rename ``artifact`` to ``<key>.<label>-<created>`` beside it, so that it no longer
        answers to its key (nothing is deleted); call it holding :meth:`lock`."""
        stamp = _dt.datetime.fromisoformat(artifact.manifest["created"]).strftime("%Y%m%dT%H%M%S")
        aside = artifact.path.with_name(f"{artifact.key}.{label}-{stamp}")
        os.rename(artifact.path, aside)
        return aside

    def resolve(self, stage: str, entry: str) -> Artifact:
        """An artifact named by its folder (anywhere) or by its key in this store."""
        folder = Path(entry)
        if (folder / MANIFEST).is_file():
            return Artifact(stage, folder.name, folder)
        return self.require(stage, entry)

    def require(self, stage: str, key: str, hint: str = "") -> Artifact:
        artifact = self.find(stage, key)
        if artifact is None:
            raise MissingArtifactError(
                f"no '{stage}' artifact with key {key} under {self.root / stage}: "
                f"run `python -m pipeline stage={stage}` with the same config first{hint}"
            )
        return artifact

    @contextlib.contextmanager
    def lock(self, stage: str, key: str) -> Iterator[None]:
        (self.root / stage).mkdir(parents=True, exist_ok=True)
        with open(self.root / stage / f".{key}.lock", "w") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)

    @contextlib.contextmanager
    def writing(
        self,
        stage: str,
        key: str,
        spec: Mapping[str, Any],
        inputs: Mapping[str, str] | None = None,
    ) -> Iterator[ArtifactWriter]:
        """Yield a writer into a temporary folder; publish it atomically when the block succeeds.

        On an exception the temporary folder is removed and any previous artifact is untouched.
        """
        stage_dir = self.root / stage
        stage_dir.mkdir(parents=True, exist_ok=True)
        tmp = stage_dir / f".tmp-{key}-{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        writer = ArtifactWriter(stage, key, tmp, dict(spec), dict(inputs or {}))
        try:
            yield writer
            writer.write_manifest()
            _fsync_dir(tmp)
            self._publish(tmp, self.path(stage, key))
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    @staticmethod
    def _publish(tmp: Path, final: Path) -> None:
        if final.exists():
            # force=true: move the old artifact aside first; both renames are atomic, so a
            # reader sees the old complete folder, no folder, or the new complete folder.
            trash = final.with_name(f".old-{final.name}-{uuid.uuid4().hex[:8]}")
            os.rename(final, trash)
            os.rename(tmp, final)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.rename(tmp, final)
        _fsync_dir(final.parent)


@dataclass
class ArtifactWriter:
    stage: str
    key: str
    path: Path
    spec: dict[str, Any]
    inputs: dict[str, str]
    summary: dict[str, Any] | None = None
    build_seconds: float | None = None  # wall time of the build (produce sets it)

    def file(self, name: str) -> Path:
        target = self.path / name
        target.parent.mkdir(parents=True, exist_ok=True)
        return target

    def write_manifest(self) -> None:
        manifest = {
            "stage": self.stage,
            "key": self.key,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "inputs": self.inputs,
            "spec": self.spec,
            "summary": self.summary or {},
            "build_seconds": self.build_seconds,
            "files": sorted(
                str(p.relative_to(self.path)) for p in self.path.rglob("*") if p.is_file()
            ),
        }
        (self.path / MANIFEST).write_text(json.dumps(manifest, indent=2, default=str))


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def produce(
    store: ArtifactStore,
    stage: str,
    spec: Mapping[str, Any],
    inputs: Mapping[str, str],
    build,
    force: bool = False,
) -> Artifact:
    """Return the artifact for ``spec`` + ``inputs``, building it with ``build(writer)`` if needed.

    ``build`` fills the writer's folder and may set ``writer.summary``. With ``force`` an existing
    artifact is rebuilt and replaced atomically.
    """
    key = artifact_key(spec, inputs)
    with store.lock(stage, key):
        existing = store.find(stage, key)
        if existing is not None and not force:
            log.info("%s: reusing artifact %s (same config; force=true recomputes)", stage,
                     existing.path)
            return existing
        with store.writing(stage, key, spec, inputs) as writer:
            started = time.perf_counter()
            build(writer)
            writer.build_seconds = round(time.perf_counter() - started, 2)
        artifact = store.require(stage, key)
        log.info("%s: wrote artifact %s", stage, artifact.path)
        return artifact
