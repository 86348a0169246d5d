"""End to end: the entry point runs collect -> align on the simulated arm and reuses artifacts."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.__main__ import run
from pipeline.chain import stages_to_run
from pipeline.config import PROJECT_ROOT
from pipeline.data.schemas import ALIGNED, COMMANDS, MOCAP, RUNS, DataError, read_table, write_table
from pipeline.infra.artifacts import ArtifactStore
from pipeline.keys import key
from pipeline.schemas import Stage


def pipeline_cmd(output_dir, *overrides):
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    flags = [o for o in overrides if o.startswith("-")]  # e.g. -m, before the overrides
    overrides = [o for o in overrides if not o.startswith("-")]
    return subprocess.run(
        [sys.executable, "-m", "pipeline", *flags, f"paths.output_dir={output_dir}", *overrides],
        cwd=PROJECT_ROOT, env=env, capture_output=True, text=True, timeout=300)


# three pipeline processes; fast: the same stages in process (test_align.py, below)
@pytest.mark.slow
def test_quick_collect_then_align_on_the_simulated_arm(tmp_path):
    out = tmp_path / "outputs"
    first = pipeline_cmd(out, "experiment=quick", "stage=collect")
    assert first.returncode == 0, first.stderr
    second = pipeline_cmd(out, "experiment=quick", "stage=align", "dataset.align.resample_hz=10")
    assert second.returncode == 0, second.stderr
    again = pipeline_cmd(out, "experiment=quick", "stage=collect")
    assert "reusing artifact" in again.stdout + again.stderr

    store = ArtifactStore(out / "artifacts")
    raw = next((out / "artifacts" / "collect").glob("[!.]*"))
    commands, _ = read_table(raw / "commands.parquet", COMMANDS)
    mocap, _ = read_table(raw / "mocap.parquet", MOCAP)
    assert commands["run_id"].nunique() == 3
    # 2 Hz commands, ~100 Hz frames, a few dropped
    assert np.median(np.diff(commands["t"][commands["run_id"] == "sim-000"])) == 0.5
    assert np.median(np.diff(mocap["t"][mocap["run_id"] == "sim-000"])) == pytest.approx(0.01,
                                                                                       abs=1e-3)
    assert 0 < (~mocap["valid"]).mean() < 0.05
    assert (raw / "figures" / "exploration_alphas.png").stat().st_size > 10_000
    assert (raw / "figures" / "runs.png").stat().st_size > 10_000

    aligned_dir = next((out / "artifacts" / "align").glob("[!.]*"))
    aligned, meta = read_table(aligned_dir / "aligned.parquet", ALIGNED)
    assert np.allclose(np.diff(aligned["t"][aligned["run_id"] == "sim-000"]), 0.1)
    assert meta["config"]["dataset.align"]["resample_hz"] == 10.0
    assert meta["provenance"]["inputs"]["collect"] == raw.name
    assert json.loads(pq.read_schema(aligned_dir / "aligned.parquet")
                      .metadata[b"sorolearn"])["units"]["x"] == "m"
    manifest = json.loads((aligned_dir / "artifact.json").read_text())
    assert manifest["summary"]["matched"] == len(commands)
    assert store.find("align", aligned_dir.name) is not None


def test_run_in_process_finds_inputs_from_the_config_alone(make_cfg):
    cfg = make_cfg("experiment=quick", "robot.num_runs=2", "exploration.num_steps=10",
                   "stage=collect")
    run(cfg)
    cfg.stage = "align"
    results = run(cfg)
    assert results["align"].key == key("align", cfg)
    assert results["align"].manifest["inputs"] == {"collect": key("collect", cfg)}


def test_a_stage_produces_what_it_needs_upstream_and_reuses_it(make_cfg):
    cfg = make_cfg("experiment=quick", "robot.num_runs=2", "exploration.num_steps=10",
                   "stage=align", "force=true")
    results = run(cfg)
    assert list(results) == ["collect", "align"]
    assert results["align"].manifest["inputs"] == {"collect": key("collect", cfg)}

    def written(artifact):  # a rewritten artifact is a new folder renamed into place
        return artifact.file("artifact.json").stat().st_ino

    before = {name: written(artifact) for name, artifact in results.items()}
    again = run(cfg)  # force=true recomputes the requested stage only
    assert written(again["collect"]) == before["collect"]
    assert written(again["align"]) != before["align"]


def test_stages_to_run_never_drives_a_real_arm_implicitly(make_cfg):
    assert stages_to_run(make_cfg("stage=fit_model")) == [Stage.collect, Stage.align,
                                                          Stage.fit_model]
    assert stages_to_run(make_cfg("stage=align", "robot=ros2")) == [Stage.align]
    assert stages_to_run(make_cfg("stage=collect", "robot=ros2")) == [Stage.collect]
    assert stages_to_run(make_cfg("stage=train_ppo", "env=gymnax")) == [Stage.train_ppo]
    assert stages_to_run(make_cfg("stage=twin")) == [Stage.twin]


def test_align_on_a_real_arm_before_collect_says_which_stage_to_run(make_cfg):
    cfg = make_cfg("stage=align", "robot=ros2")
    with pytest.raises(FileNotFoundError, match="stage=collect"):
        run(cfg)


def test_real_runs_import_and_align(make_cfg, sorolex_dir):
    cfg = make_cfg("robot=sorolex_csv", f"robot.data_dir={sorolex_dir}",
                   "robot.files=[Step_control_17_10_12_20.csv,Step_control_17_10_12_29.csv]",
                   "stage=collect")
    run(cfg)
    cfg.stage = "align"
    aligned = run(cfg)["align"]
    frame, _ = read_table(aligned.file("aligned.parquet"), ALIGNED)
    assert sorted(frame["run_id"].unique()) == ["Step_control_17_10_12_20",
                                                "Step_control_17_10_12_29"]
    assert aligned.manifest["summary"]["unmatched"] == 0


def test_align_refuses_interrupted_runs_unless_told(make_cfg):
    cfg = make_cfg("experiment=quick", "robot.num_runs=2", "exploration.num_steps=10",
                   "stage=collect")
    raw = run(cfg)["collect"]
    runs_path = raw.file("runs.parquet")
    runs, meta = read_table(runs_path, RUNS)
    runs.loc[1, "complete"] = False  # as an interrupted collection marks its last run
    write_table(runs, runs_path, RUNS, meta["config"], meta["provenance"])
    cfg.stage = "align"
    with pytest.raises(DataError, match=r"\['sim-001'\] were interrupted"):
        run(cfg)
    cfg.dataset.align.accept_incomplete = True
    assert run(cfg)["align"].manifest["summary"]["runs"] == 2


@pytest.mark.slow  # a multirun of two processes; fast: the launchers compose (test_sweeps.py)
def test_multirun_sweeps_exploration_and_shares_nothing_it_should_not(tmp_path):
    out = tmp_path / "outputs"
    result = pipeline_cmd(out, "-m", "stage=collect", "experiment=quick", "robot.num_runs=1",
                          "exploration.num_steps=10", "exploration.alpha=0.3,0.6")
    assert result.returncode == 0, result.stderr
    assert len(list((out / "artifacts" / "collect").glob("[!.]*"))) == 2
    assert len(list((out / "multirun").rglob("multirun.yaml"))) == 1


@pytest.fixture
def stage_calls(monkeypatch):
    """(stage, agent) of every stage function the router calls; each returns "stage:agent"."""
    import pipeline.__main__ as entry

    calls = []

    def recorder(name):
        def stage_fn(cfg):
            calls.append((name.value, cfg.agent.name))
            return f"{name.value}:{cfg.agent.name}"
        return stage_fn

    monkeypatch.setattr(entry, "stage_function", recorder)
    return calls


@pytest.mark.parametrize("stage", ["evaluate", "all"])
def test_evaluate_trains_every_policy_type_it_compares_upstream(make_cfg, stage_calls, stage):
    cfg = make_cfg(f"stage={stage}", "agent=ppo_ff", "evaluation.policies=[ppo_ff,ppo_rnn]")
    results = run(cfg)
    trained = sorted(agent for name, agent in stage_calls if name == "train_ppo")
    assert trained == ["ppo_ff", "ppo_rnn"]
    assert results["train_ppo"] == "train_ppo:ppo_ff"  # the config's own agent
    assert stage_calls[-1][0] == "evaluate"


def test_train_ppo_alone_trains_only_its_own_agent(make_cfg, stage_calls):
    run(make_cfg("stage=train_ppo", "agent=ppo_rnn", "evaluation.policies=[ppo_ff,ppo_rnn]"))
    assert [agent for name, agent in stage_calls if name == "train_ppo"] == ["ppo_rnn"]
