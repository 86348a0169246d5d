"""Experiment tracking: Weights & Biases when ``logger.wandb=true``, otherwise nothing.

wandb runs offline (``logger.mode=offline``, the default) and writes under the output folder the
stage gives (``paths.output_dir``); ``wandb sync`` uploads such a run later. Nothing here touches
the network unless the user sets ``logger.mode=online``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.schemas import LoggerConfig


class Tracker:
    """Logs nothing; the interface the wandb tracker shares."""

    def log(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        return None

    def log_table(self, frame: pd.DataFrame, step_column: str = "step") -> None:
        """Log every row of ``frame`` as one step (NaN cells left out)."""
        for row in frame.to_dict("records"):
            step = int(row.pop(step_column)) if step_column in row else None
            self.log({k: v for k, v in row.items() if pd.notna(v)}, step=step)


class WandbTracker(Tracker):
    def __init__(self, run: Any, prefix: str):
        self.run, self.prefix = run, prefix

    def log(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        self.run.log({f"{self.prefix}/{k}": v for k, v in metrics.items()}, step=step)


@contextlib.contextmanager
def tracking(logger: LoggerConfig, output_dir: Path, stage: str,
             run_config: Mapping[str, Any]) -> Iterator[Tracker]:
    """A tracker for one stage run; a wandb run (offline by default, under ``output_dir``) if
    ``logger`` asks for it, recording ``run_config`` (the run's whole config, resolved, as plain
    containers)."""
    if not logger.wandb:
        yield Tracker()
        return
    try:
        import wandb
    except ImportError as err:
        raise ImportError("logger.wandb=true needs wandb: pip install -e '.[wandb]'") from err
    directory = Path(output_dir)
    directory.mkdir(parents=True, exist_ok=True)
    run = wandb.init(project=logger.project, mode=logger.mode, dir=str(directory),
                     job_type=stage, config=dict(run_config), reinit="finish_previous")
    try:
        yield WandbTracker(run, stage)
    finally:
        run.finish()
