import json
import logging

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from pipeline.data.runs import Run
from pipeline.dynamics import checkpoints, scoring
from pipeline.dynamics import cv as model_cv
from pipeline.dynamics import features as model_features
from pipeline.dynamics import model as dynamics
from pipeline.dynamics import training as train_model
from pipeline.dynamics.cv import Member
from pipeline.dynamics.features import FeatureSpec

TINY = {
    "hidden": 8, "batch_size": 4, "learning_rate": 1e-2, "lr_schedule": "constant",
    "num_steps": 20, "eval_every": 10, "checkpoint_every": 10,
}


def lag_runs(lengths=(40, 30, 50), seed=0):
    """Position a first-order lag of a linear map of held pressures; runs of unequal length."""
    rng = np.random.default_rng(seed)
    gain = np.array([[2.0, -1.0, 0.0], [0.5, 0.5, 0.5], [0.0, 1.0, -2.0]]) * 1e-3
    runs = []
    for i, num_steps in enumerate(lengths):
        pressure = np.repeat(rng.uniform(0.0, 5.0, (num_steps // 5 + 1, 3)), 5, axis=0)
        pressure = pressure[:num_steps]
        position, state = [], np.zeros(3)
        for p in pressure:
            state = 0.6 * state + 0.4 * gain @ p
            position.append(np.array([0.03, 0.35, 0.2]) + state)
        runs.append(Run(f"run{i}", np.arange(num_steps) / 10.0, pressure.astype(np.float32),
                        np.array(position, np.float32)))
    return runs


def test_loro_folds_hold_out_each_run_exactly_once():
    ids = ["c", "a", "d", "b"]
    folds = model_cv.loro_folds(ids)
    assert [held for _, held in folds] == ["a", "b", "c", "d"]
    for train, held in folds:
        assert sorted([*train, held]) == ["a", "b", "c", "d"]
        assert held not in train
    members = model_cv.cv_members(ids, seeds=(0, 1))
    assert len(members) == 9 and members[-1] == Member(("a", "b", "c", "d"), None, 0)
    with pytest.raises(ValueError, match="at least 2 runs"):
        model_cv.loro_folds(["a"])
    with pytest.raises(ValueError, match="duplicate"):
        model_cv.loro_folds(["a", "a"])


def test_vmapped_members_equal_single_fits():
    """K=1 equals fit; K=2 folds with different window counts each equal their own fit."""
    runs = lag_runs()
    single, _, table = train_model.fit(runs[:2], TINY, window=8, progress=False)
    (vmapped,), losses = model_cv.fit_members(
        runs[:2], [Member(("run0", "run1"))], TINY, window=8, progress=False)
    np.testing.assert_allclose(losses[0], table.train_loss, rtol=2e-4)
    for a, b in zip(jax.tree.leaves(single.network), jax.tree.leaves(vmapped.network)):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-6)

    members = [Member(("run0", "run1"), "run2", 3), Member(("run2",), "run0", 1)]
    params, losses = model_cv.fit_members(runs, members, TINY, window=8, progress=False)
    for member, member_params, member_losses in zip(members, params, losses):
        train_runs = [r for r in runs if r.run_id in member.train_ids]
        alone, normalizer, table = train_model.fit(train_runs, dict(TINY, seed=member.seed),
                                                   window=8, progress=False)
        np.testing.assert_allclose(member_losses, table.train_loss, rtol=2e-4)
        np.testing.assert_allclose(member_params.normalizer.pressure_mean,
                                   normalizer.pressure_mean, rtol=1e-6)
        run = runs[0]
        np.testing.assert_allclose(scoring.predict_run(member_params, run),
                                   scoring.predict_run(alone, run), rtol=1e-3, atol=1e-6)


def test_members_resume_equals_uninterrupted(tmp_path):
    runs = lag_runs((30, 30))
    members = model_cv.cv_members(["run0", "run1"], final=False)
    full, full_losses = model_cv.fit_members(runs, members, TINY, window=8, progress=False)
    folder = tmp_path / "ckpt"
    model_cv.fit_members(runs, members, TINY, window=8, progress=False,
                         checkpoint_dir=folder, stop_after_steps=10)
    assert checkpoints.latest_checkpoint(folder).name == "step_00000010.msgpack"
    resumed, resumed_losses = model_cv.fit_members(runs, members, TINY, window=8,
                                                   progress=False, checkpoint_dir=folder)
    np.testing.assert_allclose(resumed_losses, full_losses, rtol=1e-6)
    for a, b in zip(jax.tree.leaves([p.network for p in full]),
                    jax.tree.leaves([p.network for p in resumed])):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    with pytest.raises(ValueError, match="different training setup"):
        model_cv.fit_members(runs, members[:1], TINY, window=8, progress=False,
                             checkpoint_dir=folder)


def test_warning_fires_when_the_model_loses_to_the_linear_baseline(caplog):
    # an untrained network against a linear model that the lagged features fit exactly
    runs = lag_runs((60, 60))
    config = train_model.ModelTrainConfig(hidden=4).architecture()
    members = model_cv.cv_members(["run0", "run1"], final=False)
    params = [dynamics.DynamicsParams(
        dynamics.init_network(jax.random.PRNGKey(0), config),
        dynamics.fit_normalizer([r for r in runs if r.run_id in m.train_ids], False),
        config) for m in members]
    metrics = model_cv.cv_metrics(runs, members, params, num_lags=5)
    assert set(metrics["split"]) == {"cv", "cv_train"}
    held = metrics[(metrics["split"] == "cv") & (metrics["model"] == "learned")]
    assert held["loses_to_linear"].all() and len(held) == 2
    assert not metrics.loc[metrics["model"] != "learned", "loses_to_linear"].any()
    with caplog.at_level(logging.WARNING):
        messages = model_cv.warn_if_losing(metrics)
    assert len(messages) == 2 and "run0" in messages[0] and "linear lagged" in messages[0]
    assert "does not beat the linear lagged baseline" in caplog.text

    winning = pd.DataFrame({
        "run_id": ["a"] * 3, "split": ["cv"] * 3, "model": list(model_cv.MODELS),
        "mean_mm": [1.0, 5.0, 2.0], "p95_mm": [2.0, 9.0, 4.0]})
    assert model_cv.warn_if_losing(winning) == []


def test_feature_transforms_known_answer():
    spec = FeatureSpec(pressure_delta=True, step_size=True, decays=(2.0,), play_widths=(0.5,),
                       step_threshold=0.05)
    assert spec.dim == 3 + 3 + 1 + 3
    p0 = [1.0, 2.0, 0.0]
    pressures = jnp.asarray([p0, p0, [1.2, 2.0, 0.0], [1.2, 2.0, 0.0], [1.0, 2.0, -1.0],
                             [2.0, 2.0, -1.0]], jnp.float32)
    features = np.asarray(model_features.sequence(spec, pressures))
    delta, step_size, decay, play = (features[:, :3], features[:, 3:6], features[:, 6],
                                     features[:, 7:])
    np.testing.assert_allclose(delta[:, 0], [0, 0, 0.2, 0, -0.2, 1.0], atol=1e-6)
    # the step at t=5 (chamber 0 by +1) replaces the one at t=4 in every chamber
    np.testing.assert_allclose(step_size[:, 2], [0, 0, 0, 0, -1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(step_size[:, 0], [0, 0, 0.2, 0.2, -0.2, 1.0], atol=1e-6)
    # steps since the last command step: never, never, 0, 1, 0, 0
    np.testing.assert_allclose(decay, [0, 0, 1, np.exp(-0.5), 1, 1], atol=1e-6)
    # play operator of half-width 0.5 on chamber 0: 1, 1, 1, 1, 1, 1.5 (backlash)
    np.testing.assert_allclose(play[:, 0], [1, 1, 1, 1, 1, 1.5], atol=1e-6)
    # chamber 2: 0, 0, 0, 0, -0.5 (dragged down by 1 - 0.5), -0.5
    np.testing.assert_allclose(play[:, 2], [0, 0, 0, 0, -0.5, -0.5], atol=1e-6)
    np.testing.assert_allclose(model_features.play_operator(
        jnp.asarray(0.0), jnp.asarray([0.2, 1.0, -3.0]), 0.5), [0.0, 0.5, -2.5])


def test_transients_known_answer_continuous_in_the_commands_and_zero_when_held():
    spec = FeatureSpec(transients=(1.0, 10.0))
    assert spec.dim == 6
    pressures = np.zeros((6, 3), np.float32)
    pressures[2:, 0] = 0.5  # chamber 0 steps by +0.5 kPa at t=2
    pressures[4:, 1] = -1.0  # chamber 1 by -1 kPa at t=4
    features = np.asarray(model_features.sequence(spec, jnp.asarray(pressures)))
    fast, slow = features[:, :3], features[:, 3:]  # tau-major: tau 1, then tau 10
    np.testing.assert_allclose(fast[:, 0], 0.5 * np.array([0, 0, 1, np.exp(-1), np.exp(-2),
                                                           np.exp(-3)]), atol=1e-6)
    np.testing.assert_allclose(slow[:, 1], -np.array([0, 0, 0, 0, 1, np.exp(-0.1)]), atol=1e-6)
    assert np.all(features[:, 2] == 0)  # chamber 2 never moved
    # steps superpose: a second step of chamber 0 adds to what is left of the first
    again = pressures.copy()
    again[3:, 0] = 1.0
    twice = np.asarray(model_features.sequence(spec, jnp.asarray(again)))
    np.testing.assert_allclose(twice[3, 3], 0.5 * np.exp(-0.1) + 0.5, atol=1e-6)

    # linear in the step's size, with no threshold: 0.04 and 0.06 kPa differ by their ratio,
    # where the step features jump from nothing to a whole command step
    def after_step(size, features_spec):
        step = np.full((40, 3), 2.0, np.float32)
        step[20:, 0] += size
        return np.asarray(model_features.sequence(features_spec, jnp.asarray(step)))

    small, larger = after_step(0.04, spec), after_step(0.06, spec)
    np.testing.assert_allclose(larger, 1.5 * small, rtol=1e-4, atol=1e-7)
    steps = FeatureSpec(step_size=True, decays=(10.0,), step_threshold=0.05)
    assert np.all(after_step(0.04, steps)[20:] == 0) and after_step(0.06, steps)[20, 3] == 1.0
    # a held command: the transients fade to nothing, the held step size stays
    assert np.abs(after_step(1.0, spec)[-1]).max() < 1.0 * np.exp(-19 / 10.0) + 1e-6
    assert after_step(1.0, steps)[-1, 0] == pytest.approx(1.0)


def test_band_coverage_and_ensemble_mean():
    mean, std = np.zeros((4, 3)), np.full((4, 3), 0.5)
    observed = np.array([[0.0, 0.9, 1.1]] * 4)
    assert model_cv.band_coverage(mean, std, observed) == pytest.approx(2 / 3)


def test_protocol_defaults_cv_for_recorded_data_and_split_for_the_simulated_arm(make_cfg):
    from pipeline.keys import model_protocol as protocol

    assert protocol(make_cfg()) == "split"
    assert protocol(make_cfg("robot=sorolex_csv")) == "cv"
    assert protocol(make_cfg("robot=sorolex_csv", "dataset.protocol=split")) == "split"
    assert protocol(make_cfg("dataset.protocol=cv")) == "cv"


def test_the_cv_key_leaves_out_the_train_fraction(make_cfg, sorolex_dir):
    from pipeline.keys import fit_model_spec

    cv_spec, _ = fit_model_spec(make_cfg("robot=sorolex_csv", f"robot.data_dir={sorolex_dir}"))
    assert cv_spec["dataset"]["protocol"] == "cv" and "train_fraction" not in cv_spec["dataset"]


def test_fit_model_cv_writes_fold_metrics_and_feeds_held_out_goals(make_cfg):
    from pipeline.__main__ import run
    from pipeline.data.schemas import MODEL_METRICS, read_table

    cfg = make_cfg("experiment=quick", "stage=fit_model", "dataset.protocol=cv",
                   "model.hidden=8", "model.num_steps=20", "model.checkpoint_every=10",
                   "dataset.window=16")
    artifact = run(cfg)["fit_model"]
    metrics, meta = read_table(artifact.file("metrics.parquet"), MODEL_METRICS)
    assert meta["units"]["mean_mm"] == "mm" and meta["config"]["dataset"]["protocol"] == "cv"
    ids = sorted(metrics["run_id"].unique())
    assert len(ids) == 3
    held = metrics[metrics["split"] == "cv"]
    assert sorted(held["held_out"]) == sorted(ids * 3) and (held["run_id"] == held["held_out"]).all()
    assert len(metrics[metrics["split"] == "cv_train"]) == 3 * 2 * 3
    assert sorted(metrics.loc[metrics["split"] == "train", "run_id"].unique()) == ids
    assert set(metrics["fold"]) == {-1, 0, 1, 2}
    split = json.loads(artifact.file("split.json").read_text())
    assert split["train"] == ids and sorted(f["held_out"] for f in split["folds"]) == ids
    summary = artifact.manifest["summary"]
    assert summary["protocol"] == "cv" and isinstance(summary["warnings"], list)
    losing = held[(held["model"] == "learned") & held["loses_to_linear"]]["run_id"].tolist()
    assert len(summary["warnings"]) == len(losing)

    from pipeline.data.alignment import runs_at_model_rate
    from pipeline.data.schemas import ALIGNED
    from pipeline.infra.artifacts import ArtifactStore
    from pipeline.keys import key
    from pipeline.stages._environment import config_environment

    store = ArtifactStore(cfg.paths.artifact_dir)
    aligned_artifact = store.require("align", key("align", cfg))
    _, train_params, eval_params = config_environment(cfg, artifact, aligned_artifact)
    aligned, _ = read_table(aligned_artifact.file("aligned.parquet"), ALIGNED)
    measured = np.concatenate([r.positions_m for r in runs_at_model_rate(aligned, 10.0)])
    np.testing.assert_allclose(np.asarray(eval_params.goal_set), measured, atol=1e-7)
    assert train_params.goal_set.shape == eval_params.goal_set.shape
    assert not np.allclose(np.asarray(train_params.goal_set), measured)  # model predictions

    # what a replayed reference replays: the measured path of every held-out run, from 0 s
    from pipeline.stages._environment import config_inputs, recorded_paths
    from pipeline.stages.evaluate import tracking_settings

    paths = recorded_paths(config_inputs(cfg, artifact, aligned_artifact))
    runs = runs_at_model_rate(aligned, 10.0)
    assert sorted(paths) == ids
    for recording in runs:
        times, positions = paths[recording.run_id]
        np.testing.assert_allclose(positions, recording.positions_m, atol=1e-7)
        np.testing.assert_allclose(times, np.arange(len(recording)) / 10.0, atol=1e-6)
    cfg.evaluation.references = {"walk": {"kind": "replay"}}
    assert sorted(tracking_settings(cfg, paths).recorded) == ids
    assert tracking_settings(cfg).recorded == {}  # no artifacts: nothing read

    # the tracking oracle's protocols replay the same paths
    from experiments.tracking_oracle import plant_sets

    _, protocols = plant_sets([f"paths.output_dir={cfg.paths.output_dir}", "experiment=quick",
                               "dataset.protocol=cv", "model.hidden=8", "model.num_steps=20",
                               "model.checkpoint_every=10", "dataset.window=16",
                               "+evaluation.references.walk={kind:replay}"])
    tracking, plants = protocols["all runs"]
    assert sorted(tracking.recorded) == ids and "learned" in plants


def test_a_model_with_features_round_trips_through_its_file(tmp_path):
    runs = lag_runs((30,))
    config = train_model.ModelTrainConfig(hidden=4, cell="gru", play_widths_kpa=(0.5,),
                                          step_decays=(2.0,), step_size=True,
                                          pressure_transients=(3.0,)).architecture()
    params = dynamics.DynamicsParams(dynamics.init_network(jax.random.PRNGKey(1), config),
                                     dynamics.fit_normalizer(runs, False), config)
    checkpoints.save_dynamics(tmp_path / "model.msgpack", params)
    loaded = checkpoints.load_dynamics(tmp_path / "model.msgpack")
    assert loaded.config == config
    np.testing.assert_allclose(scoring.predict_run(loaded, runs[0]),
                               scoring.predict_run(params, runs[0]), rtol=1e-6)


def test_a_model_saved_before_the_transient_inputs_loads_without_them(tmp_path):
    config = train_model.ModelTrainConfig(hidden=4, cell="gru", step_decays=(2.0,),
                                          step_size=True, pressure_transients=()).architecture()
    params = dynamics.DynamicsParams(dynamics.init_network(jax.random.PRNGKey(1), config),
                                     dynamics.fit_normalizer(lag_runs((30,)), False), config)
    state = checkpoints.model_state_dict(params)
    stored = json.loads(state["config"])
    del stored["pressure_transients"]  # as files written before the setting was
    state["config"] = json.dumps(stored)
    loaded = checkpoints.model_from_state_dict(state)
    assert loaded.config == config and loaded.config.input_dim == 3 + 3 + 1


def test_subsampled_members_never_train_on_their_held_out_run():
    from experiments.model_cv_study import subsampled

    members = model_cv.cv_members(list("abcdefg"), seeds=[0, 1, 2], final=False)
    drawn = subsampled(members, drop=2)
    assert drawn == subsampled(members, drop=2)  # a pure function of (seed, fold)
    for before, after in zip(members, drawn):
        assert (after.held_out, after.seed) == (before.held_out, before.seed)
        assert len(after.train_ids) == 4 and set(after.train_ids) < set(before.train_ids)
        assert after.held_out not in after.train_ids
    # the members of one fold see different subsets (seeds 0, 1, 2 of fold "a")
    assert len({m.train_ids for m in drawn if m.held_out == "a"}) > 1
    with pytest.raises(SystemExit, match="only 6 training runs"):
        subsampled(members, drop=6)


def test_model_steps_measures_the_held_first_command_and_the_answers_to_steps():
    from experiments.model_steps import data_drift, step_answers

    # a run held at its first command for 1.9 s at 10 Hz: too short to measure from 5 s
    times = np.arange(40) / 10.0
    pressures = np.full((40, 3), 2.0, np.float32)
    pressures[20:, 0] = 3.0
    positions = np.zeros((40, 3), np.float32)
    positions[:, 0] = 1e-5 * np.arange(40)
    [(run_id, held_s, moved)] = data_drift([Run("held", times, pressures, positions)])
    assert run_id == "held" and held_s == pytest.approx(1.9) and np.isnan(moved)  # < 5 s
    times = np.arange(200) / 10.0
    pressures = np.full((200, 3), 2.0, np.float32)
    pressures[170:, 1] = 2.5
    positions = np.zeros((200, 3), np.float32)
    positions[:, 2] = 1e-5 * np.arange(200)  # 0.01 mm a step
    [(_, held_s, moved)] = data_drift([Run("long", times, pressures, positions)])
    assert held_s == pytest.approx(16.9) and moved == pytest.approx(0.01 * (169 - 50), rel=1e-4)

    config = train_model.ModelTrainConfig(hidden=4, cell="gru",
                                          pressure_transients=(1.0, 3.0)).architecture()
    params = dynamics.DynamicsParams(dynamics.init_network(jax.random.PRNGKey(2), config),
                                     dynamics.fit_normalizer(lag_runs((30,)), False), config)
    commands = jnp.asarray(np.random.default_rng(0).uniform(1.0, 3.0, (5, 3)), jnp.float32)
    answers = step_answers(params, np.full(3, 2.0, np.float32), jnp.asarray([0.03, 0.35, 0.2]),
                           commands, [0.0, 0.5], 10.0)
    assert set(answers) == {"0", "0.5", "drift"}
    assert all(v.shape == (5,) and np.all(np.isfinite(v)) for v in answers.values())
    assert np.all(answers["0"] < answers["0.5"])  # no step: only the model's own drift
