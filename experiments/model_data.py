"""Private loader for the model experiments: the authors' aligned CSVs, resampled to the model rate.

Not part of the pipeline (the pipeline has its own resampler); it only feeds
``experiments/model_*.py``. Each run becomes the dict the model code takes::

    {"run_id": str, "t": float64 [T] s, "p": float32 [T, 3] kPa, "pos": float32 [T, 3] m}

on the regular grid ``t_k = t_0 + k / model_hz``. The pressure is a held command, so it is sampled
by zero-order hold (the last command at or before ``t_k``); the position is linearly interpolated
between the two mocap frames around ``t_k``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

POSITION_COLUMNS = ["1_x", "1_y", "1_z"]
PRESSURE_COLUMNS = ["control_pressure_0", "control_pressure_1", "control_pressure_2"]


def resample_run(frame: pd.DataFrame, run_id: str, model_hz: float) -> dict:
    time = frame["time"].to_numpy(np.float64)
    pressure = frame[PRESSURE_COLUMNS].to_numpy(np.float64)
    position = frame[POSITION_COLUMNS].to_numpy(np.float64)
    num_steps = int(np.floor((time[-1] - time[0]) * model_hz)) + 1
    grid = time[0] + np.arange(num_steps) / model_hz
    # Zero-order hold: index of the last row whose time is <= the grid time.
    held_index = np.clip(np.searchsorted(time, grid, side="right") - 1, 0, len(time) - 1)
    interpolated = np.stack([np.interp(grid, time, position[:, j]) for j in range(3)], axis=1)
    return {
        "run_id": run_id,
        "t": grid - grid[0],
        "p": pressure[held_index].astype(np.float32),
        "pos": interpolated.astype(np.float32),
    }


def load_runs(data_dir: str | Path, model_hz: float, pattern: str = "Step_control_*.csv") -> list:
    """All runs in ``data_dir``, sorted by file name, resampled to ``model_hz``."""
    paths = sorted(Path(data_dir).glob(pattern))
    if not paths:
        raise FileNotFoundError(f"no files matching {pattern!r} in {data_dir}")
    return [resample_run(pd.read_csv(path), path.stem, model_hz) for path in paths]
