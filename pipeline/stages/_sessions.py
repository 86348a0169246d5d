"""The session artifacts ``dataset.sessions`` names, for the stages that read them (``align``)
and make them (``improve``)."""

from __future__ import annotations

from pathlib import Path

from pipeline.infra.artifacts import MANIFEST, Artifact, ArtifactStore, MissingArtifactError

# the stages whose artifacts hold a session's run (pipeline/data/sessions.py)
SESSION_STAGES = ("control", "explore")


def session_artifact(store: ArtifactStore, entry: str) -> Artifact:
    """The session artifact ``entry`` names: its folder, or its key in ``store`` (a control
    session or an improve walk); a :class:`MissingArtifactError` naming the setting otherwise."""
    folder = Path(entry)
    if (folder / MANIFEST).is_file():
        return Artifact(folder.parent.name, folder.name, folder)
    for stage in SESSION_STAGES:
        found = store.find(stage, entry)
        if found is not None:
            return found
    raise MissingArtifactError(
        f"dataset.sessions: {entry!r} is neither an artifact folder nor the key of a session "
        f"artifact ({', '.join(SESSION_STAGES)}) under {store.root}")
