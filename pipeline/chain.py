"""The chain as data: every stage, what it reads and writes, and the jobs a run fans out into.

One declaration (:data:`STAGES`) says for each stage the function that runs it, the artifacts it
consumes and whether it drives a real arm; :func:`stages_to_run` orders a run's stages and
:func:`plan` expands them into :class:`Job` s: the ensemble's further model seeds
(``env.ensemble_seeds``), one training per policy type that evaluate compares
(``evaluation.policies``) and, for the cross-model protocol (``evaluation.cross_model``), each
group's data, models and policies. The entry point runs the plan (or prints it with
``dry_run=true``); the artifact keys (``pipeline.keys``) read the same fan-out, so what runs and
what evaluate looks up cannot drift apart.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

from omegaconf import OmegaConf

from pipeline.config import PROJECT_ROOT
from pipeline.data.importers import list_recordings
from pipeline.schemas import (
    AgentConfig,
    ConfigError,
    EnvName,
    ModelProtocol,
    RobotKind,
    Stage,
    Task,
)


@dataclass(frozen=True)
class StageSpec:
    """One stage: ``"module:function"`` that runs it, the stages whose artifacts it reads, what
    it writes (for ``--help`` and the plan), and whether it publishes to a real arm's valves."""

    runs: str
    consumes: tuple[Stage, ...] = ()
    produces: str = ""
    drives_arm: bool = False
    plans_itself: bool = False  # runs other stages' jobs itself: prints its own plan (dry_run)


STAGES: dict[Stage, StageSpec] = {
    Stage.collect: StageSpec("pipeline.stages.collect:collect", (),
                             "commands, mocap and runs tables", drives_arm=True),
    Stage.align: StageSpec("pipeline.stages.align:align", (Stage.collect,),
                           "aligned runs at the command times"),
    Stage.fit_model: StageSpec("pipeline.stages.fit_model:fit_model", (Stage.align,),
                               "the learned model, its losses and metrics"),
    Stage.train_ppo: StageSpec("pipeline.stages.train_ppo:train_ppo", (Stage.fit_model,),
                               "policy checkpoints and training metrics"),
    Stage.evaluate: StageSpec("pipeline.stages.evaluate:evaluate", (Stage.train_ppo,),
                              "evaluation tables and the report"),
    Stage.twin: StageSpec("pipeline.stages.twin:twin", (), "nothing: a ROS 2 server"),
    Stage.guard: StageSpec("pipeline.stages.guard:guard", (), "nothing: a ROS 2 server",
                           drives_arm=True),
    Stage.control: StageSpec("pipeline.stages.control:control", (Stage.train_ppo,),
                             "a control session's records and report", drives_arm=True),
    Stage.calibrate: StageSpec("pipeline.stages.calibrate:calibrate", (Stage.align,),
                               "the simulated arm's fitted physics"),
    Stage.adapt: StageSpec("pipeline.stages.adapt:adapt", (Stage.train_ppo,),
                           "a calibration walk, the calibrated model and the fine-tuned policy",
                           drives_arm=True),
    Stage.improve: StageSpec("pipeline.stages.improve:improve", (Stage.train_ppo,),
                             "rounds of sessions on the arm, refitted models, retrained "
                             "policies and the rounds' table", drives_arm=True,
                             plans_itself=True),
}
# what `stage=all` runs, in order (the digital twin and the guard are servers, started on their own)
CHAIN = (Stage.collect, Stage.align, Stage.fit_model, Stage.train_ppo, Stage.evaluate)
# stages outside the chain that read its data: the part of the chain they need first
UPSTREAM: dict[Stage, tuple[Stage, ...]] = {Stage.calibrate: (Stage.collect, Stage.align)}
# Stages that publish to a real arm's valves (robot=ros2): each runs only when asked for by name.
DRIVES_ARM = frozenset(stage for stage, spec in STAGES.items() if spec.drives_arm)
CROSS_MODEL_DIRECTIONS = ("A->B", "B->A")
# robots whose data is imported from recordings, not collected
IMPORT_KINDS = (RobotKind.sorolex_csv, RobotKind.plotjuggler_csv, RobotKind.rosbag)


def stage_function(stage: Stage) -> Any:
    """The function that runs ``stage`` (imported when asked for: a stage that composes others'
    jobs, as ``improve`` does, runs them through this, never importing them)."""
    module_name, function_name = STAGES[stage].runs.split(":")
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


# ---------------------------------------------------------------------------------------------
# fan-out: the configs one stage of a run stands for
# ---------------------------------------------------------------------------------------------
def model_protocol(cfg: Any) -> ModelProtocol:
    """``cv`` or ``split``: ``dataset.protocol``, ``auto`` resolved by the robot (split for the
    simulated arm, cv for recorded data)."""
    value = ModelProtocol(cfg.dataset.protocol)
    if value is ModelProtocol.auto:
        simulated = RobotKind(cfg.robot.kind) is RobotKind.sim
        value = ModelProtocol.split if simulated else ModelProtocol.cv
    return value


def ensemble_configs(cfg: Any) -> list[Any]:
    """The configs of the ensemble's further fit_model artifacts (``env.ensemble_seeds``): ``cfg``
    with ``model.seed + 1``, ..., ``model.seed + ensemble_seeds - 1``.

    With ``model.init_from`` (a warm start) member ``i`` starts from its entry ``i``.
    A further member is only trained in, never scored on its own: where ``cfg``'s model is
    scored leave-one-run-out (``cv``), the member trains its model on all the runs alone
    (``split`` with every run for training), since the folds score the recipe once, in ``cfg``'s
    own fit, and fitting them again for each seed would only multiply the time."""
    if EnvName(cfg.env.name) is not EnvName.learned:
        return []
    seed = int(cfg.model.seed)
    member: dict[str, Any] = {}
    if model_protocol(cfg) is ModelProtocol.cv:
        member["dataset"] = {"protocol": ModelProtocol.split.value, "train_fraction": 1.0}
    starts = list(cfg.model.get("init_from") or [])
    members = []
    for offset in range(1, int(cfg.env.get("ensemble_seeds", 1))):
        model: dict[str, Any] = {"seed": seed + offset}
        if starts:  # each member starts from its own entry
            model["init_from"] = [starts[offset]] if offset < len(starts) else []
        members.append(OmegaConf.merge(cfg, {**member, "model": model}))
    return members


def _agent_file(name: str) -> Any:
    """The settings of agent option ``name`` (``conf/agent/<name>.yaml``, its defaults list
    dropped)."""
    path = PROJECT_ROOT / "conf" / "agent" / f"{name}.yaml"
    if not path.is_file():
        options = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise ValueError(f"evaluation.policies: no agent config {name!r}; options: {options}")
    node = OmegaConf.load(path)
    node.pop("defaults", None)
    return node


def agent_option(name: str, base: Any) -> Any:
    """The agent of option ``name`` with what ``base`` (the composed ``agent``) changed.

    The option file (``conf/agent/<name>.yaml``) says what makes the policy type (name,
    trainer, recurrent, its budget, ...). What the composed agent holds beyond its own option
    file (an experiment's seeds and budget, a command line's settings) is laid over it, as when
    the option is chosen (``agent=<name>`` with the same experiment and overrides): an option
    laid over the composed agent is the agent that choosing it gives, whichever option the
    composed one is.
    """
    defaults = OmegaConf.structured(AgentConfig)
    own = (OmegaConf.merge(defaults, _agent_file(str(base.name)))
           if (PROJECT_ROOT / "conf" / "agent" / f"{base.name}.yaml").is_file() else defaults)
    changed = {key: base[key] for key in base if key not in own or base[key] != own[key]}
    return OmegaConf.merge(defaults, _agent_file(name), changed)


def policy_configs(cfg: Any) -> dict[str, Any]:
    """One full config per evaluated policy type: ``cfg`` with its ``agent`` replaced."""
    variants = {}
    for name in cfg.evaluation.policies:
        variant = cfg.copy()
        variant.agent = agent_option(name, cfg.agent)
        variants[name] = variant
    return variants


def reaching_configs(cfg: Any) -> dict[str, Any]:
    """The reaching baseline of a tracking evaluation (``env.task=track`` with
    ``evaluation.reaching``): one config per evaluated policy type, that of
    :func:`policy_configs` with ``env.task=reach`` and no preview; empty otherwise."""
    evaluation, env = cfg.get("evaluation"), cfg.get("env")
    if (evaluation is None or env is None or not evaluation.get("reaching")
            or Task(str(env.get("task", Task.reach))) is not Task.track):
        return {}
    variants = {}
    for name, variant in policy_configs(cfg).items():
        variant.env = OmegaConf.merge(variant.env, {"task": "reach", "preview": 0})
        variants[name] = variant
    return variants


def control_policy_config(cfg: Any) -> Any:
    """The config that trained ``control.policy``: ``cfg`` with that agent option laid over its
    ``agent`` (as :func:`policy_configs` does for evaluate)."""
    variant = cfg.copy()
    variant.agent = agent_option(str(cfg.control.policy), cfg.agent)
    return variant


def control_hold(cfg: Any) -> tuple[float, float, float]:
    """The hold ``stage=control`` deploys its policy with, ``(deadband_m [m], hold_gain,
    hold_backoff)``: ``env.deadband_m``, ``env.hold_gain`` and ``env.hold_backoff`` for goals;
    ``(0, 0, 1)`` following a reference (``control.trajectory``, ``control.trajectory_topic``),
    which moves on; the gain 0 where the radius is (nothing to hold within) and the backoff 1
    where the gain is (nothing to back off)."""
    following = cfg.control.trajectory is not None or cfg.control.get("trajectory_topic")
    deadband = 0.0 if following else float(cfg.env.get("deadband_m") or 0.0)
    gain = float(cfg.env.get("hold_gain") or 0.0) if deadband else 0.0
    backoff = float(cfg.env.get("hold_backoff", 1.0)) if gain else 1.0
    return deadband, gain, backoff


def cross_model_groups(cfg: Any) -> tuple[list[str], list[str]] | None:
    """The two disjoint groups of recordings (names) of the cross-model protocol, or None where
    it does not run. ``evaluation.cross_model``: true runs it (an error where it cannot), false
    does not, null runs it for recorded data in the learned env with at least two recordings a
    group (fit_model scores each group's model leave-one-run-out). Group A is
    ``evaluation.cross_model_group_a`` (names), or every other of the sorted recordings; B the
    rest."""
    evaluation = cfg.get("evaluation")
    setting = None if evaluation is None else evaluation.get("cross_model")
    if setting is False or evaluation is None:
        return None
    recorded = RobotKind(cfg.robot.kind) in IMPORT_KINDS
    if not recorded or EnvName(cfg.env.name) is not EnvName.learned:
        if setting:
            raise ConfigError(
                f"evaluation.cross_model=true needs recorded data (robot.kind one of "
                f"{[kind.value for kind in IMPORT_KINDS]}) and env=learned; this config has "
                f"robot.kind={RobotKind(cfg.robot.kind).value}, env.name="
                f"{EnvName(cfg.env.name).value}")
        return None
    names = [path.name for path in list_recordings(cfg.robot)]
    chosen = [str(name) for name in evaluation.get("cross_model_group_a") or []]
    unknown = [name for name in chosen if name not in names]
    if unknown:
        raise ConfigError(f"evaluation.cross_model_group_a: {unknown} are not among the "
                          f"recordings {names}")
    first = [name for name in names if name in chosen] if chosen else names[0::2]
    second = [name for name in names if name not in first]
    if min(len(first), len(second)) < 2:
        if setting:
            raise ConfigError(
                f"evaluation.cross_model=true: each group needs at least two recordings (its "
                f"model is scored leave-one-run-out); group A {first}, group B {second}")
        return None
    return first, second


def cross_model_group_config(cfg: Any, names: list[str]) -> Any:
    """``cfg`` restricted to the recordings ``names`` (its own data, model and policies), without
    a cross-model protocol of its own; its policies train with the protocol's own budget
    (``evaluation.cross_model_seeds``, ``evaluation.cross_model_budget``)."""
    evaluation, agent = cfg.evaluation, cfg.agent
    budget = float(evaluation.get("cross_model_budget", 1.0))
    seeds = evaluation.get("cross_model_seeds")
    trained = {"num_seeds": int(agent.num_seeds if seeds is None else seeds)}
    if budget != 1.0:
        trained.update({name: max(1, round(budget * int(agent[name])))
                        for name in ("total_timesteps", "recurrent_total_timesteps")
                        if agent.get(name) is not None})
    return OmegaConf.merge(cfg, {"robot": {"files": list(names), "num_runs": None},
                                 "evaluation": {"cross_model": False, "models": []},
                                 "agent": trained})


def cross_model_folds(cfg: Any) -> dict[str, tuple[Any, Any]]:
    """The cross-model protocol by direction (``A->B``, ``B->A``): the config that trains in one
    group's model and the config of the other group, whose model it is evaluated in. Empty
    where the protocol does not run (:func:`cross_model_groups`)."""
    groups = cross_model_groups(cfg)
    if groups is None:
        return {}
    first, second = (cross_model_group_config(cfg, names) for names in groups)
    return dict(zip(CROSS_MODEL_DIRECTIONS, ((first, second), (second, first)), strict=True))


# ---------------------------------------------------------------------------------------------
# the plan
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Job:
    """One stage run of a plan.

    stage: what runs; cfg: the config it runs with; label: what sets it apart from the stage's
    own run (empty for that one, e.g. ``model.seed=1``, ``ppo_rnn``, ``cross-model A->B``);
    result: whether its artifact is the stage's result of the run (the requested config's own
    run); parallel: jobs of one such group (consecutive, same non-empty value) may run at once.
    """

    stage: Stage
    cfg: Any
    label: str = ""
    result: bool = True
    parallel: str = ""


def model_jobs(cfg: Any, prefix: str = "", result: bool = True) -> list[Job]:
    """fit_model for ``cfg`` and for the ensemble's further model seeds (one after another)."""
    return [Job(Stage.fit_model, cfg, prefix.rstrip(", "), result)] + [
        Job(Stage.fit_model, member, f"{prefix}model.seed={int(member.model.seed)}", False)
        for member in ensemble_configs(cfg)]


def policy_jobs(cfg: Any, key_of, prefix: str = "", result: bool = True, *,
                own_agent: bool) -> list[Job]:
    """train_ppo for each policy type of ``evaluation.policies`` and the reaching baseline's
    (one job per distinct artifact key, ``key_of(cfg)``; they may run side by side), and, with
    ``own_agent``, first for ``cfg``'s own agent (the whole chain trains it; evaluate reads only
    the policies it compares)."""
    variants = {**({str(cfg.agent.name): cfg} if own_agent else {}), **policy_configs(cfg),
                **{f"{name} (reaching)": variant
                   for name, variant in reaching_configs(cfg).items()}}
    jobs, seen = [], set()
    for name, variant in variants.items():
        key = key_of(variant)
        if key in seen:
            continue
        seen.add(key)
        own = not jobs
        jobs.append(Job(Stage.train_ppo, variant, f"{prefix}{name}", result and own,
                        parallel=f"{prefix}train_ppo"))
    return jobs


def cross_model_jobs(cfg: Any, key_of) -> list[Job]:
    """For each direction of the cross-model protocol: the data, models (and ensemble) and every
    policy type of the group its policies train in."""
    jobs = []
    for direction, (train, _) in cross_model_folds(cfg).items():
        prefix = f"cross-model {direction}, "
        jobs += [Job(Stage.collect, train, prefix.rstrip(", "), False),
                 Job(Stage.align, train, prefix.rstrip(", "), False),
                 *model_jobs(train, prefix, result=False),
                 *policy_jobs(train, key_of, prefix, result=False, own_agent=False)]
    return jobs


def plan(cfg: Any, key_of) -> list[Job]:
    """The jobs of a run of ``cfg``, in order. Upstream of the requested stage every config has
    ``force=false`` (``force=true`` recomputes the requested stage only; every stage for
    ``all``); fit_model upstream of a training also fits the ensemble's further seeds; training
    upstream of evaluate trains every policy type it compares (the run's own agent only where
    it is one of them; the whole chain trains it besides), and the cross-model groups'.
    ``key_of(cfg)``: the train_ppo artifact key of a config (policy types that share a key train
    once)."""
    stage = Stage(cfg.stage)
    upstream_cfg = cfg
    if stage is not Stage.all:
        upstream_cfg = cfg.copy()
        upstream_cfg.force = False
    jobs: list[Job] = []
    for name in stages_to_run(cfg):
        stage_cfg = cfg if name is stage else upstream_cfg
        if name is Stage.train_ppo and stage in (Stage.all, Stage.evaluate):
            jobs += policy_jobs(stage_cfg, key_of, own_agent=stage is Stage.all)
            jobs += cross_model_jobs(stage_cfg, key_of)
        elif name is Stage.fit_model and stage is not Stage.fit_model:
            jobs += model_jobs(stage_cfg)
        else:
            jobs.append(Job(name, stage_cfg))
    return jobs
