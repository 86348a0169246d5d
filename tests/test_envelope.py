"""The hardware envelope and config validation: the arm's rating, limits inside it, settings that
cannot run, which stages may drive a real arm, and how a known error reaches the user."""

from __future__ import annotations

import os
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

import pipeline.__main__ as router
from pipeline.__main__ import run
from pipeline.arm.limits import UnsafeCommandError
from pipeline.chain import DRIVES_ARM, stages_to_run
from pipeline.config import PROJECT_ROOT
from pipeline.ros2.gate import CommandGate
from pipeline.schemas import ConfigError, Stage
from pipeline.validation import validate_config


def refused(cfg, match: str | None = None, choice: str | None = None) -> str:
    with pytest.raises(ConfigError, match=match) as err:
        validate_config(cfg, choice)
    return str(err.value)


# ---- limits inside the rating ------------------------------------------------------------------
@pytest.mark.parametrize(("override", "message"), [
    ("robot.limits.p_max=7.5",
     "robot.limits.p_max=7.5 kPa lies outside the arm's rating robot.rating.p_max=7.0 kPa"),
    ("robot.limits.sum_max=14",
     "robot.limits.sum_max=14.0 kPa lies outside the arm's rating robot.rating.sum_max=13.0 kPa"),
    ("robot.limits.p_min=-0.5",
     "robot.limits.p_min=-0.5 kPa lies outside the arm's rating robot.rating.p_min=0.0 kPa"),
    ("exploration.p_max=14",
     "exploration.p_max=14.0 kPa exceeds the arm's rating robot.rating.sum_max=13.0 kPa"),
])
@pytest.mark.parametrize("robot", ["sim", "ros2"])
def test_limits_outside_the_rating_are_refused_naming_both(make_cfg, robot, override, message):
    assert refused(make_cfg(f"robot={robot}", override), "outside|exceeds").startswith(message)


def test_the_reported_overrun_is_refused_before_any_work(make_cfg):
    """The overrides that once published 43 kPa per valve to a real arm."""
    cfg = make_cfg("stage=collect", "robot=ros2", "robot.limits.p_max=50",
                   "robot.limits.sum_max=100", "exploration.p_max=100")
    refused(cfg, r"robot\.limits\.p_max=50\.0 kPa lies outside the arm's rating "
                 r"robot\.rating\.p_max=7\.0 kPa")


def test_limits_may_tighten_the_rating(make_cfg):
    validate_config(make_cfg("robot=ros2", "robot.limits.p_max=4.5", "robot.limits.sum_max=10",
                             "exploration.p_max=10"), "ros2")


@pytest.mark.parametrize("override", ["robot.rating.p_max=50", "robot.rating.sum_max=12",
                                      "robot.rating.preload=1.5"])
def test_a_real_arms_rating_cannot_be_overridden(make_cfg, override):
    """Even an override that tightens it: the rating is the one in conf/robot/ros2.yaml."""
    name = override.split("=")[0].split(".")[-1]
    message = refused(make_cfg("robot=ros2", override), f"robot.rating.{name}=", "ros2")
    assert "cannot be overridden" in message and str(PROJECT_ROOT / "conf/robot/ros2.yaml") in message


def test_a_simulated_arms_rating_may_be_overridden(make_cfg):
    validate_config(make_cfg("robot.rating.p_max=8", "robot.limits.p_max=8"))


# ---- settings that cannot run ------------------------------------------------------------------
@pytest.mark.parametrize(("override", "message"), [
    ("robot.watchdog_s=inf", "robot.watchdog_s=inf must be finite and positive"),
    ("robot.watchdog_s=0", "robot.watchdog_s=0.0 must be finite and positive"),
    ("robot.startup_timeout_s=-1", "robot.startup_timeout_s=-1.0 must be finite and positive"),
    ("robot.stop_timeout_s=inf", "robot.stop_timeout_s=inf must be finite and positive"),
    ("robot.command_timeout_s=0", "robot.command_timeout_s=0.0 must be finite and positive"),
    ("robot.command_timeout_s=0.4", "robot.command_timeout_s=0.4 s must exceed one control "
                                    "period (1 / robot.control_hz = 0.5 s)"),
    ("robot.watchdog_s=nan", "robot.watchdog_s=nan: a number is required"),
])
def test_robot_durations_must_be_finite_and_positive(make_cfg, override, message):
    assert refused(make_cfg("robot=ros2", override)).startswith(message)


@pytest.mark.parametrize(("override", "message"), [
    ("exploration.alpha=1.5", "exploration.alpha=1.5 must lie in [0, 1]"),
    ("exploration.alpha=-1", "exploration.alpha=-1.0 must lie in [0, 1]"),
    ("exploration.alpha=nan", "exploration.alpha=nan: a number is required"),
    ("exploration.beta=inf", "exploration.beta=inf must be finite"),
    ("exploration.beta=nan", "exploration.beta=nan: a number is required"),
    ("exploration.noise_std=-0.1", "exploration.noise_std=-0.1 must be >= 0"),
    ("exploration.noise_std=inf", "exploration.noise_std=inf must be finite"),
    ("model.learning_rate=nan", "model.learning_rate=nan: a number is required"),
    ("robot.physics.bend_gain=nan", "robot.physics.bend_gain=nan: a number is required"),
])
def test_exploration_ranges_and_nan_anywhere_are_refused(make_cfg, override, message):
    assert refused(make_cfg(override)).startswith(message)


@pytest.mark.parametrize("override", ["robot=ros2", "robot=sim", "experiment=paper",
                                      "experiment=quick"])
def test_shipped_configs_pass_validation(make_cfg, override):
    validate_config(make_cfg(override))


def test_validation_runs_before_any_stage(make_cfg, monkeypatch):
    monkeypatch.setattr(router, "stage_function", lambda stage: pytest.fail(f"{stage} ran"))
    with pytest.raises(ConfigError, match=r"exploration\.alpha"):
        run(make_cfg("stage=collect", "exploration.alpha=1.5"))


# ---- the gate: both the limits and the rating, float64 -----------------------------------------
def test_gate_checks_the_rating_as_well_as_the_limits():
    limits = SimpleNamespace(p_min=0.0, p_max=7.0, sum_max=13.0, preload=2.0)
    rating = SimpleNamespace(p_min=0.0, p_max=5.0, sum_max=13.0, preload=2.0)  # tighter
    gate = CommandGate(limits, 3, rating)
    np.testing.assert_array_equal(gate.check(np.array([5.0, 0.0, 0.0])), [5.0, 0.0, 0.0])
    with pytest.raises(UnsafeCommandError, match=r"outside the arm's rating robot\.rating: "
                                                  r"\[0\.0, 5\.0\] per valve"):
        gate.check(np.array([6.0, 0.0, 0.0]))
    with pytest.raises(UnsafeCommandError, match=r"robot\.rating"):
        gate.check(np.array([np.nextafter(5.0, 6.0), 0.0, 0.0]))  # float64: 1 ulp over


# ---- only an explicit stage drives a real arm ---------------------------------------------------
@pytest.mark.parametrize("stage", list(Stage))
def test_no_stage_drives_a_real_arm_unless_asked_for_by_name(make_cfg, monkeypatch, stage):
    cfg = make_cfg(f"stage={stage}", "robot=ros2")
    planned = stages_to_run(cfg)
    assert [s for s in planned if s in DRIVES_ARM] == ([stage] if stage in DRIVES_ARM else [])
    ran = []
    monkeypatch.setattr(router, "stage_function", lambda s: lambda _cfg: ran.append(s))
    run(cfg)
    assert set(ran) & DRIVES_ARM <= {stage}
    assert Stage.collect not in ran or stage is Stage.collect


def test_stage_all_on_a_real_arm_skips_collect(make_cfg):
    assert stages_to_run(make_cfg("robot=ros2")) == [Stage.align, Stage.fit_model,
                                                     Stage.train_ppo, Stage.evaluate]
    assert stages_to_run(make_cfg())[0] is Stage.collect  # the simulated arm is collected


# ---- a known error: one message, exit status 1, no traceback (unless HYDRA_FULL_ERROR=1) --------
def pipeline(tmp_path, *overrides, full_error: bool = False):
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env.update(JAX_PLATFORMS="cpu", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    if full_error:
        env["HYDRA_FULL_ERROR"] = "1"
    return subprocess.run(
        [sys.executable, "-m", "pipeline", f"paths.output_dir={tmp_path / 'outputs'}",
         f"hydra.run.dir={tmp_path / 'run'}", *overrides],
        cwd=PROJECT_ROOT, env=env, capture_output=True, text=True, timeout=300)


def test_overriding_a_real_arms_rating_fails_with_one_message(tmp_path):
    result = pipeline(tmp_path, "stage=collect", "robot=ros2", "robot.rating.p_max=50")
    output = result.stdout + result.stderr
    assert result.returncode == 1, output
    assert ("ConfigError: robot.rating.p_max=50.0 kPa differs from 7.0 kPa in "
            f"{PROJECT_ROOT / 'conf/robot/ros2.yaml'}: the rating of a real arm (robot=ros2) "
            "cannot be overridden") in output
    assert "Traceback" not in output and output.count("ERROR") == 1


def test_a_missing_artifact_fails_with_one_message(tmp_path):
    result = pipeline(tmp_path, "stage=align", "robot=ros2")
    output = result.stdout + result.stderr
    assert result.returncode == 1, output
    assert "MissingArtifactError: " in output and "stage=collect" in output
    assert "Traceback" not in output


def test_hydra_full_error_shows_the_traceback(tmp_path):
    result = pipeline(tmp_path, "exploration.alpha=1.5", full_error=True)
    assert result.returncode == 1
    assert "Traceback" in result.stderr
    assert "pipeline.schemas.values.ConfigError: exploration.alpha=1.5 must lie in [0, 1]" in result.stderr


def test_a_lab_arm_config_extending_ros2_inherits_its_rating(tmp_path):
    from pipeline.validation import rating_from_file

    robot = tmp_path / "robot"
    robot.mkdir()
    (robot / "ros2.yaml").write_text("defaults:\n  - base_ros2\n  - _self_\n"
                                     "rating:\n  p_max: 6.0\n  sum_max: 12.0\n")
    (robot / "lab_arm.yaml").write_text("defaults:\n  - ros2\n  - _self_\nrating:\n  p_max: 5.0\n")
    assert rating_from_file(robot / "lab_arm.yaml", [tmp_path]) == {
        "p_min": 0.0, "p_max": 5.0, "sum_max": 12.0, "preload": 2.0, "max_session_s": 600.0}
