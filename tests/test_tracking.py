"""wandb tracking is off by default and offline when enabled."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from pipeline.infra.tracking import Tracker, tracking
from pipeline.schemas import LoggerConfig


def test_tracking_is_a_no_op_by_default(tmp_path):
    with tracking(LoggerConfig(), tmp_path, "fit_model", {}) as tracker:
        assert type(tracker) is Tracker
        tracker.log_table(pd.DataFrame({"step": [1, 2], "loss": [0.5, float("nan")]}))
    assert not any(tmp_path.iterdir())  # nothing written


def test_wandb_runs_offline_into_the_output_folder(make_cfg, monkeypatch):
    pytest.importorskip("wandb")
    from omegaconf import OmegaConf

    monkeypatch.setenv("WANDB_SILENT", "true")
    cfg = make_cfg("logger=wandb")
    logger = OmegaConf.to_object(cfg.logger)
    assert logger.wandb and logger.mode == "offline"
    output = Path(cfg.paths.output_dir)
    with tracking(logger, output, "fit_model", OmegaConf.to_container(cfg, resolve=True)
                  ) as tracker:
        tracker.log_table(pd.DataFrame({"step": [1, 2], "loss": [0.5, 0.25]}))
    runs = list((output / "wandb").glob("offline-run-*"))
    assert len(runs) == 1
