"""stage=adapt: the correction folded into a model file, the calibration walk, the settings it
refuses, and (slow) adapt then control on a simulated session whose physics differ from the
training runs'."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.arm.limits import UnsafeCommandError
from pipeline.chain import plan
from pipeline.config import PROJECT_ROOT
from pipeline.control.loop import SimArm
from pipeline.control.walk import drive_walk
from pipeline.dynamics.adaptation import SessionCorrection, predict_adapted
from pipeline.dynamics.model import (
    DynamicsConfig,
    DynamicsParams,
    Normalizer,
    init_network,
    predict_sequence,
)
from pipeline.dynamics.session import fold_correction, fold_error_m
from pipeline.infra.artifacts import ArtifactStore
from pipeline.ros2.gate import CommandGate
from pipeline.schemas import ConfigError, Stage
from pipeline.stages._deployed import training_config
from pipeline.stages._environment import config_environment
from pipeline.stages.adapt import adapt, refuse_rehearsal
from tests.conftest import compose_config
from tests.control_fixtures import goals_mm


def small_model(predict_displacement: bool) -> DynamicsParams:
    config = DynamicsConfig(hidden=8, predict_displacement=predict_displacement)
    network = init_network(jax.random.key(0), config)
    normalizer = Normalizer(
        pressure_mean=jnp.array([1.0, 1.2, 0.9]), pressure_std=jnp.array([0.5, 0.6, 0.4]),
        pose_mean=jnp.array([0.03, 0.47, 0.2]), pose_std=jnp.array([0.004, 0.002, 0.003]),
        target_mean=jnp.array([0.001, -0.002, 0.0005]),
        target_std=jnp.array([0.004, 0.002, 0.003]))
    return DynamicsParams(network, normalizer, config)


def a_correction(center) -> SessionCorrection:
    return SessionCorrection(
        input_gain=jnp.array([0.1, -0.05, 0.02]), input_offset_kpa=jnp.array([0.3, -0.2, 0.1]),
        output_matrix=jnp.array([[0.1, 0.02, 0.0], [0.0, -0.2, 0.01], [0.03, 0.0, 0.05]]),
        output_offset_m=jnp.array([1e-3, -2e-3, 5e-4]), center_m=jnp.asarray(center))


PRESSURES = np.abs(np.sin(np.arange(40)[:, None] * np.array([0.3, 0.5, 0.7]))) * 2.0 + 0.5
POSE = np.array([0.031, 0.47, 0.201])


def test_an_absolute_model_folds_exactly_for_any_initial_pose():
    params = small_model(predict_displacement=False)
    correction = a_correction(POSE + 0.002)
    folded = fold_correction(params, correction, jnp.asarray(POSE))
    for start in (POSE, POSE + np.array([0.003, -0.001, 0.002])):
        assert fold_error_m(params, correction, folded, PRESSURES, start) < 1e-7  # < 0.1 µm


def test_a_displacement_model_folds_exactly_at_the_reference_pose_and_turns_about_it():
    params = small_model(predict_displacement=True)
    correction = a_correction(POSE + 0.002)
    folded = fold_correction(params, correction, jnp.asarray(POSE))
    assert fold_error_m(params, correction, folded, PRESSURES, POSE) < 1e-7
    # from 1 mm further in x the folded model is off by M (x_0 - x_ref) = M[:, 0] * 1 mm at
    # every step: (0.1, 0, 0.03) mm
    start = POSE + np.array([0.001, 0.0, 0.0])
    calibrated = predict_adapted(params, correction, jnp.asarray(PRESSURES, jnp.float32),
                                 jnp.asarray(start, jnp.float32))
    plain = predict_sequence(folded, jnp.asarray(PRESSURES, jnp.float32),
                             jnp.asarray(start, jnp.float32))
    np.testing.assert_allclose(np.asarray(calibrated - plain),
                               np.tile([1e-4, 0.0, 3e-5], (len(PRESSURES), 1)), atol=2e-7)


def test_the_identity_folds_to_the_same_predictions():
    params = small_model(predict_displacement=True)
    identity = SessionCorrection.identity()
    folded = fold_correction(params, identity, jnp.asarray(POSE))
    assert fold_error_m(params, identity, folded, PRESSURES, POSE + 0.001) < 1e-8


def test_the_walk_goes_through_the_gate_and_ends_at_the_preload(make_cfg):
    cfg = make_cfg()
    robot = OmegaConf.to_object(cfg.robot)
    gate = CommandGate.for_robot(robot)
    arm = SimArm(robot, 3, gate)
    commands = np.array([[1.0, 1.0, 1.0], [3.0, 1.0, 1.0], [2.0, 0.5, 1.5]])
    sent, frames = drive_walk(arm, gate, commands, 2.0, "walk")
    assert sent["t"].tolist() == pytest.approx([0.0, 0.5, 1.0])
    assert sent["p_cmd_0"].tolist() == [1.0, 3.0, 2.0]
    assert len(arm.commands) == 4  # the three, then the preload
    np.testing.assert_allclose(arm.commands[-1], np.full(3, robot.limits.preload))
    rate = float(robot.mocap.rate_hz)  # frames until the end of the last period, some dropped
    assert 0.8 * 1.5 * rate <= len(frames) <= 1.5 * rate + 1
    assert frames["valid"].all() and -0.05 < frames["t"].min() < frames["t"].max() < 1.55


def test_a_walk_outside_the_limits_stops_at_the_preload(make_cfg):
    cfg = make_cfg("robot.limits.p_max=4.0")
    robot = OmegaConf.to_object(cfg.robot)
    gate = CommandGate.for_robot(robot)
    arm = SimArm(robot, 3, gate)
    with pytest.raises(UnsafeCommandError, match=r"outside robot\.limits"):
        drive_walk(arm, gate, np.array([[1.0, 1.0, 1.0], [5.0, 1.0, 1.0]]), 2.0, "walk")
    assert len(arm.commands) == 2  # the first command, then the preload: 5 kPa never left
    np.testing.assert_allclose(arm.commands[-1], np.full(3, robot.limits.preload))


@pytest.mark.parametrize("override, message", [
    ("adapt.walk_s=0", "adapt.walk_s=0.0 must be finite and > 0"),
    ("adapt.max_fold_error_mm=-1", "adapt.max_fold_error_mm=-1.0 must be finite and > 0"),
    ("adapt.mechanism=magic", "adapt.mechanism='magic' must be one of"),
    ("adapt.output=skew", "adapt.output='skew' must be one of"),
    ("adapt.steps=-1", "adapt: adaptation steps must be an integer >= 0"),
    ("robot=sorolex_csv", "stage=adapt drives an arm for its calibration walk"),
])
def test_bad_settings_are_refused_with_a_line_naming_them(make_cfg, override, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        adapt(make_cfg("stage=adapt", override))


def test_an_adapted_policy_is_not_adapted_again_and_control_reads_it(make_cfg, tmp_path):
    folder = tmp_path / "adapt" / "abc123"
    folder.mkdir(parents=True)
    (folder / "policy.msgpack").write_bytes(b"")
    (folder / "artifact.json").write_text(json.dumps({"stage": "adapt", "key": "abc123"}))
    cfg = make_cfg("stage=adapt", f"control.policy_file={folder / 'policy.msgpack'}")
    assert keys.control_policy(cfg) == ("adapt", "abc123")
    assert keys.control_spec(cfg)[1] == {"adapt": "abc123"}
    with pytest.raises(ConfigError, match="is an adapted policy"):
        keys.adapt_spec(cfg)


def test_an_adapt_on_the_arm_never_answers_with_the_twins(tmp_path):
    folder = tmp_path / "adapt" / "k1"
    folder.mkdir(parents=True)
    (folder / "artifact.json").write_text(json.dumps({"summary": {"rehearsal": True}}))
    store = ArtifactStore(tmp_path)
    with pytest.raises(ConfigError, match="calibrated on the digital twin"):
        refuse_rehearsal(store, "k1", rehearsal=False, force=False)
    refuse_rehearsal(store, "k1", rehearsal=True, force=False)  # the rehearsal may reuse it
    refuse_rehearsal(store, "k1", rehearsal=False, force=True)  # walks the arm anew
    refuse_rehearsal(store, "k2", rehearsal=False, force=False)  # nothing there


def test_adapt_runs_alone_and_only_when_named(make_cfg):
    for robot in ("sim", "ros2"):
        jobs = plan(make_cfg("stage=adapt", f"robot={robot}"), lambda cfg: "key")
        assert [job.stage for job in jobs] == [Stage.adapt]
    assert not [job for job in plan(make_cfg("stage=all"), lambda cfg: "key")
                if job.stage is Stage.adapt]


@pytest.mark.slow  # a pipeline process
def test_the_entry_point_refuses_a_bad_walk_in_one_line(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    result = subprocess.run(
        [sys.executable, "-m", "pipeline", f"paths.output_dir={tmp_path}", "stage=adapt",
         "adapt.max_fold_error_mm=-1"],
        cwd=PROJECT_ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 1
    output = result.stdout + result.stderr
    errors = [line for line in output.splitlines() if "ERROR" in line]
    assert len(errors) == 1
    assert errors[0].endswith("ConfigError: adapt.max_fold_error_mm=-1.0 must be finite and > 0")
    assert "Traceback" not in output


# a chain of seconds: two short runs of the simulated arm, a small model and policy
TINY = ["experiment=quick", "robot.num_runs=2", "exploration.num_steps=60", "model.hidden=16",
        "model.num_steps=150", "agent.num_seeds=1", "agent.total_timesteps=8192",
        "agent.num_evals=2"]
# a session of the day: the chambers' gains differ from the training runs'
SESSION = ["robot.physics.chamber_gains=[0.85,1.15,1.0]", "control.arm_seed=5"]


@pytest.mark.slow
def test_adapt_then_control_on_a_session_whose_physics_differ(make_cfg):
    from pipeline.__main__ import run

    trained = run(make_cfg("stage=train_ppo", *TINY))["train_ppo"]
    policy = str(trained.file("policy.msgpack"))
    # a session latent needs a model trained with one: refused before the walk
    with pytest.raises(ConfigError, match=r"adapt\.mechanism=latent .* trained without one"):
        run(make_cfg("stage=adapt", *TINY, *SESSION, f"control.policy_file={policy}",
                     "adapt.mechanism=latent"))
    adapted = run(make_cfg("stage=adapt", *TINY, *SESSION, f"control.policy_file={policy}",
                           "adapt.walk_s=20", "adapt.steps=100",
                           "adapt.policy_timesteps=8192"))["adapt"]
    for name in ("model.msgpack", "split.json", "walk/commands.parquet", "walk/mocap.parquet",
                 "walk/aligned.parquet", "open_loop.csv", "correction.json", "policy.msgpack",
                 "evaluation.parquet", "metrics.parquet"):
        assert adapted.file(name).is_file(), name
    summary = adapted.manifest["summary"]
    errors = pd.read_csv(adapted.file("open_loop.csv"), comment="#").set_index("model")
    # calibrated on the walk, the model predicts it better than the deployed one
    assert errors.loc["calibrated", "mean_mm"] < errors.loc["deployed", "mean_mm"]
    assert summary["fold_error_mm"] <= 0.1
    assert 20.0 <= summary["walk_arm_s"] <= 25.0  # the walk and its preload padding
    store = ArtifactStore(trained.path.parent.parent)
    train_cfg, model, aligned = training_config(trained, store, 3)
    _, _, eval_params = config_environment(train_cfg, model, aligned)
    goal_overrides = [f"control.goals={json.dumps(goals_mm(eval_params, 3))}"]
    distances = {}
    for name, policy_file, seed in (("deployed", policy, summary["policy_seed"]),
                                    ("adapted", str(adapted.file("policy.msgpack")), 0)):
        session = run(make_cfg("stage=control", *TINY, *SESSION, *goal_overrides,
                               f"control.policy_file={policy_file}", f"control.seed={seed}",
                               "control.hold_s=10"))["control"]
        distances[name] = pd.read_parquet(session.file("goals.parquet"))["final_distance_mm"]
    print({name: np.round(d.to_numpy(), 3).tolist() for name, d in distances.items()})
    assert all(np.isfinite(d).all() and len(d) >= 1 for d in distances.values())


@pytest.mark.slow
@pytest.mark.ros
def test_adapt_over_ros2_on_the_twin_then_control_drives_the_adapted_policy(tmp_path,
                                                                           ros_domain):
    """The walk recorded over ROS 2 from the twin (a session whose chamber gains differ), through
    the gate and ending at the preload; then stage=control drives the adapted policy there."""
    pytest.importorskip("rclpy")
    from pipeline.__main__ import run
    from pipeline.data.schemas import CMD_COLUMNS
    from tests.test_ros2_link import Pipeline, received, stop

    trained = run(compose_config(tmp_path / "sim", *TINY, "stage=train_ppo"))["train_ppo"]
    store = ArtifactStore(trained.path.parent.parent)
    train_cfg, model, aligned = training_config(trained, store, 3)
    _, _, eval_params = config_environment(train_cfg, model, aligned)
    goals = json.dumps(goals_mm(eval_params, 2)).replace(" ", "")
    pipe = Pipeline(tmp_path, ros_domain)
    pipe.overrides = [*TINY, "robot=ros2", "robot.rehearsal=true", "robot.time_scale=4.0",
                      "robot.watchdog_s=1.0", "robot.stop_timeout_s=2.0",
                      "robot.startup_timeout_s=60", "robot.twin.seed=5",
                      "robot.twin.physics.chamber_gains=[0.85,1.15,1.0]"]
    record = tmp_path / "twin_received.jsonl"
    twin = pipe.start("twin", f"robot.twin.record_path={record}", "robot.twin.max_duration_s=900")
    walk = [f"control.policy_file={trained.file('policy.msgpack')}", "adapt.walk_s=10",
            "adapt.steps=50", "adapt.policy_timesteps=8192"]
    try:
        assert pipe.start("adapt", *walk).wait(timeout=400) == 0, pipe.log("adapt")
        sent = received(record)[CMD_COLUMNS].to_numpy()
        adapted = ArtifactStore(pipe.out / "artifacts").require(
            "adapt", keys.key("adapt", pipe.cfg("stage=adapt", *walk)))
        control = pipe.start("control", f"control.policy_file={adapted.file('policy.msgpack')}",
                             f"control.goals={goals}", "control.hold_s=5")
        assert control.wait(timeout=300) == 0, pipe.log("control")
    finally:
        assert stop(twin) == 0, pipe.log("twin")
    assert len(sent) >= 20 + 1  # the walk's commands (10 s at 2 Hz and its padding), the preload
    np.testing.assert_allclose(sent[-1], [2.0, 2.0, 2.0])
    assert np.isfinite(sent).all() and sent.max() <= 7.0 and sent.sum(axis=1).max() <= 13.0
    assert adapted.manifest["summary"]["walk_arm_s"] >= 10.0
    assert "control: report at" in pipe.log("control")
