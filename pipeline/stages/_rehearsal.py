"""What the stages that drive an arm share about rehearsals on the digital twin."""

from __future__ import annotations

from pipeline.infra.artifacts import ArtifactStore
from pipeline.schemas import ConfigError


def refuse_twin_artifact(store: ArtifactStore, stage: str, key: str, rehearsal: bool,
                         force: bool, refusal: str) -> None:
    """On the arm, never answer with the twin's artifact: the rehearsal settings are not part of
    a key (a rehearsal runs the arm's config on its twin), so an artifact of ``stage`` under
    ``key`` whose summary says ``rehearsal`` is refused with ``refusal`` (``{path}``: where it
    lies). Nothing is refused for a rehearsal itself or with ``force``."""
    if rehearsal or force:
        return
    existing = store.find(stage, key)
    if existing is not None and existing.manifest.get("summary", {}).get("rehearsal"):
        raise ConfigError(refusal.format(path=existing.path))
