"""Calibrating the simulated arm: bounds, recovery of known physics, the stage, physics_from."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.__main__ import apply_physics_from, run
from pipeline.arm import calibration as calib
from pipeline.arm import sim_arm
from pipeline.arm.twins import load_physics
from pipeline.chain import stages_to_run
from pipeline.data.runs import Run
from pipeline.data.schemas import DataError, read_table
from pipeline.dynamics.calibration_report import PARAMETERS, fitted_physics, fold_weights
from pipeline.schemas import ConfigError, SimPhysics, Stage

INIT = calib.sim_physics_values(SimPhysics())
INIT.pop("substeps")


def test_bounds_hold_whatever_the_unconstrained_values():
    param = calib.Parameterization.create(["chamber_angles_deg", "bend_gain", "creep_gain"],
                                          INIT)
    assert param.size == 5
    # angles are bounded around their start, the others absolutely
    np.testing.assert_allclose(param.lower[:3], np.array(INIT["chamber_angles_deg"]) - 60.0)
    z = np.concatenate([np.full((1, 5), -1e6), np.full((1, 5), 1e6),
                        np.random.default_rng(0).normal(0, 30, (20, 5))]).astype(np.float32)
    for z_m in z:
        values = param.to_physics(jnp.asarray(z_m))
        flat = np.concatenate([np.atleast_1d(values[n]) for n in param.names])
        assert np.all(flat >= param.lower - 1e-4) and np.all(flat <= param.upper + 1e-4)
    assert np.ndim(param.to_physics(jnp.zeros(5))["bend_gain"]) == 0
    # a start on a bound starts just inside it; the round trip keeps an inner value
    z0 = param.from_physics({**INIT, "creep_gain": 0.0})
    assert np.all(np.isfinite(z0))
    back = param.to_physics(jnp.asarray(z0, jnp.float32))
    assert float(back["bend_gain"]) == pytest.approx(INIT["bend_gain"], rel=1e-4)
    assert 0.0 < float(back["creep_gain"]) < 0.05


def test_unknown_or_repeated_parameters_are_refused():
    with pytest.raises(ValueError, match="cannot fit \\['base_position_m'\\]"):
        calib.Parameterization.create(["base_position_m"], INIT)
    with pytest.raises(ValueError, match="twice"):
        calib.Parameterization.create(["bend_gain", "bend_gain"], INIT)


def _tiny_runs(physics: dict, num_frames: int, noise_m: float, seed: int) -> list[Run]:
    """Two runs the simulator itself generates at 10 Hz (1 substep), with position noise."""
    template = sim_arm.SimParams.noise_free(physics, 10.0, 1)
    rng = np.random.default_rng(seed)
    runs = []
    for i in range(2):
        hold = rng.uniform(0.0, 5.0, (num_frames // 5, 3))
        commands = np.concatenate([np.full((3, 3), 2.0), np.repeat(hold, 5, axis=0)])
        commands = commands[:num_frames].astype(np.float32)
        state = sim_arm.settled_state(template, jnp.full(3, 2.0), jnp.zeros(3))
        truth = np.asarray(sim_arm.predict_positions(template, state, jnp.asarray(commands)))
        offset = np.array([0.002, 0.0, -0.001]) * (1 if i else -1)
        runs.append(Run(f"r{i}", np.arange(num_frames) / 10.0, commands,
                        (truth + offset + rng.normal(0, noise_m, truth.shape)).astype(np.float32)))
    return runs


def test_recovers_known_physics_from_the_simulators_own_noisy_data():
    truth = {**INIT, "bend_gain": 0.08, "pressure_tau_s": 0.3, "hysteresis_kpa": 0.0,
             "creep_gain": 0.0}
    runs = _tiny_runs(truth, 60, noise_m=1e-4, seed=0)
    start = {**truth, "bend_gain": 0.04, "pressure_tau_s": 0.1}
    template = sim_arm.SimParams.noise_free(start, 10.0, 1)
    param = calib.Parameterization.create(["bend_gain", "pressure_tau_s"], start)
    batch = calib.RunBatch.from_runs(runs)
    result = calib.calibrate(template, param, start, batch, np.ones((1, 2)), num_steps=150,
                             learning_rate=0.1, num_restarts=2, restart_std=0.5,
                             key=jax.random.key(0))
    fitted = result.physics[0]
    assert float(fitted["bend_gain"]) == pytest.approx(0.08, rel=0.05)
    assert float(fitted["pressure_tau_s"]) == pytest.approx(0.3, rel=0.15)
    # the nuisance offsets found each run's rest offset (m)
    np.testing.assert_allclose(result.offsets[0, 1] - result.offsets[0, 0],
                               [0.004, 0.0, -0.002], atol=3e-4)
    # the fit explains the data to about its noise: 0.1 mm per axis
    assert result.losses[-1, 0, result.chosen[0]] < 0.1
    assert result.losses[-1, 0, result.chosen[0]] < result.losses[0, 0, result.chosen[0]] / 20
    # the physics predict a run from its first pose (no fitted offset) to within its noise
    first_pose = calib.open_loop(template, param, result.z, batch)[0, 0]
    assert 1e3 * np.linalg.norm(first_pose - runs[0].positions_m, axis=1).mean() < 0.6
    # at the training runs' mean offset the run is off by its own rest offset, (2, 0, -1) mm
    mean_offset = calib.training_mean_offsets(result.offsets, np.ones((1, 2)))
    at_mean = calib.open_loop(template, param, result.z, batch, mean_offset)[0, 0]
    np.testing.assert_allclose(1e3 * (runs[0].positions_m - at_mean).mean(0), [-2.0, 0.0, 1.0],
                               atol=0.3)


def test_fold_weights_hold_each_run_out_once_then_use_all():
    folds, weights = fold_weights(3, True)
    assert folds == [0, 1, 2, "all"]
    np.testing.assert_array_equal(weights, [[0, 1, 1], [1, 0, 1], [1, 1, 0], [1, 1, 1]])
    assert fold_weights(3, False)[0] == ["all"]


def test_a_folds_physics_rest_where_its_training_runs_rest():
    # 2 runs: fold 0 holds out run 0, fold 1 run 1, the last fold trains on both
    weights = np.array([[0, 1], [1, 0], [1, 1]], np.float32)
    offsets = np.array([[[9.0, 9.0, 9.0], [0.001, 0.002, 0.0]],
                        [[0.003, 0.0, 0.0], [9.0, 9.0, 9.0]],
                        [[0.001, 0.0, 0.0], [0.003, 0.002, 0.0]]])
    result = calib.FitResult(np.zeros((3, 1)), offsets, np.zeros(3, int), np.zeros((1, 3, 1)),
                             [{"bend_gain": np.float64(0.1 * (f + 1))} for f in range(3)])
    init = {"bend_gain": 0.5, "base_position_m": [0.03, 0.47, 0.2]}
    held_out_0 = fitted_physics(init, result, 10, fold=0, weights=weights)
    assert held_out_0["bend_gain"] == pytest.approx(0.1)
    assert held_out_0["base_position_m"] == pytest.approx([0.031, 0.472, 0.2])  # run 1 alone
    assert held_out_0["rest_pose_std_m"] == pytest.approx([0.0, 0.0, 0.0])
    every = fitted_physics(init, result, 10, weights=weights)  # the fit on all runs
    assert every["base_position_m"] == pytest.approx([0.032, 0.471, 0.2])
    assert every["rest_pose_std_m"] == pytest.approx([0.001, 0.001, 0.0])
    assert every == fitted_physics(init, result, 10) and every["substeps"] == 10


TINY = ("experiment=quick", "robot.num_runs=2", "exploration.num_steps=24",
        "stage=calibrate", "dataset.model_hz=10", "calibration.rate_hz=10",
        "calibration.substeps=1", "calibration.num_steps=3", "calibration.num_restarts=2",
        "calibration.fitted=[bend_gain,pressure_tau_s]")


def test_calibrate_stage_writes_its_artifact_and_reuses_it(make_cfg):
    cfg = make_cfg(*TINY)
    assert stages_to_run(cfg) == [Stage.collect, Stage.align, Stage.calibrate]
    artifact = run(cfg)["calibrate"]
    assert artifact.key == keys.key("calibrate", cfg)
    first = artifact.file("artifact.json").stat().st_ino
    again = run(cfg)["calibrate"]
    assert again.path == artifact.path
    assert again.file("artifact.json").stat().st_ino == first  # reused, not rewritten

    params, meta = read_table(artifact.file("parameters.parquet"), PARAMETERS)
    assert meta["schema"] == "calibrated_parameters"
    assert set(params["fold"]) == {"sim-000", "sim-001", "all"}
    assert set(params["name"]) == {"bend_gain", "pressure_tau_s"}
    assert (params["value"] >= params["lower"]).all() and (params["value"] <= params["upper"]).all()
    assert dict(zip(params["name"], params["unit"]))["pressure_tau_s"] == "s"
    physics = json.loads(artifact.file("physics.json").read_text())["physics"]
    # every SimPhysics field but the spread between sessions, which is not fitted
    assert set(SimPhysics.__dataclass_fields__) - {"session_std"} == set(physics)
    # the integrator steps of the physics (what a twin of them integrates with), not the fit's
    assert physics["substeps"] == cfg.calibration.init.substeps != cfg.calibration.substeps
    metrics = __import__("pandas").read_parquet(artifact.file("metrics.parquet"))
    assert set(metrics["model"]) == {"sim_calibrated", "sim_calibrated_first_pose",
                                     "sim_default", "sim_default_first_pose", "mean_position",
                                     "linear_lagged"}
    assert set(metrics["split"]) == {"train", "test"}
    assert artifact.file("figures/reconstruction.png").stat().st_size > 0
    # a different setting is a different artifact
    other = make_cfg(*TINY, "calibration.seed=1")
    assert keys.key("calibrate", other) != keys.key("calibrate", cfg)

    # robot.physics_from by key (and by folder) replaces the physics, for sim and the twin
    sim_cfg = apply_physics_from(make_cfg(f"robot.physics_from={artifact.key}"))
    assert sim_cfg.robot.physics.bend_gain == pytest.approx(physics["bend_gain"])
    assert list(sim_cfg.robot.physics.base_position_m) == pytest.approx(
        physics["base_position_m"])
    twin_cfg = apply_physics_from(make_cfg("robot=ros2", f"robot.physics_from={artifact.path}"))
    assert twin_cfg.robot.twin.physics.pressure_tau_s == pytest.approx(
        physics["pressure_tau_s"])
    assert load_physics(str(artifact.path), "/nonexistent") == physics


def test_run_after_keeps_the_steps_from_a_time_into_the_run():
    run_ = Run("r", np.array([10.0, 10.5, 11.0, 11.5]),
               np.arange(12, dtype=np.float32).reshape(4, 3),
               np.arange(12, dtype=np.float32).reshape(4, 3) * 1e-3)
    later = run_.after(1.0)
    np.testing.assert_array_equal(later.times_s, [11.0, 11.5])
    np.testing.assert_array_equal(later.pressures_kpa[0], [6.0, 7.0, 8.0])
    assert later.run_id == "r" and len(run_.after(0.0)) == 4
    with pytest.raises(ValueError, match=r"run 'r' lasts 1.5 s: less than two steps of it are "
                                         r"left from 1.5 s on"):
        run_.after(1.5)


def test_calibrate_stage_starts_each_run_later(make_cfg):
    whole = run(make_cfg(*TINY))["calibrate"]
    later = run(make_cfg(*TINY, "calibration.start_s=2"))["calibrate"]
    assert later.key != whole.key
    steps = {}
    for name, artifact in (("whole", whole), ("later", later)):
        metrics = pd.read_parquet(artifact.file("metrics.parquet"))
        steps[name] = metrics.groupby("run_id")["steps"].first()
    # 2 s fewer of every run at dataset.model_hz=10, scored and fitted
    assert ((steps["whole"] - steps["later"]) == 20).all()


def test_calibrate_stage_refuses_a_start_outside_the_runs(make_cfg):
    with pytest.raises(ConfigError, match=r"calibration.start_s=-1"):
        run(make_cfg(*TINY, "calibration.start_s=-1"))
    cfg = make_cfg(*TINY, "calibration.start_s=1000")
    with pytest.raises(DataError, match=r"aligned.parquet: calibration.start_s=1000: run 'sim-000' "
                                        r"lasts .* s: less than two steps of it are left from "
                                        r"1000 s on"):
        run(cfg)
    written = Path(cfg.paths.artifact_dir) / "calibrate"  # nothing but a lock file
    assert not [p for p in written.glob("*") if not p.name.startswith(".")]


def test_physics_from_names_what_it_could_not_find(make_cfg):
    with pytest.raises(FileNotFoundError, match="physics_from='nokey'"):
        apply_physics_from(make_cfg("robot.physics_from=nokey"))


def test_sim_sorolex_composes_and_simulates(make_cfg):
    cfg = make_cfg("robot=sim_sorolex")
    assert cfg.robot.kind.value == "sim"
    # each session draws its own physics around the fitted ones; it needs no recordings
    assert cfg.robot.replay is None and cfg.robot.limits.p_min == 0.0
    assert "chamber_gains" in cfg.robot.physics.session_std
    replay = make_cfg("robot=sim_sorolex_replay")  # the same arm replaying the paper's runs
    assert replay.robot.replay.kind.value == "sorolex_csv" and replay.robot.limits.p_min == -3.0
    assert replay.robot.physics == cfg.robot.physics
    defaults = OmegaConf.structured(SimPhysics)
    assert cfg.robot.physics.bend_gain != defaults.bend_gain  # holds fitted values
    params = sim_arm.SimParams.from_config(cfg.robot)
    preload = jnp.full(3, 2.0)
    state = sim_arm.settled_state(params, preload, jnp.zeros(3))
    rest = np.asarray(sim_arm.tip_position(params, state)) * 1e3
    # the real runs rest near (29-33, 353-354, 200-202) mm
    np.testing.assert_allclose(rest, [31.0, 353.5, 201.2], atol=3.0)
    bent = sim_arm.advance(params, state, jnp.array([5.0, 0.5, 0.5]), 300)
    lateral = np.hypot(*(np.asarray(sim_arm.tip_position(params, bent)) * 1e3 - rest)[[0, 2]])
    assert 8.0 < lateral < 60.0
