"""Stage ``control``: a trained policy drives the arm toward goals (see
:mod:`pipeline.control.session`). Not part of ``stage=all``: started on its own."""

from __future__ import annotations

from typing import Any

from pipeline.control.session import control as run_control
from pipeline.infra.artifacts import Artifact


def control(cfg: Any) -> Artifact:
    return run_control(cfg)
