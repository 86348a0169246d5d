"""Stage ``adapt``: the deployed model and policy calibrated to the session of the day.

Not part of ``stage=all``: started on its own; with ``robot=ros2`` it drives the arm (only when
named, through the command gate, as collect does; rehearse it on the twin,
``robot.rehearsal=true``).

1. A calibration walk of the current session: the exploration walk cut to ``adapt.walk_s``
   seconds, on ``robot=sim`` the simulated session ``control.arm_seed`` (the session
   ``stage=control`` then drives), on ``robot=ros2`` recorded as collect records a run. It is
   aligned and resampled at the deployed model's rate.
2. The deployed model (the fit_model artifact the policy of ``control.policy`` /
   ``control.policy_file`` trained in) calibrated to the walk
   (:func:`pipeline.dynamics.adaptation.adapt`, ``adapt.mechanism``) and the correction folded
   into a model file (:mod:`pipeline.dynamics.session`).
3. The policy's seed (``control.seed``, default the best of its training) fine-tuned for
   ``adapt.policy_timesteps`` PPO steps in the calibrated model, warm started from it.

Artifact: ``model.msgpack`` and ``split.json`` (the calibrated model, read as a fit_model
artifact's), ``walk/commands.parquet``, ``walk/mocap.parquet``, ``walk/aligned.parquet``,
``open_loop.csv`` (the model's open-loop error on the walk before and after, mm),
``correction.json``, ``policy.msgpack``, ``evaluation.parquet``, ``metrics.parquet`` (as
train_ppo writes them). ``stage=control control.policy_file=<artifact>/policy.msgpack`` drives
with the adapted policy.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import logging
import math
import shutil
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.arm.exploration import exploration_plan
from pipeline.arm.limits import validate_limits
from pipeline.data.alignment import align_tables, runs_at_model_rate
from pipeline.data.raw import CollectionInterrupted
from pipeline.data.schemas import ALIGNED, COMMANDS, MOCAP, write_table
from pipeline.dynamics import adaptation
from pipeline.dynamics.checkpoints import load_dynamics, save_dynamics
from pipeline.dynamics.model import predict_sequence, session_latent_dim
from pipeline.dynamics.scoring import position_errors_mm
from pipeline.dynamics.session import fold_correction, fold_error_m
from pipeline.infra.artifacts import Artifact, ArtifactStore, ArtifactWriter, artifact_key, produce
from pipeline.rl.policy_io import best_seed
from pipeline.schemas import AgentConfig, ConfigError, RobotKind
from pipeline.stages._deployed import policy_artifact, training_config
from pipeline.stages._environment import config_environment
from pipeline.stages._policies import train_into
from pipeline.stages._rehearsal import refuse_twin_artifact
from pipeline.validation import validate_config

log = logging.getLogger(__name__)
STAGE = "adapt"


def adapt(cfg: Any) -> Artifact:
    """Calibrate the deployed model and policy to this session (see the module doc)."""
    validate_config(cfg)
    settings = adaptation_settings(cfg.adapt)
    robot = OmegaConf.to_object(cfg.robot)
    kind = RobotKind(robot.kind)
    if kind not in (RobotKind.sim, RobotKind.ros2):
        raise ConfigError(f"stage=adapt drives an arm for its calibration walk: robot=ros2 (or "
                          f"the twin) or robot=sim; got robot={robot.name} (recorded data)")
    validate_limits(robot.limits, robot.n_valves)
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.adapt_spec(cfg)
    deployed, lineage = policy_artifact(cfg, store)
    train_cfg, model, aligned = training_config(deployed, lineage, int(robot.n_valves))
    if model is None or aligned is None:
        raise ConfigError(f"adapt: the policy {deployed.path} was trained in env="
                          f"{train_cfg.env.name}, without a fitted model to calibrate; adapt a "
                          f"policy of the learned environment")
    if (settings.mechanism == "latent"
            and session_latent_dim(load_dynamics(model.file("model.msgpack"))) == 0):
        raise ConfigError(f"adapt.mechanism=latent infers a session latent, and the model "
                          f"{model.path} was trained without one (model.session_latent_dim=0); "
                          f"choose another mechanism or deploy a policy of a latent model")
    if abs(float(train_cfg.robot.control_hz) - float(robot.control_hz)) > 1e-9:
        raise ConfigError(f"robot.control_hz={robot.control_hz}: the policy {deployed.path} was "
                          f"trained at {train_cfg.robot.control_hz} Hz")
    seed = (best_seed(pd.read_parquet(deployed.file("evaluation.parquet")), deployed.path)
            if cfg.control.seed is None else int(cfg.control.seed))
    agent = fine_tune_agent(cfg.adapt, deployed, seed)
    exploration = dataclasses.replace(OmegaConf.to_object(cfg.exploration),
                                      num_steps=walk_steps(cfg.adapt, robot.control_hz))
    walk = exploration_plan(exploration, robot.limits, robot.n_valves, 1).commands[0]

    def build(writer: ArtifactWriter) -> None:
        timings: dict[str, float] = {}
        started = time.perf_counter()
        commands, mocap = record_walk(cfg, robot, exploration, walk, writer)
        timings["walk_wall_s"] = time.perf_counter() - started
        run = aligned_walk(writer, commands, mocap, cfg.dataset.align, train_cfg.dataset)
        started = time.perf_counter()
        summary = calibrate_model(writer, model, run, settings, cfg.adapt,
                                  float(train_cfg.dataset.model_hz))
        timings["calibrate_wall_s"] = time.perf_counter() - started
        calibrated = Artifact(STAGE, writer.key, writer.path)
        started = time.perf_counter()
        summary.update(fine_tune_policy(writer, train_cfg, calibrated, aligned, agent, spec,
                                        int(cfg.seed), timings))
        timings["policy_wall_s"] = time.perf_counter() - started
        if kind is RobotKind.ros2:
            summary["rehearsal"] = bool(robot.rehearsal)  # walked on the twin
        writer.summary = {**summary, "policy_seed": seed, "deployed_path": str(deployed.path),
                          "walk_arm_s": float(run.times_s[-1]),
                          **{k: round(v, 2) for k, v in timings.items()
                             if isinstance(v, (int, float))}}  # the seconds and counts
        log.info("adapt: %s", json.dumps(writer.summary))

    if kind is RobotKind.ros2:
        refuse_rehearsal(store, artifact_key(spec, inputs), bool(robot.rehearsal), bool(cfg.force))
    artifact = produce(store, STAGE, spec, inputs, build, force=cfg.force)
    log.info("adapt: drive with stage=control control.policy_file=%s",
             artifact.file("policy.msgpack"))
    return artifact


def refuse_rehearsal(store: ArtifactStore, key: str, rehearsal: bool, force: bool) -> None:
    """An adapt on the arm never answers with a rehearsal's calibration."""
    refuse_twin_artifact(
        store, STAGE, key, rehearsal, force,
        "adapt: {path} was calibrated on the digital twin under this config's key; name this "
        "session anew (robot.session=...), or force=true to walk the arm again")


def adaptation_settings(node: Any) -> adaptation.AdaptationSettings:
    """The calibration settings of ``adapt`` (AdaptationSettings); a bad value is a
    :class:`ConfigError` naming it. The bounds of the walk, the fine-tune and the fold too."""
    for name, low in (("walk_s", 0.0), ("max_fold_error_mm", 0.0)):
        value = float(node[name])
        if not (math.isfinite(value) and value > low):
            raise ConfigError(f"adapt.{name}={node[name]} must be finite and > {low:g}")
    for name, options in (("mechanism", adaptation.MECHANISMS), ("output", adaptation.OUTPUTS)):
        if str(node[name]) not in options:
            raise ConfigError(f"adapt.{name}={node[name]!r} must be one of {list(options)}")
    try:
        return adaptation.AdaptationSettings(
            mechanism=str(node.mechanism), output=str(node.output),
            input_affine=bool(node.input_affine), steps=int(node.steps),
            prior_mm2=float(node.prior_mm2))
    except ValueError as error:
        raise ConfigError(f"adapt: {error}") from None


def walk_steps(node: Any, control_hz: float) -> int:
    """Exploration steps of the calibration walk: ``adapt.walk_s`` at ``control_hz``."""
    return max(1, round(float(node.walk_s) * float(control_hz)))


def fine_tune_agent(node: Any, deployed: Artifact, seed: int) -> dict[str, Any]:
    """The deployed policy's agent settings for the fine-tune: one seed (``seed`` of the deployed
    policy, warm started), ``adapt.policy_timesteps`` steps, ``adapt.policy_log_std``."""
    agent = {**deployed.manifest["spec"]["agent"], "num_seeds": 1,
             "init_policy": str(deployed.file("policy.msgpack")), "init_policy_seed": seed,
             "init_policy_log_std": node.policy_log_std,
             "total_timesteps": int(node.policy_timesteps), "recurrent_total_timesteps": None}
    config = AgentConfig.from_any(agent, progress=False)
    config.check()
    smallest = config.steps_per_update * config.num_evals
    if int(node.policy_timesteps) < smallest:
        raise ConfigError(f"adapt.policy_timesteps={node.policy_timesteps} is below one update "
                          f"per evaluation of the deployed agent (num_envs x num_steps x "
                          f"num_evals = {smallest})")
    return agent


def record_walk(cfg: Any, robot: Any, exploration: Any, walk: np.ndarray,
                writer: ArtifactWriter) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The calibration walk's raw ``commands`` and ``mocap`` rows, also written to the
    artifact: the simulated session ``control.arm_seed``, or the arm over ROS 2 (collect's
    recorder, one run of the shortened walk)."""
    if RobotKind(robot.kind) is RobotKind.sim:
        from pipeline.control.loop import SimArm
        from pipeline.control.walk import drive_walk
        from pipeline.ros2.gate import CommandGate

        gate = CommandGate.for_robot(robot)
        arm = SimArm(robot, int(cfg.control.arm_seed), gate)
        commands, mocap = drive_walk(arm, gate, walk, float(robot.control_hz), "walk")
    else:
        from pipeline.ros2.collector import collect_ros2

        started = _dt.datetime.now().strftime("%Y%m%dT%H%M%S")
        recovery = Path(cfg.paths.output_dir) / "recovery" / f"{STAGE}-{writer.key}-{started}"
        recorded = collect_ros2(dataclasses.replace(robot, num_runs=1), exploration, recovery,
                                writer.spec)
        if recorded.interruption is not None:
            raise CollectionInterrupted(
                f"adapt: the calibration walk was interrupted ({recorded.interruption.reason}); "
                f"the preload was commanded. Its rows are in {recovery}; nothing was adapted"
            ) from recorded.interruption.error
        commands, mocap = recorded.commands, recorded.mocap
        shutil.rmtree(recorded.recovery)
    provenance = {"stage": STAGE, "robot": robot.name}
    write_table(commands, writer.file("walk/commands.parquet"), COMMANDS, writer.spec, provenance)
    write_table(mocap, writer.file("walk/mocap.parquet"), MOCAP, writer.spec, provenance)
    return commands, mocap


def aligned_walk(writer: ArtifactWriter, commands: pd.DataFrame, mocap: pd.DataFrame,
                 align: Any, dataset: Any) -> Any:
    """The walk aligned (``dataset.align``) and resampled at the deployed model's rate and grid:
    one :class:`~pipeline.data.runs.Run`."""
    aligned, _ = align_tables(commands, mocap, align, str(writer.file("walk/mocap.parquet")))
    write_table(aligned, writer.file("walk/aligned.parquet"), ALIGNED, writer.spec,
                {"stage": STAGE})
    runs = runs_at_model_rate(aligned, float(dataset.model_hz), str(dataset.model_grid))
    if len(runs) != 1:
        raise ConfigError(f"adapt: the calibration walk aligned into {len(runs)} segments (mocap "
                          f"gaps longer than dataset.align.max_gap_s); record it again")
    return runs[0]


def calibrate_model(writer: ArtifactWriter, model: Artifact, run: Any,
                    settings: adaptation.AdaptationSettings, node: Any, model_hz: float
                    ) -> dict[str, Any]:
    """Calibrate the deployed model to the walk ``run``, fold the correction into
    ``model.msgpack`` (with the deployed model's ``split.json``), write the open-loop errors
    before and after and the correction; returns their summary."""
    params = load_dynamics(model.file("model.msgpack"))
    correction = adaptation.adapt(params, run.pressures_kpa, run.positions_m, settings, model_hz)
    folded = fold_correction(params, correction, jax.numpy.asarray(run.positions_m[0]))
    fold_mm = 1000.0 * fold_error_m(params, correction, folded, run.pressures_kpa,
                                    run.positions_m[0])
    if fold_mm > float(node.max_fold_error_mm):
        raise ConfigError(f"adapt: the calibrated model folds into a model file only to within "
                          f"{fold_mm:.3f} mm over the walk, above adapt.max_fold_error_mm="
                          f"{node.max_fold_error_mm}")
    save_dynamics(writer.file("model.msgpack"), folded)
    shutil.copyfile(model.file("split.json"), writer.file("split.json"))
    rows = []
    for name, candidate in (("deployed", params), ("calibrated", folded)):
        predicted = np.asarray(predict_sequence(candidate, run.pressures_kpa, run.positions_m[0]))
        rows.append({"model": name, **position_errors_mm(predicted, run.positions_m)})
    table = pd.DataFrame(rows)
    with writer.file("open_loop.csv").open("w") as handle:
        handle.write(f"# open-loop error over the calibration walk ({len(run)} steps at "
                     f"{model_hz:g} Hz), mm; calibrated: adapt.mechanism={settings.mechanism}\n")
        table.to_csv(handle, index=False, float_format="%.4f")
    values = {name: np.asarray(value).tolist() for name, value in
              dataclasses.asdict(correction).items() if value is not None}
    writer.file("correction.json").write_text(json.dumps(
        {"units": {"input_gain": "1", "input_offset_kpa": "kPa", "output_matrix": "1",
                   "output_offset_m": "m", "center_m": "m"}, **values}, indent=2))
    return {"open_loop_mm": {row["model"]: {k: round(float(row[k]), 4)
                                            for k in ("mean_mm", "p95_mm")} for row in rows},
            "fold_error_mm": round(fold_mm, 5), "mechanism": settings.mechanism}


def fine_tune_policy(writer: ArtifactWriter, train_cfg: Any, calibrated: Artifact,
                     aligned: Artifact, agent_spec: dict[str, Any], spec: dict[str, Any],
                     seed: int, timings: dict[str, float]) -> dict[str, Any]:
    """The deployed policy's seed fine-tuned in the calibrated model (its environment otherwise
    the deployed one's): ``policy.msgpack`` (one seed), ``evaluation.parquet``,
    ``episodes.parquet``, ``metrics.parquet``; returns the held-out summary of its last
    evaluation in that model."""
    agent = AgentConfig.from_any(agent_spec, progress=False)
    env, train_params, eval_params = config_environment(train_cfg, calibrated, aligned)
    config = {"env": OmegaConf.to_container(train_cfg.env), "adapt": spec["adapt"]}
    trained = train_into(writer, STAGE, agent, env, train_params, eval_params, seed=seed,
                         config=config, desc=f"{STAGE} {agent.name}", warm_start=True,
                         policy_meta={"agent": agent_spec, "env": config["env"]})
    timings.update(trained.timings)
    final = trained.episodes["final_distance_m"].to_numpy()
    return {"policy_timesteps": agent.num_updates * agent.steps_per_update,
            "policy_eval_median_distance_mm_in_calibrated_model": (
                float(np.nanmedian(final) * 1000) if np.isfinite(final).any() else None)}
