"""Stage ``guard``: the arm-side deadman and rating filter as a ROS 2 node, until stopped.

Not part of ``stage=all``: a server a lab runs beside its valve driver (see
:mod:`pipeline.ros2.guard`).
"""

from __future__ import annotations

from typing import Any

from omegaconf import OmegaConf


def guard(cfg: Any) -> None:
    from pipeline.ros2.guard import guard as serve  # the optional ros extra

    serve(OmegaConf.to_object(cfg.robot))
