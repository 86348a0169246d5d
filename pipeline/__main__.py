"""Entry point: ``python -m pipeline stage=<name> [overrides]``; only composes and routes.

``stage=all`` (the default) runs the chain collect -> align -> fit_model -> train_ppo -> evaluate,
each stage reusing the artifacts of identical upstream settings. A single stage first produces
what it needs upstream the same way (reused when present; fit_model upstream of train_ppo also
fits the ensemble's further model seeds, ``env.ensemble_seeds``; upstream of evaluate, the
cross-model protocol's groups get their own data, models and policies, ``evaluation.cross_model``),
except data from a real arm: with
``robot=ros2`` a stage of :data:`DRIVES_ARM` runs only when it is the stage asked for, never as
another stage's upstream (nor in ``stage=all``).

The composed config is validated (:func:`pipeline.config.validate_config`) before any work.
Known errors (:data:`KNOWN_ERRORS`: bad data, bad config, an unsafe command, a missing artifact,
an interrupted recording) print one message and exit with status 1; ``HYDRA_FULL_ERROR=1`` shows
the traceback instead.
"""

from __future__ import annotations

import importlib
import logging
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

# XLA's C++ log below FATAL stays quiet (errors that matter reach Python as exceptions). On
# AVX-512 CPUs every load from the compilation cache logs a spurious "machine type doesn't
# match" error for tuning flags of the same machine (jax-ml/jax#38445); set
# TF_CPP_MIN_LOG_LEVEL=0 to see everything. main() applies it to jaxlib as well
# (pipeline.infra.compile_cache.quiet_xla_log): the variable alone does not hide them here.
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

import hydra
from omegaconf import DictConfig

from pipeline import cli, keys
from pipeline.arm.limits import UnsafeCommandError
from pipeline.config import ConfigError, RobotKind, Stage, register_configs, validate_config
from pipeline.data.importers import RecordingNotFoundError
from pipeline.data.raw import CollectionInterrupted
from pipeline.data.schemas import DataError
from pipeline.infra.artifacts import MissingArtifactError
from pipeline.infra.compile_cache import quiet_xla_log, use_compilation_cache
from pipeline.infra.devices import configure_cpu_devices
from pipeline.ros2.node import RosUnavailableError

log = logging.getLogger("pipeline")

# stage -> "module:function"
STAGES: dict[Stage, str] = {
    Stage.collect: "pipeline.stages.collect:collect",
    Stage.align: "pipeline.stages.align:align",
    Stage.fit_model: "pipeline.stages.fit_model:fit_model",
    Stage.train_ppo: "pipeline.stages.train_ppo:train_ppo",
    Stage.evaluate: "pipeline.stages.evaluate:evaluate",
    Stage.twin: "pipeline.stages.twin:twin",
    Stage.guard: "pipeline.stages.guard:guard",
    Stage.control: "pipeline.stages.control:control",
    Stage.calibrate: "pipeline.stages.calibrate:calibrate",
}
# what `stage=all` runs, in order (the digital twin and the guard are servers, started on their own)
CHAIN = (Stage.collect, Stage.align, Stage.fit_model, Stage.train_ppo, Stage.evaluate)
# stages outside the chain that read its data: the part of the chain they need first
UPSTREAM: dict[Stage, tuple[Stage, ...]] = {Stage.calibrate: (Stage.collect, Stage.align)}
# Stages that publish to a real arm's valves (robot=ros2): each runs only when asked for by name.
DRIVES_ARM = frozenset({Stage.collect, Stage.guard, Stage.control})
# Errors that are the user's to fix: one message, exit status 1, no traceback.
KNOWN_ERRORS: tuple[type[BaseException], ...] = (
    ConfigError, DataError, RecordingNotFoundError, UnsafeCommandError, MissingArtifactError,
    CollectionInterrupted, RosUnavailableError)


def stage_function(stage: Stage) -> Callable[[Any], Any]:
    """The function that runs ``stage``."""
    module_name, function_name = STAGES[stage].split(":")
    return getattr(importlib.import_module(module_name), function_name)


def stages_to_run(cfg: Any) -> list[Stage]:
    """``cfg.stage`` preceded by the upstream stages it needs (the whole chain for ``all``); a
    real arm's collection is never started by another stage."""
    stage = Stage(cfg.stage)
    if stage is Stage.all:
        chain = list(CHAIN)
    elif stage not in CHAIN:
        chain = [*UPSTREAM.get(stage, ()), stage]
    else:
        chain = list(CHAIN[: CHAIN.index(stage) + 1])
        env = getattr(cfg.env.name, "value", cfg.env.name)
        # only the learned environment trains on data; evaluate also reads it, except on gymnax
        needs_data = env == "learned" or (stage is Stage.evaluate and env != "gymnax")
        if not needs_data:
            chain = [s for s in chain if s not in (Stage.collect, Stage.align, Stage.fit_model)]
    if RobotKind(cfg.robot.kind) is RobotKind.ros2:
        chain = [s for s in chain if s is stage or s not in DRIVES_ARM]
    return chain


def robot_choice() -> tuple[str | None, list]:
    """The robot group option and the config search folders of the running Hydra app, if any."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None, []
    hydra_cfg = HydraConfig.get()
    folders = [source.path for source in hydra_cfg.runtime.config_sources
               if source.schema == "file" and source.path]
    return hydra_cfg.runtime.choices.get("robot"), folders


def apply_physics_from(cfg: Any) -> Any:
    """``robot.physics_from`` resolved into the robot's physics (see pipeline.stages.calibrate)."""
    if not (hasattr(cfg.robot, "get") and cfg.robot.get("physics_from")):
        return cfg
    from pipeline.stages.calibrate import apply_physics_from as apply

    return apply(cfg)


def run(cfg: Any) -> dict[str, Any]:
    """Run ``cfg.stage`` after its upstream stages (or the whole chain); return each stage's
    result by name. ``force=true`` recomputes the requested stage only (every stage for ``all``)."""
    choice, folders = robot_choice()
    validate_config(cfg, choice, folders)
    configure_cpu_devices(cfg.get("cpu_devices"))  # before JAX starts, where it has not
    stage = Stage(cfg.stage)
    cfg = apply_physics_from(cfg)
    if stage in (Stage.all, Stage.evaluate):
        keys.evaluation_twins(cfg)  # an unknown twin fails now, not after the training
    upstream_cfg = cfg
    if stage is not Stage.all:
        upstream_cfg = cfg.copy()
        upstream_cfg.force = False
    results = {}
    for name in stages_to_run(cfg):
        started = time.perf_counter()
        stage_cfg = cfg if name is stage else upstream_cfg
        if name is Stage.train_ppo and stage in (Stage.all, Stage.evaluate):
            # upstream of evaluate: its own agent and every policy type evaluate compares
            results[name.value] = train_policies(stage_cfg, int(cfg.train_workers))
            cross_model_upstream(stage_cfg, int(cfg.train_workers))
        elif name is Stage.fit_model and stage is not Stage.fit_model:
            results[name.value] = fit_models(stage_cfg)
        else:
            results[name.value] = stage_function(name)(stage_cfg)
        log.info("stage %s done in %.1f s", name.value, time.perf_counter() - started)
    return results


def fit_models(cfg: Any) -> Any:
    """fit_model for ``cfg`` and, for training in an ensemble (``env.ensemble_seeds``), for its
    further model seeds (one after another); returns the artifact of ``cfg``'s own model."""
    fit = stage_function(Stage.fit_model)
    artifact = fit(cfg)
    for member in keys.ensemble_configs(cfg):
        started = time.perf_counter()
        fit(member)
        log.info("stage fit_model (model.seed=%d) done in %.1f s", int(member.model.seed),
                 time.perf_counter() - started)
    return artifact


def train_policies(cfg: Any, workers: int) -> Any:
    """train_ppo for ``cfg``'s agent and for each policy type of ``evaluation.policies``
    (``workers`` at once); returns the artifact of ``cfg``'s own agent."""
    train = stage_function(Stage.train_ppo)
    variants = {cfg.agent.name: cfg, **keys.policy_configs(cfg)}
    by_key = {keys.key("train_ppo", variant): (name, variant) for name, variant in
              variants.items()}

    def timed(name: str, variant: Any) -> Any:
        started = time.perf_counter()
        artifact = train(variant)
        log.info("stage train_ppo (%s) done in %.1f s", name, time.perf_counter() - started)
        return artifact

    with ThreadPoolExecutor(max(1, min(workers, len(by_key)))) as pool:
        futures = {key: pool.submit(timed, *job) for key, job in by_key.items()}
        artifacts = {key: future.result() for key, future in futures.items()}
    return artifacts[keys.key("train_ppo", cfg)]


def cross_model_upstream(cfg: Any, workers: int) -> None:
    """What evaluate's cross-model protocol reads (``evaluation.cross_model``): for each group
    of recordings its data, its model (and ensemble) and every policy type trained in it."""
    for direction, (train, _) in keys.cross_model_folds(cfg).items():
        started = time.perf_counter()
        for stage in (Stage.collect, Stage.align):
            stage_function(stage)(train)
        fit_models(train)
        train_policies(train, workers)
        log.info("cross-model: the group %s trains in (%s) ready in %.1f s", direction[0],
                 ", ".join(train.robot.files), time.perf_counter() - started)


register_configs()
cli.register_help(STAGES)  # the stages and groups of `--help` (conf/hydra/help/)


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> None:
    use_compilation_cache(cfg.paths.compile_cache_dir)
    if Stage(cfg.stage) is not Stage.guard:  # the guard never compiles: it starts without JAX
        quiet_xla_log()
    try:
        results = run(cfg)
    except KNOWN_ERRORS as err:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        log.error("%s: %s", type(err).__name__, err)
        sys.exit(1)
    print_summary(cfg, results)


def print_summary(cfg: Any, results: dict[str, Any]) -> None:
    """The closing summary (:mod:`pipeline.evaluation.summary`) on stdout: the tables of what
    ran, the artifact and report paths, the next command (with this run's overrides)."""
    from hydra.core.hydra_config import HydraConfig

    from pipeline.evaluation.summary import closing_summary

    overrides = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    lines = closing_summary(str(Stage(cfg.stage).value), results, cfg, overrides)
    if lines:
        print("\n".join(lines), flush=True)


def console() -> None:
    """``python -m pipeline`` and the ``sorolearn`` script: a mistyped key is refused first
    (saying so, rather than Hydra's suggestion to append it with ``+key=value``)."""
    cli.exit_on_unknown_key(sys.argv[1:])
    main()


if __name__ == "__main__":
    console()
