"""Sessions as data and stage=improve: a session's run in collect's format, joined to a model's
data with its provenance and weighed; windows drawn by weight; the ensemble's disagreement; the
rounds end to end on the simulated arm, resumed after an interruption; the refusals."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import jax
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from pipeline import chain, keys
from pipeline.config import PROJECT_ROOT
from pipeline.data.schemas import DataError
from pipeline.data.sessions import (
    SESSION_PREFIX,
    arm_identity,
    check_session,
    read_session,
    session_tables,
)
from pipeline.data.windows import make_windows, weighted_starts
from pipeline.dynamics.disagreement import disagreement_m2, held_at_model_rate, most_disputed
from pipeline.dynamics.model import predict_sequence
from pipeline.infra.artifacts import ArtifactStore
from pipeline.schemas import ConfigError, PressureRating, Stage
from pipeline.stages.improve import goal_pool, improve
from tests.conftest import built_once, compose_config
from tests.test_adapt_stage import small_model

# the quick chain shrunk further: one seed of the gradient trainer, a small model
SMALL = ["experiment=quick", "agent.num_seeds=1", "agent.total_timesteps=4096",
         "model.num_steps=60", "model.hidden=16", "evaluation.num_episodes=8",
         "control.policy=apg", "improve.rounds=1", "improve.arm_s=10", "improve.goal_s=5",
         "improve.model_steps=40", "improve.policy_timesteps=2048"]


# ------------------------------------------------------------------------------------------------
# libraries, by hand
# ------------------------------------------------------------------------------------------------
def test_weighted_starts_draw_each_run_by_its_weight():
    windows = make_windows([4, 3, 3], length=2, stride=1)  # starts [0 1 2] [4 5] [7 8]
    starts = weighted_starts(windows, [1.0, 2.5, 0.0])
    # run 0 once; run 1 twice and, for the half, its windows at floor(k / 0.5), k = 0: window 0
    assert starts.tolist() == [0, 1, 2, 4, 5, 4, 5, 4]
    with pytest.raises(ValueError, match="finite and >= 0"):
        weighted_starts(windows, [1.0, -1.0, 1.0])


def test_the_disagreement_of_two_models_is_a_quarter_of_their_squared_gap():
    first, second = small_model(False), small_model(True)
    commands = np.array([[[2.0, 2.0, 2.0], [3.0, 1.0, 2.0]], [[2.0, 2.0, 2.0], [2.0, 2.0, 2.0]]])
    pressures = held_at_model_rate(commands, 3)
    assert pressures.shape == (2, 6, 3) and (pressures[0, 3:] == [3.0, 1.0, 2.0]).all()
    pose = np.array([0.031, 0.47, 0.201])
    scores = disagreement_m2([first, second], pressures, pose)
    for c in range(2):
        a = np.asarray(predict_sequence(first, pressures[c], pose))
        b = np.asarray(predict_sequence(second, pressures[c], pose))
        # two members: each is |a - b| / 2 from their mean
        expected = np.mean(np.sum((a - b) ** 2, axis=-1) / 4)
        assert scores[c] == pytest.approx(expected, rel=1e-4)
    assert disagreement_m2([first, first], pressures, pose) == pytest.approx([0.0, 0.0])
    assert most_disputed(np.array([0.1, 0.5, 0.5, 0.2]), 2).tolist() == [1, 2]


def test_a_sessions_rows_become_one_run():
    nan = np.nan
    periods = pd.DataFrame({
        "publish_t": [0.0, 0.5, nan, 1.0, nan],
        "goal_index": [-2, 0, 0, 1, -1],
        "t": [0.0, 0.5, 0.5, 1.0, 1.5],
        **{f"p_cmd_{j}": [2.0, 3.0, 3.0, 4.0, nan] for j in range(3)},
        "goal_x": [nan, 0.01, 0.01, 0.02, nan], "goal_y": [nan, 0.3, 0.3, 0.3, nan],
        "goal_z": [nan, 0.2, 0.2, 0.2, nan],
        "ref_x": [nan, nan, nan, 0.05, nan], "ref_y": [nan, nan, nan, 0.35, nan],
        "ref_z": [nan, nan, nan, 0.25, nan]})
    frames = pd.DataFrame({"t": [0.0, 0.01, 0.009, 0.02], "x": [0.0, 0.1, 0.2, nan],
                           "y": [0.3] * 4, "z": [0.2] * 4,
                           "valid": [True, True, True, False]})
    run = session_tables(periods, frames, "session-control-abc", "control:x", True, 3)
    # every published command but the last row's (the pose at the end)
    assert run.commands["t"].tolist() == [0.0, 0.5, 1.0]
    assert run.commands["p_cmd_1"].tolist() == [2.0, 3.0, 4.0]
    # a stamp not after the earlier ones is dropped; a lost marker stays as an invalid frame
    assert run.mocap["t"].tolist() == [0.0, 0.01, 0.02]
    assert run.mocap["valid"].tolist() == [True, True, False]
    # served periods: the goal, or the reference point where one is followed
    assert run.targets["goal_x"].tolist() == [0.01, 0.01, 0.05]
    assert run.runs.iloc[0].to_dict() == {"run_id": "session-control-abc", "source": "control:x",
                                          "complete": True, "n_commands": 3, "n_frames": 3}


def test_a_session_of_another_arm_or_rate_is_refused_naming_it(tmp_path):
    periods = pd.DataFrame({"publish_t": [0.0, 0.5], "goal_index": [0, 0], "t": [0.0, 0.5],
                            **{f"p_cmd_{j}": [2.0, 2.5] for j in range(3)},
                            **{f"goal_{a}": [0.0, 0.0] for a in "xyz"},
                            **{f"ref_{a}": [np.nan] * 2 for a in "xyz"}})
    frames = pd.DataFrame({"t": np.arange(60) / 100.0, "x": 0.0, "y": 0.3, "z": 0.2,
                           "valid": True})
    run = session_tables(periods, frames, "session-control-x", "control:x", True, 3)
    arm = arm_identity(PressureRating())
    run = run.__class__(run.commands, run.mocap, run.runs, run.targets,
                        {"control_hz": 2.0, "arm": arm})
    check_session(run, "s", n_valves=3, control_hz=2.0, mocap_hz=100.0, arm=arm)
    for settings, column in (({"control_hz": 5.0}, "control_hz"), ({"mocap_hz": 50.0}, "'t'"),
                             ({"arm": arm_identity(PressureRating(p_max=9.0))}, "arm")):
        given = {"n_valves": 3, "control_hz": 2.0, "mocap_hz": 100.0, "arm": arm, **settings}
        with pytest.raises(DataError, match=column) as error:
            check_session(run, "the/session", **given)
        assert str(error.value).startswith("the/session")


# ------------------------------------------------------------------------------------------------
# the stage, end to end on the simulated arm
# ------------------------------------------------------------------------------------------------
def _train(folder):
    output = folder / "outputs"
    cfg = compose_config(output, *SMALL)
    policy = chain.control_policy_config(cfg)
    for job in chain.plan(compose_config(output, *SMALL, "stage=train_ppo", "agent=apg"),
                          lambda variant: keys.key("train_ppo", variant)):
        chain.stage_function(job.stage)(job.cfg)
    assert ArtifactStore(cfg.paths.artifact_dir).find("train_ppo", keys.key("train_ppo", policy))


@pytest.fixture
def trained(tmp_path_factory, tmp_path):
    """The shrunk quick chain's policy (``control.policy=apg``): trained once for the session,
    each test writing into its own copy of the outputs."""
    built = built_once(tmp_path_factory, "improve", _train)
    shutil.copytree(built / "outputs", tmp_path / "outputs")
    return tmp_path / "outputs"


def test_rounds_run_end_to_end_and_resume_after_an_interruption(trained, monkeypatch):
    cfg = compose_config(trained, *SMALL, "stage=improve")
    store = ArtifactStore(cfg.paths.artifact_dir)
    real = chain.stage_function

    def interrupted(stage):
        if stage is Stage.train_ppo:
            def fail(_cfg):
                raise KeyboardInterrupt("interrupted while retraining")
            return fail
        return real(stage)

    monkeypatch.setattr(chain, "stage_function", interrupted)
    with pytest.raises(KeyboardInterrupt):
        improve(cfg)
    monkeypatch.setattr(chain, "stage_function", real)
    finished = {stage: {p.name: json.loads((p / "artifact.json").read_text())["created"]
                        for p in (store.root / stage).iterdir() if (p / "artifact.json").is_file()}
                for stage in ("control", "align", "fit_model")}
    assert finished["control"] and finished["fit_model"]  # the drive and refit had finished
    rounds = [p for p in (store.root / "improve").iterdir() if (p / "artifact.json").is_file()]
    assert len(rounds) == 1  # round 0's: the deployed policy's evaluation

    artifact = improve(cfg)
    # the steps finished before the interruption were reused, not run again
    for stage, created in finished.items():
        for key, stamp in created.items():
            assert json.loads((store.root / stage / key / "artifact.json").read_text())[
                "created"] == stamp
    table = pd.read_parquet(artifact.file("rounds.parquet"))
    assert table["round"].tolist() == [0, 1]
    first, second = table.iloc[0], table.iloc[1]
    assert first["arm_s"] == 0 and 9.0 <= second["arm_s"] <= 11.0  # 2 goals of 5 s
    assert second["drive_goals"] == 2 and np.isfinite(second["model_after_mean_mm"])
    assert second["wall_train_ppo_s"] > 0 and second["wall_compute_s"] >= second["wall_fit_model_s"]
    for column in ("plant_median_mm", "plant_within_1mm", "plant_p90_mm", "model_median_mm"):
        assert np.isfinite(table[column]).all(), column
    assert artifact.file("rounds.png").is_file() and "| round |" in artifact.file(
        "report.md").read_text()

    # the round's session joined the model's data, with its provenance
    round_cfg = keys.key("align", cfg)  # the deployed data: no session
    aligned = [p for p in (store.root / "align").iterdir() if p.name != round_cfg
               and (p / "aligned.parquet").is_file()]
    assert len(aligned) == 1
    meta = json.loads(pq.read_schema(aligned[0] / "aligned.parquet").metadata[b"sorolearn"])
    (run_id, provenance), = meta["provenance"]["sessions"].items()
    assert run_id.startswith(SESSION_PREFIX)
    assert provenance["stage"] == "control" and provenance["controller"]["task"] == "reach"
    session = read_session(provenance["path"])
    assert session.run_id == run_id and len(session.targets) > 0
    models = [json.loads((p / "split.json").read_text()) for p in (store.root / "fit_model")
              .iterdir() if (p / "split.json").is_file()]
    assert any(run_id in split["train"] for split in models)


def test_the_plan_of_the_rounds_is_printed_and_nothing_runs(trained, caplog):
    cfg = compose_config(trained, *SMALL, "stage=improve", "improve.rounds=3", "dry_run=true")
    before = sorted(p.name for p in ArtifactStore(cfg.paths.artifact_dir).root.iterdir())
    with caplog.at_level("INFO"):
        assert improve(cfg) is None
    plan = caplog.text
    assert "evaluate (deployed)" in plan and "pending" in plan
    assert sorted(p.name for p in ArtifactStore(cfg.paths.artifact_dir).root.iterdir()) == before


@pytest.mark.parametrize("override, message", [
    ("improve.arm_s=601", "robot.rating.max_session_s"),
    ("improve.arm_s=0", "robot.rating.max_session_s"),
    ("improve.explore_share=0.5", "env.ensemble_seeds"),
    ("improve.refit=never", "improve.refit"),
    ("improve.goal_s=20", "no time for one goal"),
])
def test_bad_settings_are_refused_naming_them(trained, override, message):
    cfg = compose_config(trained, *SMALL, "stage=improve", override)
    with pytest.raises(ConfigError, match=message):
        improve(cfg)


@pytest.mark.slow  # a pipeline process; fast: the same refusal in process (above)
def test_the_entry_point_refuses_a_budget_beyond_the_rating_in_one_line(tmp_path):
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    result = subprocess.run(
        [sys.executable, "-m", "pipeline", "stage=improve", "experiment=quick",
         f"paths.output_dir={tmp_path}", "improve.arm_s=3600"],
        cwd=PROJECT_ROOT, capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 1
    errors = [line for line in result.stderr.splitlines() + result.stdout.splitlines()
              if "ConfigError" in line]
    assert len(errors) == 1 and "max_session_s" in errors[0], result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "artifacts").exists() or not any((tmp_path / "artifacts").iterdir())


def test_a_session_of_another_arm_joins_no_data(trained, tmp_path):
    cfg = compose_config(trained, *SMALL)
    store = ArtifactStore(cfg.paths.artifact_dir)
    deployed = store.require("train_ppo", keys.key("train_ppo", chain.control_policy_config(cfg)))
    goals = goal_pool(deployed, store, cfg)[0][:2] * 1000.0
    session = chain.stage_function(Stage.control)(compose_config(
        trained, *SMALL, "stage=control", "control.hold_s=2", "control.arm_seed=7",
        f"control.goals={np.round(goals, 2).tolist()}")).path
    assert read_session(session).commands["t"].size == 8  # 2 goals of 4 periods
    other = tmp_path / "control" / f"{session.name}-elsewhere"  # its own key
    shutil.copytree(session, other)
    for name in ("commands", "mocap", "runs", "targets"):
        path = other / "run" / f"{name}.parquet"
        table = pq.read_table(path)
        meta = json.loads(table.schema.metadata[b"sorolearn"])
        meta["provenance"]["control_hz"] = 5.0
        pq.write_table(table.replace_schema_metadata(
            {**table.schema.metadata, b"sorolearn": json.dumps(meta).encode()}), path)
    joined = compose_config(trained, *SMALL, "stage=align", f"dataset.sessions=[{other}]")
    with pytest.raises(DataError, match=r"5\.0 Hz"):
        chain.stage_function(Stage.align)(joined)
    assert store.find("align", keys.key("align", joined)) is None
    jax.clear_caches()


@pytest.mark.slow
@pytest.mark.ros
def test_a_round_over_ros2_on_the_twin(tmp_path, ros_domain):
    """The whole path on the arm's side: runs collected over ROS 2 from the twin, the policy
    trained on them, then a round of stage=improve whose drive goes through the gate to the twin
    and ends at the preload, its session joining the refitted model's data."""
    pytest.importorskip("rclpy")
    from pipeline.data.schemas import CMD_COLUMNS
    from tests.test_ros2_link import Pipeline, received, stop

    pipe = Pipeline(tmp_path, ros_domain)
    pipe.overrides = [*SMALL, "robot=ros2", "robot.rehearsal=true", "robot.time_scale=4.0",
                      "robot.num_runs=2", "exploration.num_steps=60", "robot.watchdog_s=1.0",
                      "robot.stop_timeout_s=2.0", "robot.startup_timeout_s=60",
                      "robot.twin.seed=5", "robot.twin.physics.chamber_gains=[0.85,1.15,1.0]"]
    record = tmp_path / "twin_received.jsonl"
    twin = pipe.start("twin", f"robot.twin.record_path={record}", "robot.twin.max_duration_s=900")
    try:
        assert pipe.start("collect").wait(timeout=300) == 0, pipe.log("collect")
        assert pipe.start("train_ppo").wait(timeout=400) == 0, pipe.log("train_ppo")
        collected = len(received(record))
        assert pipe.start("improve").wait(timeout=600) == 0, pipe.log("improve")
    finally:
        assert stop(twin) == 0, pipe.log("twin")
    sent = received(record)[CMD_COLUMNS].to_numpy()[collected:]
    assert len(sent) >= 20  # 2 goals of 5 s at 2 Hz, then the preload
    np.testing.assert_allclose(sent[-1], [2.0, 2.0, 2.0])
    assert np.isfinite(sent).all() and sent.max() <= 7.0 and sent.sum(axis=1).max() <= 13.0
    store = ArtifactStore(pipe.out / "artifacts")
    (last,) = [p for p in (store.root / "improve").iterdir()
               if (p / "rounds.parquet").is_file() and json.loads(
                   (p / "artifact.json").read_text())["spec"]["round"] == 1]
    table = pd.read_parquet(last / "rounds.parquet")
    assert table["round"].tolist() == [0, 1] and table["drive_goals"].iloc[1] == 2
    assert np.isfinite(table["model_after_mean_mm"].iloc[1])


@pytest.mark.slow
def test_a_round_explores_where_the_ensemble_disagrees(tmp_path):
    """Half the round's arm time on the walk its two models disagree on most: an explore
    artifact of the chosen walk, joined to the refit's data beside the goals' session."""
    overrides = [*SMALL, "env.ensemble_seeds=2", "improve.arm_s=20",
                 "improve.explore_share=0.5", "improve.explore_walk_s=10",
                 "improve.explore_candidates=4"]
    for job in chain.plan(compose_config(tmp_path, *overrides, "stage=train_ppo"),
                          lambda variant: keys.key("train_ppo", variant)):
        chain.stage_function(job.stage)(job.cfg)
    artifact = improve(compose_config(tmp_path, *overrides, "stage=improve"))
    store = ArtifactStore(tmp_path / "artifacts")
    (walk,) = [p for p in (store.root / "explore").iterdir() if (p / "artifact.json").is_file()]
    summary = json.loads((walk / "artifact.json").read_text())["summary"]
    # the chosen walk is the most disputed of the candidates
    assert summary["disagreement_mm2"] >= summary["median_candidate_mm2"] > 0
    session = read_session(walk)
    assert session.provenance["stage"] == "explore" and len(session.targets) == 0
    assert 9.0 <= float(session.mocap["t"].iloc[-1] - session.mocap["t"].iloc[0]) <= 10.5
    row = pd.read_parquet(artifact.file("rounds.parquet")).iloc[-1]
    assert row["sessions"] == 2 and row["drive_goals"] == 2 and 19.0 <= row["arm_s"] <= 21.0
