"""The fit_model stage: what it logs without a test run, and force=true training afresh."""

from __future__ import annotations

import logging

import pandas as pd
import pytest

from pipeline.__main__ import run
from pipeline.infra.artifacts import ArtifactStore
from pipeline.keys import key

TINY = ["robot.num_runs=2", "exploration.num_steps=20", "exploration.pad_steps=2",
        "dataset.window=8", "model.hidden=8", "model.num_steps=4", "model.eval_every=2",
        "model.checkpoint_every=2", "model.batch_size=4", "stage=fit_model"]


def test_without_a_test_run_the_training_error_is_not_called_held_out(make_cfg, caplog):
    cfg = make_cfg(*TINY, "dataset.train_fraction=1.0")
    with caplog.at_level(logging.INFO, logger="pipeline"):
        artifact = run(cfg)["fit_model"]
    assert artifact.manifest["summary"]["test_runs"] == []
    assert artifact.manifest["summary"]["error_on"] == "train"
    assert ("fit_model: training-run (no test run: dataset.train_fraction keeps every run) "
            "open-loop error") in caplog.text
    assert "held-out" not in caplog.text


def test_force_trains_afresh_instead_of_resuming_old_checkpoints(make_cfg, caplog):
    cfg = make_cfg(*TINY, "force=true")
    work = ArtifactStore(cfg.paths.artifact_dir).root / "fit_model" / f".work-{key('fit_model', cfg)}"
    work.mkdir(parents=True)
    stale = work / "step_00000099.msgpack"  # not even a checkpoint: resuming it would fail
    stale.write_bytes(b"not a checkpoint")
    with caplog.at_level(logging.INFO):
        artifact = run(cfg)["fit_model"]
    losses = pd.read_parquet(artifact.file("losses.parquet"))
    assert list(losses["step"]) == [1, 2, 3, 4]
    assert "force=true: training afresh" in caplog.text
    assert "cannot be read" not in caplog.text and not work.exists()


@pytest.mark.parametrize("robot", ["sorolex_csv", "plotjuggler_csv", "rosbag", "ros2"])
def test_experiment_quick_composes_on_every_robot(make_cfg, robot):
    cfg = make_cfg("experiment=quick", f"robot={robot}")
    assert cfg.robot.num_runs == 3


def test_quick_on_the_real_runs_reads_three_of_them(make_cfg, sorolex_dir):
    from pipeline.data.importers import list_recordings

    cfg = make_cfg("experiment=quick", "robot=sorolex_csv", f"robot.data_dir={sorolex_dir}")
    assert len(list_recordings(cfg.robot)) == 3
