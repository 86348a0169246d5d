"""Entry point: ``python -m pipeline stage=<name> [overrides]``; only composes and routes.

``stage=all`` (the default) runs the chain collect -> align -> fit_model -> train_ppo -> evaluate,
each stage reusing the artifacts of identical upstream settings. A single stage first produces
what it needs upstream the same way (reused when present; fit_model upstream of train_ppo also
fits the ensemble's further model seeds, ``env.ensemble_seeds``; upstream of evaluate, the
cross-model protocol's groups get their own data, models and policies, ``evaluation.cross_model``),
except data from a real arm: with
``robot=ros2`` a stage of :data:`DRIVES_ARM` runs only when it is the stage asked for, never as
another stage's upstream (nor in ``stage=all``).

The composed config is validated (:func:`pipeline.validation.validate_config`) before any work.
Known errors (:data:`KNOWN_ERRORS`: bad data, bad config, an unsafe command, a missing artifact,
an interrupted recording) print one message and exit with status 1; ``HYDRA_FULL_ERROR=1`` shows
the traceback instead.
"""

from __future__ import annotations

import logging
import os
import sys
import time
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
from pipeline.chain import STAGES, Job, plan, stage_function
from pipeline.config import register_configs
from pipeline.data.importers import RecordingNotFoundError
from pipeline.data.raw import CollectionInterrupted
from pipeline.data.schemas import DataError
from pipeline.infra.artifacts import ArtifactStore, MissingArtifactError
from pipeline.infra.compile_cache import quiet_xla_log, use_compilation_cache
from pipeline.infra.devices import configure_cpu_devices
from pipeline.ros2.node import ArmRefused, RosUnavailableError
from pipeline.schemas import ConfigError, Stage
from pipeline.validation import validate_config

log = logging.getLogger("pipeline")

# Errors that are the user's to fix: one message, exit status 1, no traceback.
KNOWN_ERRORS: tuple[type[BaseException], ...] = (
    ConfigError, DataError, RecordingNotFoundError, UnsafeCommandError, MissingArtifactError,
    CollectionInterrupted, RosUnavailableError, ArmRefused)


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
    """``cfg`` with ``robot.physics`` (robot=sim) or ``robot.twin.physics`` (robot=ros2)
    replaced by the calibrate artifact named in ``robot.physics_from`` (unchanged if unset)."""
    source = cfg.robot.get("physics_from") if hasattr(cfg.robot, "get") else None
    if not source:
        return cfg
    from pipeline.arm.twins import load_physics

    physics = load_physics(str(source), cfg.paths.artifact_dir)
    target = cfg.robot.twin if "twin" in cfg.robot else cfg.robot
    unknown = sorted(set(physics) - set(target.physics.keys()))
    if unknown:
        raise ConfigError(f"robot.physics_from={source!r}: parameters {unknown} are not "
                          f"SimPhysics fields of this version")
    for name, value in physics.items():
        target.physics[name] = value
    log.info("robot physics from calibrate artifact %s", source)
    return cfg


def run(cfg: Any) -> dict[str, Any]:
    """Run ``cfg.stage`` after its upstream stages (or the whole chain): the jobs of
    :func:`pipeline.chain.plan`; return each stage's result (its own config's artifact) by
    name. ``dry_run=true`` logs the plan instead and runs nothing."""
    choice, folders = robot_choice()
    validate_config(cfg, choice, folders)
    configure_cpu_devices(cfg.get("cpu_devices"))  # before JAX starts, where it has not
    stage = Stage(cfg.stage)
    cfg = apply_physics_from(cfg)
    if stage in (Stage.all, Stage.evaluate):
        keys.evaluation_twins(cfg)  # an unknown twin fails now, not after the training
    jobs = plan(cfg, lambda variant: keys.key("train_ppo", variant))
    if cfg.get("dry_run"):
        if STAGES[stage].plans_itself:  # its own plan: the jobs it will compose
            stage_function(stage)(cfg)
        else:
            log.info("dry run: %d jobs, nothing runs\n%s", len(jobs), plan_table(jobs))
        return {}
    results: dict[str, Any] = {}
    position = 0
    while position < len(jobs):
        group = [jobs[position]]
        while (group[0].parallel and position + len(group) < len(jobs)
               and jobs[position + len(group)].parallel == group[0].parallel):
            group.append(jobs[position + len(group)])
        workers = min(int(cfg.train_workers), len(group))
        if workers > 1:  # side by side (threads: each job one compiled program)
            with ThreadPoolExecutor(workers) as pool:
                artifacts = list(pool.map(run_job, group))
        else:  # in this thread: stages that serve a ROS 2 graph install signal handlers
            artifacts = [run_job(job) for job in group]
        for job, artifact in zip(group, artifacts, strict=True):
            if job.result:
                results[job.stage.value] = artifact
        position += len(group)
    return results


def run_job(job: Job) -> Any:
    """Runs one job and logs how long it took."""
    started = time.perf_counter()
    artifact = stage_function(job.stage)(job.cfg)
    label = f" ({job.label})" if job.label else ""
    log.info("stage %s%s done in %.1f s", job.stage.value, label, time.perf_counter() - started)
    return artifact


def plan_table(jobs: list[Job]) -> str:
    """One aligned line per job: stage, label, artifact key and whether it is reused."""
    rows = [("stage", "job", "artifact", "status")]
    for job in jobs:
        key, status = "-", "runs"
        if job.stage.value in keys.SPECS:
            key = keys.key(job.stage.value, job.cfg)
            found = ArtifactStore(job.cfg.paths.artifact_dir).find(job.stage.value, key)
            status = ("recomputed (force)" if found is not None and job.cfg.force
                      else "reused" if found is not None else "runs")
        rows.append((job.stage.value, job.label or "-", key, status))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip()
                     for row in rows)


register_configs()
cli.register_help({stage: spec.runs for stage, spec in STAGES.items()})  # the stages and groups of `--help` (conf/hydra/help/)


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


def run_facts(cfg: Any) -> Any:
    """What the closing summary reads of the config (:class:`RunFacts`)."""
    from pipeline.evaluation.summary import RunFacts

    value = lambda v: str(getattr(v, "value", v))  # noqa: E731  (an enum or its string)
    return RunFacts(robot=str(cfg.robot.name), robot_kind=value(cfg.robot.kind),
                    agent=str(cfg.agent.name), env=value(cfg.env.name))


def print_summary(cfg: Any, results: dict[str, Any]) -> None:
    """The closing summary (:mod:`pipeline.evaluation.summary`) on stdout: the tables of what
    ran, the artifact and report paths, the next command (with this run's overrides)."""
    from hydra.core.hydra_config import HydraConfig

    from pipeline.evaluation.summary import closing_summary

    overrides = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    lines = closing_summary(str(Stage(cfg.stage).value), results, run_facts(cfg), overrides)
    if lines:
        print("\n".join(lines), flush=True)


def console() -> None:
    """``python -m pipeline`` and the ``sorolearn`` script: a mistyped key is refused first
    (saying so, rather than Hydra's suggestion to append it with ``+key=value``); ``--dry-run``
    stands for ``dry_run=true``."""
    sys.argv[1:] = cli.dry_run_flag(sys.argv[1:])
    cli.exit_on_unknown_key(sys.argv[1:])
    main()


if __name__ == "__main__":
    console()
