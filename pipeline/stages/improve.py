"""Stage ``improve``: the deployed policy and its models learn from the arm they drive, in rounds.

Not part of ``stage=all``: started on its own, after the policy of ``control.policy`` was
trained under this config (``stage=train_ppo``). With ``robot=ros2`` it drives the arm (only
when named, through the guard, after a rehearsal on the twin, as ``stage=control`` does).

Round 0 evaluates the deployed policy. Each round ``r = 1 .. improve.rounds`` then runs, as jobs
of the existing stages (:func:`pipeline.chain.stage_function`), each reused where its artifact
is there, so an interrupted run resumes from the last finished step:

(a) **drive**: ``stage=control`` with the last round's policy on the arm (``improve.plant``, a
    simulated arm as ``evaluation.twins`` names one, else ``robot``): goals drawn from its
    training goals, each held ``improve.goal_s``, for ``(1 - improve.explore_share)`` of
    ``improve.arm_s``; the rest on walks where the ensemble of the last round's models disagrees
    most (:mod:`pipeline.dynamics.disagreement`), ``explore`` artifacts driven through the same
    gate. Each is a session artifact (:mod:`pipeline.data.sessions`);
(b) **refit**: ``align`` and ``fit_model`` (and the ensemble's further seeds) with every session
    so far in ``dataset.sessions``, each model warm started from the last round's
    (``improve.refit=warm``) or fitted anew, every run training it (``dataset.protocol=split``;
    the collected runs' held-out split kept);
(c) **retrain**: ``train_ppo`` in the refitted models, warm started from the last round's policy,
    for ``improve.policy_timesteps``;
(d) **evaluate**: ``evaluate`` of the new policy in its model and on the plant (the simulated
    arm, or the twin ``improve.plant``), the preload its baseline.

Each round writes an ``improve`` artifact keyed by its inputs (the last round's and the new
policy's, models', sessions' and evaluation's keys): ``rounds.parquet`` (one row per round so
far, :mod:`pipeline.evaluation.rounds`), ``rounds.png`` and ``report.md``. ``dry_run=true`` logs
the plan: every step's artifact key and whether it is reused or runs.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import chain, keys
from pipeline.arm.exploration import exploration_plan
from pipeline.arm.twins import twin_physics
from pipeline.data.sessions import arm_identity, session_run_id, walk_tables, write_session
from pipeline.dynamics.checkpoints import load_dynamics
from pipeline.dynamics.disagreement import disagreement_m2, held_at_model_rate, most_disputed
from pipeline.evaluation import rounds as rounds_table
from pipeline.infra.artifacts import Artifact, ArtifactStore, ArtifactWriter, produce
from pipeline.schemas import ConfigError, EnvName, ImproveConfig, RobotKind, SimRobotConfig, Stage
from pipeline.stages._deployed import training_config
from pipeline.stages._environment import config_environment
from pipeline.validation import validate_config

log = logging.getLogger(__name__)
STAGE = "improve"
EXPLORE = "explore"
REFITS = ("warm", "scratch")
EXPLORES = ("disagreement", "walk")


@dataclass
class Round:
    """One round's configs and what they stand for.

    ``index``: 0 the deployed policy, else the round; ``drive``: the control config of its goals
    (None in round 0); ``walks``: the exploration walks' commands ``[N, valves]`` kPa;
    ``cfg``: the config of its data, models and policy; ``evaluation``: its evaluate config."""

    index: int
    cfg: Any
    evaluation: Any
    drive: Any = None
    goals_mm: list[list[float]] = field(default_factory=list)
    walks: list[np.ndarray] = field(default_factory=list)


def improve(cfg: Any) -> Artifact | None:
    """Run the rounds of ``cfg.improve`` (see the module doc); the last round's artifact."""
    validate_config(cfg)
    settings = improve_settings(cfg)
    store = ArtifactStore(cfg.paths.artifact_dir)
    deployed_cfg = chain.control_policy_config(cfg)
    deployed = store.require("train_ppo", keys.key("train_ppo", deployed_cfg), hint=(
        f" with agent={cfg.control.policy}: stage=improve starts from the trained policy of "
        f"control.policy under this config"))
    pool, model_steps_per_command, start_pose = goal_pool(deployed, store, cfg)
    rounds = [first_round(cfg, settings)]
    if cfg.get("dry_run"):
        log.info("improve: dry run, nothing runs\n%s", plan_table(cfg, settings, store, pool))
        return None
    chain.stage_function(Stage.evaluate)(rounds[0].evaluation)  # the deployed policy
    artifact = finish_round(store, settings, rounds[0], None, [])
    sessions: list[str] = []
    for index in range(1, settings.rounds + 1):
        last = rounds[-1]
        current = next_round(cfg, settings, store, last, sessions, pool, index)
        drives = ([chain.stage_function(Stage.control)(current.drive)] if current.goals_mm
                  else [])
        drives += drive_walks(current, last, store, settings, model_steps_per_command,
                              start_pose)
        sessions = [*sessions, *(drive.key for drive in drives)]
        current = next_round(cfg, settings, store, last, sessions, pool, index)
        for job in round_jobs(current):
            chain.stage_function(job.stage)(job.cfg)
        artifact = finish_round(store, settings, current, artifact, drives, last)
        rounds.append(current)
    log.info("improve: the rounds' table in %s", artifact.file("rounds.parquet"))
    return artifact


def improve_settings(cfg: Any) -> ImproveConfig:
    """``cfg.improve`` checked: a bad value is a :class:`ConfigError` naming it, a budget outside
    the arm's rating (``robot.rating.max_session_s``) included."""
    settings = OmegaConf.to_object(cfg.improve)
    rating_s = float(cfg.robot.rating.max_session_s)
    if not (math.isfinite(settings.arm_s) and 0 < settings.arm_s <= rating_s):
        raise ConfigError(f"improve.arm_s={settings.arm_s}: a round's arm time must lie in "
                          f"(0, {rating_s:g}] s, the arm's rating (robot.rating.max_session_s)")
    if settings.rounds < 1:
        raise ConfigError(f"improve.rounds={settings.rounds} must be at least 1")
    if not 0 <= settings.explore_share <= 1:
        raise ConfigError(f"improve.explore_share={settings.explore_share} must lie in [0, 1]")
    if settings.explore not in EXPLORES:
        raise ConfigError(f"improve.explore={settings.explore!r} must be one of {list(EXPLORES)}")
    if settings.explore_candidates < 1 or not settings.explore_walk_s > 0:
        raise ConfigError(f"improve.explore_candidates={settings.explore_candidates} and "
                          f"improve.explore_walk_s={settings.explore_walk_s} must be positive")
    if settings.refit not in REFITS:
        raise ConfigError(f"improve.refit={settings.refit!r} must be one of {list(REFITS)}")
    if EnvName(cfg.env.name) is not EnvName.learned:
        raise ConfigError(f"stage=improve refits the model a policy was trained in: env=learned, "
                          f"not env={cfg.env.name}")
    if cfg.control.policy_file:
        raise ConfigError("stage=improve starts from the trained policy of control.policy under "
                          "this config; leave control.policy_file out")
    kind = RobotKind(cfg.robot.kind)
    if settings.plant is None and kind not in (RobotKind.sim, RobotKind.ros2):
        raise ConfigError(f"stage=improve drives an arm: improve.plant (a simulated robot config "
                          f"or a calibrate artifact) with robot={cfg.robot.name}'s recordings, "
                          f"or robot=sim / robot=ros2")
    if settings.explore_share > 0:
        if settings.plant is None and kind is RobotKind.ros2:
            raise ConfigError("improve.explore_share > 0 drives its walks on in-process arms "
                              "only; on robot=ros2 set improve.explore_share=0")
        if (settings.explore == "disagreement" and int(cfg.env.ensemble_seeds) < 2
                and not cfg.env.models):
            raise ConfigError("improve.explore_share > 0 chooses walks where the ensemble's "
                              "models disagree: set env.ensemble_seeds to 2 or more")
    goal_s = goal_seconds(cfg, settings)
    goals = goal_count(settings, goal_s)
    if goals < 1 and settings.explore_share < 1:
        raise ConfigError(f"improve.arm_s={settings.arm_s} with explore_share="
                          f"{settings.explore_share} leaves no time for one goal of "
                          f"{goal_s:g} s (improve.goal_s)")
    return settings


def goal_seconds(cfg: Any, settings: ImproveConfig) -> float:
    """Arm seconds each goal of a round is held: ``improve.goal_s``, else the env's episode."""
    if settings.goal_s is not None:
        return float(settings.goal_s)
    return int(cfg.env.max_steps) / float(cfg.robot.control_hz)


def goal_count(settings: ImproveConfig, goal_s: float) -> int:
    return int((1.0 - settings.explore_share) * settings.arm_s / goal_s + 1e-9)


def walk_count(settings: ImproveConfig) -> int:
    if settings.explore_share == 0:
        return 0
    return max(1, round(settings.explore_share * settings.arm_s / settings.explore_walk_s))


def candidate_count(settings: ImproveConfig) -> int:
    """Walks drawn for each one driven: the disagreement's candidates, or the walk itself."""
    return int(settings.explore_candidates) if settings.explore == "disagreement" else 1


# ---------------------------------------------------------------------------------------------
# the rounds' configs
# ---------------------------------------------------------------------------------------------
def evaluation_config(cfg: Any, settings: ImproveConfig) -> Any:
    """``cfg``'s evaluation of its policy alone, in its model and on the plant (the twin
    ``improve.plant``, or the simulated arm of ``robot=sim``), the preload its baseline."""
    return OmegaConf.merge(cfg, {"stage": "evaluate", "evaluation": {
        "policies": [str(cfg.control.policy)], "baselines": ["preload"],
        "tracking_baselines": ["preload"], "reaching": False, "cross_model": False,
        "models": [], "num_consecutive_goals": 0,
        "twins": [settings.plant] if settings.plant else []}})


def first_round(cfg: Any, settings: ImproveConfig) -> Round:
    return Round(0, cfg, evaluation_config(cfg, settings))


def round_config(cfg: Any, settings: ImproveConfig, store: ArtifactStore, last: Round,
                 sessions: list[str]) -> Any:
    """The data, models and policy of a round after ``last``: every session so far joined,
    the models warm started from ``last``'s (``improve.refit=warm``), every run training them,
    the policy warm started from ``last``'s."""
    members = [keys.key("fit_model", last.cfg),
               *(keys.key("fit_model", member) for member in chain.ensemble_configs(last.cfg))]
    policy = policy_folder(store, last.cfg)
    dataset: dict[str, Any] = {"sessions": list(sessions)}
    if chain.model_protocol(cfg).value == "cv":  # every run trains, as the cv's final model
        dataset.update({"protocol": "split", "train_fraction": 1.0})
    model: dict[str, Any] = {"init_from": members if settings.refit == "warm" else []}
    if settings.model_steps is not None:
        model["num_steps"] = int(settings.model_steps)
    agent: dict[str, Any] = {"init_policy": str(policy / "policy.msgpack")}
    if settings.policy_timesteps is not None:
        agent.update({"total_timesteps": int(settings.policy_timesteps),
                      "recurrent_total_timesteps": int(settings.policy_timesteps)})
    return OmegaConf.merge(cfg, {"dataset": dataset, "model": model, "agent": agent,
                                 "force": False})


def policy_folder(store: ArtifactStore, cfg: Any) -> Path:
    """Where the train_ppo artifact of ``cfg``'s deployed policy (``control.policy``) lies."""
    return store.path("train_ppo", keys.key("train_ppo", chain.control_policy_config(cfg)))


def plant_robot(cfg: Any, settings: ImproveConfig) -> Any:
    """The arm the rounds drive: ``robot`` itself, or the simulated arm with the physics of
    ``improve.plant`` (the robot's rates, limits, rating and workspace)."""
    if settings.plant is None:
        return cfg.robot
    physics = twin_physics(str(settings.plant), cfg.paths.artifact_dir)
    robot = cfg.robot
    return OmegaConf.merge(OmegaConf.structured(SimRobotConfig), {
        "name": Path(str(settings.plant)).name, "physics": physics,
        "n_valves": robot.n_valves, "control_hz": robot.control_hz, "limits": robot.limits,
        "rating": robot.rating, "workspace": robot.workspace})


def drive_config(cfg: Any, settings: ImproveConfig, store: ArtifactStore, last: Round,
                 goals_mm: list[list[float]], index: int) -> Any:
    """``stage=control`` with ``last``'s policy on the plant toward ``goals_mm``."""
    policy = policy_folder(store, last.cfg)
    drive = OmegaConf.merge(cfg, {"stage": "control", "force": False, "control": {
        "policy_file": str(policy / "policy.msgpack"), "goals": goals_mm, "goals_csv": None,
        "trajectory": None, "hold_s": goal_seconds(cfg, settings),
        "arm_seed": 1000 * int(settings.seed) + index}})
    drive.robot = plant_robot(cfg, settings)
    return drive


def next_round(cfg: Any, settings: ImproveConfig, store: ArtifactStore, last: Round,
               sessions: list[str], pool: np.ndarray, index: int) -> Round:
    """Round ``index`` after ``last`` with ``sessions`` joined (those so far, or with this
    round's once driven)."""
    rng = np.random.default_rng([int(settings.seed), index])
    goals = pool[rng.choice(len(pool), goal_count(settings, goal_seconds(cfg, settings)))]
    goals_mm = np.round(goals * 1000.0, 3).tolist()
    current = round_config(cfg, settings, store, last, sessions)
    walks = []
    count = walk_count(settings)
    if count:
        # a walk's commands, its preload padding before and after included, fill walk_s
        steps = max(1, round(settings.explore_walk_s * float(cfg.robot.control_hz))
                    - 2 * int(cfg.exploration.pad_steps))
        exploration = OmegaConf.merge(cfg.exploration, {
            "num_steps": steps, "seed": int(cfg.exploration.seed) + 7919 * index
            + 104729 * int(settings.seed)})
        walks = list(exploration_plan(OmegaConf.to_object(exploration), cfg.robot.limits,
                                      int(cfg.robot.n_valves),
                                      count * candidate_count(settings)).commands)
    return Round(index, current, evaluation_config(current, settings),
                 drive_config(cfg, settings, store, last, goals_mm, index), goals_mm, walks)


def round_jobs(current: Round) -> list[chain.Job]:
    """(b)-(d) of a round: align, the models, the policy and its evaluation."""
    return [chain.Job(Stage.align, current.cfg), *chain.model_jobs(current.cfg),
            chain.Job(Stage.train_ppo, chain.control_policy_config(current.cfg)),
            chain.Job(Stage.evaluate, current.evaluation)]


def goal_pool(deployed: Artifact, store: ArtifactStore, cfg: Any
              ) -> tuple[np.ndarray, int, np.ndarray]:
    """The deployed policy's training goals ``[G, 3]`` m (what the rounds draw their goals
    from), the model steps per control period and its rest pose ``[3]`` m."""
    train_cfg, model, aligned = training_config(deployed, store, int(cfg.robot.n_valves))
    _, train_params, _ = config_environment(train_cfg, model, aligned)
    steps = max(1, round(float(train_cfg.dataset.model_hz) / float(cfg.robot.control_hz)))
    return (np.asarray(train_params.goal_set, np.float64), steps,
            np.asarray(train_params.reset_positions[0], np.float64))


# ---------------------------------------------------------------------------------------------
# exploration where the models disagree
# ---------------------------------------------------------------------------------------------
def drive_walks(current: Round, last: Round, store: ArtifactStore, settings: ImproveConfig,
                steps_per_command: int, start_pose: np.ndarray) -> list[Artifact]:
    """The round's exploration walks: of ``improve.explore_candidates`` candidates each, the
    one the ensemble of ``last``'s models disagrees on most, driven on the plant through the
    gate (an ``explore`` artifact each)."""
    count = walk_count(settings)
    if not count:
        return []
    member_keys = {"fit_model": keys.key("fit_model", last.cfg), **{
        f"fit_model/seed+{i}": keys.key("fit_model", member)
        for i, member in enumerate(chain.ensemble_configs(last.cfg), start=1)}}
    candidates = np.stack(current.walks)  # [count * candidates, N, valves]
    robot = OmegaConf.to_object(current.drive.robot)
    per_walk = candidate_count(settings)
    artifacts = []
    for walk in range(count):
        group = candidates[walk * per_walk:(walk + 1) * per_walk]
        spec = keys.explore_spec(current.drive, group, walk)
        arm_seed = int(current.drive.control.arm_seed) + 100 * (walk + 1)

        def build(writer: ArtifactWriter, group=group, arm_seed=arm_seed) -> None:
            scores = np.zeros(1)
            if settings.explore == "disagreement":
                members = [load_dynamics(store.require("fit_model", key).file("model.msgpack"))
                           for key in member_keys.values()]
                scores = disagreement_m2(members, held_at_model_rate(group, steps_per_command),
                                         start_pose)
            best = int(most_disputed(scores, 1)[0])
            drive_walk_session(writer, robot, group[best], arm_seed)
            writer.summary.update({"disagreement_mm2": float(scores[best] * 1e6),
                                   "median_candidate_mm2": float(np.median(scores) * 1e6)})

        inputs = member_keys if settings.explore == "disagreement" else {}
        artifacts.append(produce(store, EXPLORE, spec, inputs, build))
    return artifacts


def drive_walk_session(writer: ArtifactWriter, robot: Any, commands: np.ndarray,
                       arm_seed: int) -> None:
    """Drive ``commands`` on the simulated arm ``robot`` (session ``arm_seed``) through the
    command gate; the walk's run into the artifact (``run/``)."""
    from pipeline.control.loop import SimArm
    from pipeline.control.walk import drive_walk
    from pipeline.ros2.gate import CommandGate

    gate = CommandGate.for_robot(robot)
    arm = SimArm(robot, arm_seed, gate)
    sent, frames = drive_walk(arm, gate, commands, float(robot.control_hz), "walk")
    run = walk_tables(sent, frames, session_run_id(EXPLORE, writer.key), f"{EXPLORE}:disagreement")
    write_session(writer.path, run, writer.spec, {
        "stage": EXPLORE, "artifact": writer.key, "robot": robot.name,
        "arm": arm_identity(robot.rating), "control_hz": float(robot.control_hz),
        "controller": {"walk": "most disputed of the candidates"}})
    writer.summary = {"session_run": {"run_id": run.run_id, "commands": len(run.commands),
                                      "frames": len(run.mocap)}}


# ---------------------------------------------------------------------------------------------
# the round's artifact and the plan
# ---------------------------------------------------------------------------------------------
def round_spec(settings: ImproveConfig, current: Round, previous: Artifact | None,
               drives: list[Artifact]) -> tuple[dict[str, Any], dict[str, str]]:
    spec = keys.improve_round_spec(settings, current.index)
    inputs = {"train_ppo": keys.key("train_ppo", chain.control_policy_config(current.cfg)),
              "evaluate": keys.key("evaluate", current.evaluation),
              "fit_model": keys.key("fit_model", current.cfg),
              **{f"{artifact.stage}/{artifact.key}": artifact.key for artifact in drives}}
    if previous is not None:
        inputs["previous"] = previous.key
    return spec, inputs


def finish_round(store: ArtifactStore, settings: ImproveConfig, current: Round,
                 previous: Artifact | None, drives: list[Artifact], last: Round | None = None
                 ) -> Artifact:
    """The round's artifact: its row appended to ``previous``'s table (the first round's
    evaluation when ``previous`` is None)."""
    spec, inputs = round_spec(settings, current, previous, drives)

    def build(writer: ArtifactWriter) -> None:
        evaluation = store.require("evaluate", inputs["evaluate"])
        steps = {"evaluate": [evaluation]}
        if current.index:
            steps.update({
                "drive": drives, "align": [store.require("align", keys.key("align", current.cfg))],
                "fit_model": [store.require("fit_model", keys.key("fit_model", member)) for member
                              in (current.cfg, *chain.ensemble_configs(current.cfg))],
                "train_ppo": [store.require("train_ppo", inputs["train_ppo"])]})
        before = after = None
        if last is not None:
            before = store.require("fit_model", keys.key("fit_model", last.cfg))
            after = store.require("fit_model", inputs["fit_model"])
        row = rounds_table.round_row(
            current.index, str(current.cfg.control.policy), plant_name(settings), evaluation,
            steps, before, after,
            rounds_table.round_runs(steps.get("align"), drives,
                                    float(current.cfg.dataset.model_hz),
                                    str(current.cfg.dataset.model_grid)))
        earlier = (pd.read_parquet(previous.file("rounds.parquet")) if previous is not None
                   else None)
        table = rounds_table.append(earlier, row)
        rounds_table.write(writer, table, {"improve": dataclasses.asdict(settings)})
        writer.summary = {key: value for key, value in row.items()
                          if isinstance(value, (int, float, str))}
        log.info("improve: round %d: %s", current.index, rounds_table.one_line(row))

    return produce(store, STAGE, spec, inputs, build)


def plant_name(settings: ImproveConfig) -> str:
    """The plant's name in evaluate's tables."""
    return f"twin {Path(str(settings.plant)).name}" if settings.plant else "plant"


def plan_table(cfg: Any, settings: ImproveConfig, store: ArtifactStore, pool: np.ndarray
               ) -> str:
    """Each step of each round: its artifact and whether it is reused or runs; a round whose
    policy to start from is not trained yet is pending."""
    rows = [("round", "step", "artifact", "status")]
    last = first_round(cfg, settings)
    rows.append(("0", "evaluate (deployed)", *_status(store, "evaluate", last.evaluation)))
    sessions: list[str] = []
    for index in range(1, settings.rounds + 1):
        policy = store.find("train_ppo", keys.key("train_ppo", chain.control_policy_config(
            last.cfg)))
        if policy is None:
            rows.append((str(index), "drive, refit, retrain, evaluate", "-",
                         f"pending (after round {index - 1})"))
            continue
        current = next_round(cfg, settings, store, last, sessions, pool, index)
        rows.append((str(index), f"drive ({len(current.goals_mm)} goals, "
                     f"{walk_count(settings)} walks)", *_status(store, "control", current.drive)))
        found = store.find("control", keys.key("control", current.drive))
        sessions = [*sessions, *([found.key] if found is not None else [])]
        if found is None or walk_count(settings):
            rows.append((str(index), "refit, retrain, evaluate", "-",
                         "pending (after the drive)"))
            last = current
            continue
        current = next_round(cfg, settings, store, last, sessions, pool, index)
        for job in round_jobs(current):
            rows.append((str(index), job.stage.value + (f" ({job.label})" if job.label else ""),
                         *_status(store, job.stage.value, job.cfg)))
        last = current
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip()
                     for row in rows)


def _status(store: ArtifactStore, stage: str, cfg: Any) -> tuple[str, str]:
    key = keys.key(stage, cfg)
    return key, "reused" if store.find(stage, key) is not None else "runs"
