"""What determines each stage's artifact: its spec (the config it reads) and its inputs (the keys
of the upstream artifacts it reads), hashed into the artifact key (:func:`artifact_key`).

One place for the whole lineage, so that a stage finds its inputs from the config alone without
importing the stage that made them, and sweeps share upstream artifacts.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from pipeline.arm.twins import twin_physics
from pipeline.chain import (
    IMPORT_KINDS,
    control_hold,
    control_policy_config,
    cross_model_folds,
    ensemble_configs,
    model_protocol,
    policy_configs,
    reaching_configs,
)
from pipeline.data.importers import file_digest, list_recordings, recording_digest
from pipeline.infra.artifacts import MANIFEST, artifact_key
from pipeline.schemas import (
    TRACK_EVALUATION_SETTINGS,
    TRACK_SETTINGS,
    AgentConfig,
    ConfigError,
    EnvName,
    ModelProtocol,
    RobotKind,
    StopAt,
    Task,
    incremental_actions,
)

Spec = tuple[dict[str, Any], dict[str, str]]

# How a ROS 2 session runs, not what it records: kept out of the key (so that, e.g.,
# robot.reuse_incomplete=true finds the interrupted artifact it is meant to reuse).
_ROS2_OPERATIONAL = ("node_name", "domain_id", "startup_timeout_s", "flush_every_s",
                     "stop_timeout_s", "reuse_incomplete", "rehearsal", "rehearsal_domain_id")
# Checks of the commands and data, not what is recorded: a run that passes them records the same
# data whatever they are (the limits, which shape the commands, stay in the key).
_SAFETY_ONLY = ("rating", "workspace", "command_timeout_s", "guard", "safety_bounds",
                "max_missed_periods", "max_pose_latency_s", "max_clock_offset_s")
# the dataset settings of the model (alignment has its own key); the split's only for it
_MODEL_DATASET_KEYS = ("model_hz", "model_grid", "window", "stride", "order")
_SPLIT_KEYS = ("train_fraction", "split_seed")
# agent fields that do not change the result (display only)
_NON_DETERMINING_AGENT_KEYS = ("progress",)
# env settings of deployment only (the hold near the goal): training never meets them
_DEPLOYMENT_ONLY_ENV = ("deadband_m", "hold_gain", "hold_backoff")
# agent settings kept out of the key at these values (their default: training as before they
# existed), so that the artifacts made before them keep their keys
_AGENT_KEYS_UNLESS_SET = {"trainer": "ppo", "stop_at": dataclasses.asdict(StopAt())}


# The version of each stage's spec. A change to what a stage's artifact holds or to how its spec is
# formed (a new setting, a setting renamed) raises that stage's number: every artifact of the
# stage, and through their input keys every artifact downstream, is then made anew, once. Every
# setting of the composed config is in its stage's spec with its value, defaults included.
SPEC_VERSIONS = {"collect": 2, "align": 2, "calibrate": 2, "fit_model": 3, "train_ppo": 3,
                 "evaluate": 7, "control": 4, "adapt": 1, "explore": 1, "improve": 1}


def _container(node: Any) -> Any:
    return OmegaConf.to_container(node, resolve=True)


def _versioned(stage: str, spec: dict[str, Any]) -> dict[str, Any]:
    return {"spec_version": SPEC_VERSIONS[stage], **spec}


def collect_spec(cfg: Any) -> Spec:
    """The raw data: the robot and, where it is driven, the exploration."""
    robot = _container(cfg.robot)
    for setting in _SAFETY_ONLY:
        robot.pop(setting, None)
    kind = RobotKind(cfg.robot.kind)
    if kind in IMPORT_KINDS:
        # Imported data is keyed by its content, not by where it lies.
        for where in ("data_dir", "pattern", "files", "num_runs"):
            robot.pop(where, None)
        files = {p.name: recording_digest(p) for p in list_recordings(cfg.robot)}
        return _versioned("collect", {"robot": robot, "files": files}), {}
    if kind is RobotKind.ros2:
        for setting in _ROS2_OPERATIONAL:
            robot.pop(setting, None)
    if robot.get("replay"):
        # replayed commands are keyed by the recordings' content, not by where they lie
        robot["replay"] = {"kind": robot["replay"]["kind"], "files": {
            p.name: recording_digest(p) for p in list_recordings(cfg.robot.replay)}}
    return _versioned("collect", {"robot": robot, "exploration": _container(cfg.exploration)}), {}


def session_inputs(cfg: Any) -> dict[str, str]:
    """The session artifacts of ``dataset.sessions`` (keys or folders) by input name,
    ``session/<key>``: their keys (a folder's name), whatever the order they are named in."""
    entries = [str(entry) for entry in cfg.dataset.get("sessions") or []]
    names = [Path(entry).name for entry in entries]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ConfigError(f"dataset.sessions: {repeated} named more than once")
    return {f"session/{name}": name for name in names}


def align_spec(cfg: Any) -> Spec:
    """The alignment settings; the collected data and the sessions that join it
    (``dataset.sessions``) are the inputs."""
    return (_versioned("align", {"align": _container(cfg.dataset.align)}),
            {"collect": artifact_key(*collect_spec(cfg)), **session_inputs(cfg)})


def calibrate_spec(cfg: Any) -> Spec:
    """The simulator fitted to the aligned runs: the calibration settings and the rate its
    errors are scored at."""
    spec = _versioned("calibrate", {"calibration": _container(cfg.calibration),
                                    "dataset": {"model_hz": float(cfg.dataset.model_hz)}})
    return spec, {"align": artifact_key(*align_spec(cfg))}


def fit_model_spec(cfg: Any) -> Spec:
    dataset = _container(cfg.dataset)
    protocol = model_protocol(cfg)
    chosen = _MODEL_DATASET_KEYS + (_SPLIT_KEYS if protocol is ModelProtocol.split else ())
    model = _container(cfg.model)
    if not model.get("pressure_transients"):  # off: the keys of the models made before it
        model.pop("pressure_transients", None)
    starts = model.pop("init_from", None) or []  # a warm start: the starting model's key decides
    chosen_dataset = {k: dataset[k] for k in chosen}
    if dataset.get("sessions") and float(dataset.get("session_weight", 1.0)) != 1.0:
        chosen_dataset["session_weight"] = float(dataset["session_weight"])
    spec = _versioned("fit_model", {
        "model": model, "dataset": {**chosen_dataset, "protocol": protocol.value}})
    inputs = {"align": artifact_key(*align_spec(cfg))}
    if starts:
        inputs["init_from"] = Path(str(starts[0])).name
    return spec, inputs


def env_spec(cfg: Any) -> dict[str, Any]:
    """``cfg.env`` as keys see it: without ``env.models`` (where those lie does not matter, their
    keys are inputs), without ``env.train_max_steps`` where unset, ``env.deadband_m`` where 0,
    ``env.hold_gain`` where it does not act and ``env.hold_backoff`` where it does not act or
    is 1 (the keys of before), for absolute actions
    without the incremental step, to reach without the tracking task's settings (unused) and to
    track without ``env.reference_integral_gain`` and its bound where the gain is 0."""
    env = _container(cfg.env)
    env.pop("models", None)
    if env.get("train_max_steps") is None:  # unset: training's horizon is max_steps, as before
        env.pop("train_max_steps", None)
    if not env.get("deadband_m"):  # off: every controller acts as before it existed
        env.pop("deadband_m", None)
    if not (env.get("hold_gain") and env.get("deadband_m")):  # no hold: the keys as before
        env.pop("hold_gain", None)
        env.pop("hold_backoff", None)
    if env.get("hold_backoff") == 1:  # a fixed gain: the hold as before it backed off
        env.pop("hold_backoff", None)
    if Task(env.get("task", Task.reach)) is Task.reach:
        for setting in TRACK_SETTINGS:
            env.pop(setting, None)
    elif not env.get("reference_integral_gain"):  # no integral action: the keys of before
        env.pop("reference_integral_gain", None)
        env.pop("reference_shift_max_mm", None)
    if not incremental_actions(env):
        env.pop("action_step_kpa", None)
    return env


def ensemble_entries(cfg: Any) -> dict[str, str]:
    """The ensemble's further members by input name: the fit_model keys of
    :func:`ensemble_configs`, then ``env.models`` (folders or keys; ``ArtifactStore.resolve``
    reads both). Empty without an ensemble."""
    if EnvName(cfg.env.name) is not EnvName.learned:
        return {}
    entries = {f"fit_model/seed+{offset}": artifact_key(*fit_model_spec(member))
               for offset, member in enumerate(ensemble_configs(cfg), start=1)}
    for entry in cfg.env.get("models") or []:
        entries[f"fit_model/{Path(str(entry)).name}"] = str(entry)
    return entries


def train_ppo_spec(cfg: Any) -> Spec:
    """The policies: env, agent, seed and, by env, the robot or the model (and the ensemble's
    further models)."""
    agent = _container(cfg.agent)
    for name in _NON_DETERMINING_AGENT_KEYS:
        agent.pop(name, None)
    for name, unset in _AGENT_KEYS_UNLESS_SET.items():
        if name in agent and agent[name] == unset:
            agent.pop(name)
    if "hold_tune" in agent and not AgentConfig.from_any(cfg.agent).hold_tune_timesteps:
        agent.pop("hold_tune")  # no such phase for this policy type: the key as without it
    env = env_spec(cfg)
    for setting in _DEPLOYMENT_ONLY_ENV:
        env.pop(setting, None)
    spec: dict[str, Any] = _versioned("train_ppo", {"env": env, "agent": agent,
                                                    "seed": int(cfg.seed)})
    if agent.get("init_policy"):  # a warm start: the starting policy's content decides too
        from pipeline.rl.policy_io import init_policy_file  # JAX only where a policy is read

        path = init_policy_file(agent["init_policy"])
        spec["init_policy_sha256"] = file_digest(path)
    plant, inputs = env_plant_spec(cfg)
    spec.update(plant)
    return spec, inputs


def env_plant_spec(cfg: Any) -> Spec:
    """What the environment steps, by env: the robot (``env.name=sim``), or the limits, the
    control rate, the model and the ensemble's further models (``learned``); nothing for the
    others."""
    env_name = EnvName(cfg.env.name)
    spec: dict[str, Any] = {}
    inputs: dict[str, str] = {}
    if env_name is EnvName.sim:
        spec["robot"] = _container(cfg.robot)
        spec["model_hz"] = float(cfg.dataset.model_hz)
    elif env_name is EnvName.learned:
        spec["limits"] = _container(cfg.robot.limits)
        spec["control_hz"] = float(cfg.robot.control_hz)
        inputs["fit_model"] = artifact_key(*fit_model_spec(cfg))
        inputs.update({name: Path(entry).name for name, entry in ensemble_entries(cfg).items()})
    return spec, inputs


def evaluation_twins(cfg: Any) -> dict[str, dict[str, Any]]:
    """The calibrated twins of ``evaluation.twins`` by name (a robot config's name, or the
    calibrate artifact's folder name or key): their SimPhysics values."""
    evaluation = cfg.get("evaluation")
    twins = {}
    for entry in (evaluation.get("twins") if evaluation is not None else None) or []:
        name = Path(str(entry)).name
        if name in twins:
            raise ConfigError(f"evaluation.twins: {name!r} is named twice")
        twins[name] = twin_physics(str(entry), cfg.paths.artifact_dir)
    return twins


def evaluate_spec(cfg: Any) -> Spec:
    """The evaluation settings and env, and what the env steps (the baselines act in it whatever
    the policies); the policies, the other models (``evaluation.models``) and, for the
    cross-model protocol, each group's policies and the model they meet."""
    plant, inputs = env_plant_spec(cfg)
    spec = _versioned("evaluate", {"evaluation": _container(cfg.evaluation),
                                   "env": env_spec(cfg), "plant": plant})
    inputs.update({f"train_ppo/{name}": artifact_key(*train_ppo_spec(variant))
                   for name, variant in policy_configs(cfg).items()})
    spec["evaluation"].pop("models", None)  # where they lie does not matter, their keys do
    if "task" not in spec["env"]:  # reaching: the tracking evaluation does not run
        for setting in TRACK_EVALUATION_SETTINGS:
            spec["evaluation"].pop(setting, None)
    for name, entry in (spec["evaluation"].get("references") or {}).items():
        spec["evaluation"]["references"][name] = _reference_content(entry)
    for entry in cfg.evaluation.models:
        inputs[f"fit_model/{Path(str(entry)).name}"] = Path(str(entry)).name
    # a twin is its physics, wherever they were read from
    spec["evaluation"].pop("twins", None)
    if cfg.evaluation.get("twins"):
        spec["evaluation"]["twins"] = evaluation_twins(cfg)
    # the groups' policies and models decide the cross-model results, not how they were chosen
    for setting in ("cross_model", "cross_model_group_a"):
        spec["evaluation"].pop(setting, None)
    for name, variant in reaching_configs(cfg).items():
        inputs[f"reaching/train_ppo/{name}"] = artifact_key(*train_ppo_spec(variant))
    for direction, (train, test) in cross_model_folds(cfg).items():
        for name, variant in policy_configs(train).items():
            inputs[f"cross_model/{direction}/train_ppo/{name}"] = artifact_key(
                *train_ppo_spec(variant))
        inputs[f"cross_model/{direction}/fit_model"] = artifact_key(*fit_model_spec(test))
        for name, variant in reaching_configs(train).items():
            inputs[f"cross_model/{direction}/reaching/train_ppo/{name}"] = artifact_key(
                *train_ppo_spec(variant))
    return spec, inputs


# the stages whose artifacts hold a policy stage=control can drive with
POLICY_STAGES = ("train_ppo", "adapt")


def control_policy(cfg: Any) -> tuple[str, str]:
    """``(stage, key)`` of the artifact of the policy ``stage=control`` runs: that of
    ``control.policy_file``'s artifact folder (a train_ppo or an adapt artifact), else the
    train_ppo artifact of ``control.policy`` under this config."""
    if cfg.control.policy_file:
        path = Path(str(cfg.control.policy_file))
        manifest = path.parent / MANIFEST
        if not path.is_file():
            raise FileNotFoundError(f"control.policy_file: no file at {path}")
        stage = (json.loads(manifest.read_text()).get("stage") if manifest.is_file() else None)
        if stage not in POLICY_STAGES:
            raise ValueError(f"control.policy_file={path} is not inside a train_ppo or adapt "
                             f"artifact (no such {MANIFEST} beside it): the environment it was "
                             f"trained in, hence its observation, cannot be rebuilt")
        return str(stage), str(json.loads(manifest.read_text())["key"])
    return "train_ppo", artifact_key(*train_ppo_spec(control_policy_config(cfg)))


def control_policy_key(cfg: Any) -> str:
    """The key of the artifact of the policy ``stage=control`` runs (:func:`control_policy`)."""
    return control_policy(cfg)[1]


# settings of stage=control that do not change what is commanded
_CONTROL_OPERATIONAL = ("policy", "policy_file", "goals_csv", "flush_every_s", "node_name")


def control_spec(cfg: Any) -> Spec:
    """A control session: the policy (its train_ppo or adapt key), the goals, the robot and its session
    label (``robot.session`` on ROS 2; a new label runs anew)."""
    control = _container(cfg.control)
    for setting in _CONTROL_OPERATIONAL:
        control.pop(setting, None)
    if cfg.control.goals_csv:
        control["goals_csv_sha256"] = file_digest(Path(str(cfg.control.goals_csv)))
    _control_trajectory(cfg, control)
    robot = _session_robot(cfg)
    if RobotKind(cfg.robot.kind) is RobotKind.ros2:
        control.pop("arm_seed", None)
    stage, policy_key = control_policy(cfg)
    spec = {"control": control, "robot": robot}
    deadband, hold_gain, hold_backoff = control_hold(cfg)
    if deadband:  # off: the key as before it existed
        spec["deadband_m"] = deadband
    if hold_gain:  # the last command held: the key of the deadband as before
        spec["hold_gain"] = hold_gain
    if hold_backoff != 1:  # a fixed gain: the key of the hold as before
        spec["hold_backoff"] = hold_backoff
    return _versioned("control", spec), {stage: policy_key}


def _reference_content(entry: Any) -> Any:
    """A reference's settings as keys see them: a replayed CSV by its content, not its path."""
    if isinstance(entry, Mapping) and entry.get("file") is not None:
        path = Path(str(entry["file"]))
        digest = file_digest(path) if path.is_file() else None
        entry = {**{k: v for k, v in entry.items() if k != "file"}, "file_sha256": digest}
    return entry


def _control_trajectory(cfg: Any, control: dict[str, Any]) -> None:
    """The reference of ``control.trajectory`` as the key sees it, in ``control``: none
    (goals: the key as before), else the shape it names in ``evaluation.references`` or a CSV's
    content, and the evaluation's timing it defaults to."""
    trajectory = control.pop("trajectory", None)
    if not control.get("trajectory_topic"):  # unset: the key as before it existed
        control.pop("trajectory_topic", None)
    elif trajectory is None:  # a live reference: scored with the evaluation's settle time
        control["trajectory"] = {"tracking_settle_seconds":
                                 cfg.evaluation.tracking_settle_seconds}
        return
    if trajectory is None:
        control.pop("settle_s", None)
        return
    evaluation = cfg.evaluation
    if isinstance(trajectory, str) and trajectory in (evaluation.references or {}):
        entry = evaluation.references[trajectory]
        trajectory = {"name": trajectory,
                      **_reference_content(_container(entry) if entry is not None else {})}
    elif isinstance(trajectory, Mapping):
        trajectory = _reference_content(trajectory)
    elif isinstance(trajectory, str) and Path(trajectory).is_file():
        trajectory = {"csv_sha256": file_digest(Path(trajectory))}
    control["trajectory"] = {"reference": trajectory,
                             "tracking_seconds": evaluation.tracking_seconds,
                             "tracking_settle_seconds": evaluation.tracking_settle_seconds}


def _session_robot(cfg: Any) -> dict[str, Any]:
    """The robot as a session's key sees it: on ROS 2 without how the link runs nor the twin's
    settings (another process), with the session label (``robot.session``: a new label runs
    anew)."""
    robot = _container(cfg.robot)
    if RobotKind(cfg.robot.kind) is RobotKind.ros2:
        for setting in (*_ROS2_OPERATIONAL, "twin"):
            robot.pop(setting, None)
    return robot


def adapt_spec(cfg: Any) -> Spec:
    """The deployed policy calibrated to a session: the adapt settings, the walk (exploration,
    alignment), the robot's session (robot=sim: ``control.arm_seed``) and the policy's seed; the
    deployed policy (its train_ppo key) is the input."""
    stage, policy_key = control_policy(cfg)
    if stage != "train_ppo":
        raise ConfigError(f"adapt: control.policy_file={cfg.control.policy_file} is an adapted "
                          f"policy (an {stage} artifact); adapt the train_ppo policy it came "
                          f"from")
    spec = {"adapt": _container(cfg.adapt), "robot": _session_robot(cfg),
            "exploration": _container(cfg.exploration), "align": _container(cfg.dataset.align),
            "policy_seed": cfg.control.seed}
    if RobotKind(cfg.robot.kind) is not RobotKind.ros2:
        spec["arm_seed"] = int(cfg.control.arm_seed)
    return _versioned("adapt", spec), {"train_ppo": policy_key}


def explore_spec(drive: Any, candidates: Any, walk: int) -> dict[str, Any]:
    """An exploration walk of ``stage=improve`` (its inputs: the models whose disagreement
    chose it): the arm it is driven on (``drive``: the round's control config), its session
    and the candidate walks' content."""
    digest = hashlib.sha256(np.ascontiguousarray(candidates, np.float64).tobytes()).hexdigest()
    return _versioned("explore", {"robot": _session_robot(drive),
                                  "arm_seed": int(drive.control.arm_seed), "walk": int(walk),
                                  "candidates_sha256": digest,
                                  "candidates_shape": list(np.shape(candidates))})


def improve_round_spec(settings: Any, index: int) -> dict[str, Any]:
    """A round of ``stage=improve``: its settings (but the number of rounds, so that more
    rounds extend a run) and its index; the steps' artifacts are its inputs."""
    values = dataclasses.asdict(settings)
    values.pop("rounds", None)
    return _versioned("improve", {"improve": values, "round": int(index)})


SPECS = {"collect": collect_spec, "align": align_spec, "fit_model": fit_model_spec,
         "train_ppo": train_ppo_spec, "evaluate": evaluate_spec, "control": control_spec,
         "calibrate": calibrate_spec, "adapt": adapt_spec}


def key(stage: str, cfg: Any) -> str:
    """The artifact key of ``stage`` under ``cfg``."""
    return artifact_key(*SPECS[stage](cfg))
