"""Entry point: ``python -m pipeline stage=<name> [overrides]``; only composes and routes.

``stage=all`` (the default) runs the chain collect -> align -> fit_model -> train_ppo -> evaluate,
each stage reusing the artifacts of identical upstream settings. A single stage first produces
what it needs upstream the same way (reused when present), except data from a real arm: with
``robot=ros2`` the arm is driven only by an explicit ``stage=collect``.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Callable
from typing import Any

import hydra
from omegaconf import DictConfig

from pipeline.config import RobotKind, Stage, register_configs

log = logging.getLogger("pipeline")

# stage -> "module:function"; a stage whose module is not there yet is skipped by `all`.
STAGES: dict[Stage, str] = {
    Stage.collect: "pipeline.collect:collect",
    Stage.align: "pipeline.align:align",
    Stage.fit_model: "pipeline.fit_model:fit_model",
    Stage.train_ppo: "pipeline.train_ppo:train_ppo",
    Stage.evaluate: "pipeline.evaluate:evaluate",
    Stage.twin: "pipeline.ros2.twin:twin",
    Stage.calibrate: "pipeline.calibrate:calibrate",
}
# what `stage=all` runs, in order (the digital twin is a server, started on its own)
CHAIN = (Stage.collect, Stage.align, Stage.fit_model, Stage.train_ppo, Stage.evaluate)
# evaluate trains the other policy types it compares when they are missing
CHAIN_OPTIONS: dict[Stage, dict[str, Any]] = {Stage.evaluate: {"train_missing": True}}
# stages outside the chain that read its data: the part of the chain they need first
UPSTREAM: dict[Stage, tuple[Stage, ...]] = {Stage.calibrate: (Stage.collect, Stage.align)}


def stage_function(stage: Stage) -> Callable[[Any], Any] | None:
    """The function that runs ``stage``, or None if this version does not implement it."""
    module_name, function_name = STAGES[stage].split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if err.name == module_name:
            return None
        raise
    return getattr(module, function_name)


def stages_to_run(cfg: Any) -> list[Stage]:
    """``cfg.stage`` preceded by the upstream stages it needs (the whole chain for ``all``); a
    real arm's collection is never started by another stage."""
    stage = Stage(cfg.stage)
    if stage is Stage.all:
        return list(CHAIN)
    if stage not in CHAIN:
        chain = [*UPSTREAM.get(stage, ()), stage]
        if stage is not Stage.collect and RobotKind(cfg.robot.kind) is RobotKind.ros2:
            chain = [s for s in chain if s is not Stage.collect]
        return chain
    chain = list(CHAIN[: CHAIN.index(stage) + 1])
    env = getattr(cfg.env.name, "value", cfg.env.name)
    # only the learned environment trains on data; evaluate also reads it, except on gymnax
    needs_data = env == "learned" or (stage is Stage.evaluate and env != "gymnax")
    if not needs_data:
        chain = [s for s in chain if s not in (Stage.collect, Stage.align, Stage.fit_model)]
    if stage is not Stage.collect and RobotKind(cfg.robot.kind) is RobotKind.ros2:
        chain = [s for s in chain if s is not Stage.collect]
    return chain


def apply_physics_from(cfg: Any) -> Any:
    """``robot.physics_from`` resolved into the robot's physics (see pipeline.calibrate)."""
    if not (hasattr(cfg.robot, "get") and cfg.robot.get("physics_from")):
        return cfg
    from pipeline.calibrate import apply_physics_from as apply

    return apply(cfg)


def run(cfg: Any) -> dict[str, Any]:
    """Run ``cfg.stage`` after its upstream stages (or the whole chain); return each stage's
    result by name. ``force=true`` recomputes the requested stage only (every stage for ``all``)."""
    stage = Stage(cfg.stage)
    cfg = apply_physics_from(cfg)
    upstream_cfg = cfg
    if stage is not Stage.all:
        upstream_cfg = cfg.copy()
        upstream_cfg.force = False
    results = {}
    for name in stages_to_run(cfg):
        function = stage_function(name)
        if function is None:
            if stage is Stage.all:
                log.warning("stage %s is not implemented in this version; the chain stops here",
                            name.value)
                break
            raise NotImplementedError(f"stage={name.value} is not implemented in this version")
        started = time.perf_counter()
        stage_cfg = cfg if name is stage else upstream_cfg
        results[name.value] = function(stage_cfg, **CHAIN_OPTIONS.get(name, {}))
        log.info("stage %s done in %.1f s", name.value, time.perf_counter() - started)
    return results


register_configs()


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
