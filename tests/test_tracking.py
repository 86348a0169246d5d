"""wandb tracking is off by default and offline when enabled."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from pipeline.infra.tracking import Tracker, tracking


def test_tracking_is_a_no_op_by_default(make_cfg):
    with tracking(make_cfg(), "fit_model") as tracker:
        assert type(tracker) is Tracker
        tracker.log_table(pd.DataFrame({"step": [1, 2], "loss": [0.5, float("nan")]}))


def test_wandb_runs_offline_into_the_output_folder(make_cfg, monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_SILENT", "true")
    cfg = make_cfg("logger=wandb")
    assert cfg.logger.mode == "offline"
    with tracking(cfg, "fit_model") as tracker:
        tracker.log_table(pd.DataFrame({"step": [1, 2], "loss": [0.5, 0.25]}))
    runs = list((Path(cfg.paths.output_dir) / "wandb").glob("offline-run-*"))
    assert len(runs) == 1
