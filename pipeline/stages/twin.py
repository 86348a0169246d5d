"""Stage ``twin``: the simulated arm as a ROS 2 node on ``robot=ros2``'s topics, until stopped.

Not part of ``stage=all``: a server, started on its own (see :mod:`pipeline.ros2.twin`).
"""

from __future__ import annotations

from typing import Any

from omegaconf import OmegaConf


def twin(cfg: Any) -> None:
    from pipeline.ros2.twin import serve  # the optional ros extra

    serve(OmegaConf.to_object(cfg.robot))
