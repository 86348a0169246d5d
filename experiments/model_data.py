"""Private loader for the model experiments: the authors' aligned CSVs, resampled to the model rate.

Not part of the pipeline (the pipeline has its own resampler); it only feeds
``experiments/model_*.py``. Each run becomes the dict the model code takes::

    {"run_id": str, "t": float64 [T] s, "p": float32 [T, 3] kPa, "pos": float32 [T, 3] m}

on the regular grid ``t_k = t_0 + k / model_hz``. The position is linearly interpolated between the
two mocap frames around ``t_k``. The pressure is a held command; two ways to put it on the grid:

* ``"sample"``: zero-order hold, the last command at or before ``t_k``;
* ``"interval_mean"``: the time average of the held command over ``(t_k - 1/model_hz, t_k]``,
  i.e. what acted on the arm during the model step that ends at ``t_k``. When commands change
  on the grid (as in a learned environment stepping the model) both agree; on recorded data the
  mean also tells the model how late in the step a command changed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

POSITION_COLUMNS = ["1_x", "1_y", "1_z"]
PRESSURE_COLUMNS = ["control_pressure_0", "control_pressure_1", "control_pressure_2"]


def _held_integral(time: np.ndarray, values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Integral from time[0] to ``at`` of the piecewise-constant signal ``values`` (held)."""
    cumulative = np.concatenate([np.zeros((1, values.shape[1])),
                                 np.cumsum(values[:-1] * np.diff(time)[:, None], axis=0)])
    index = np.clip(np.searchsorted(time, at, side="right") - 1, 0, len(time) - 1)
    return cumulative[index] + values[index] * (at - time[index])[:, None]


def resample_run(
    frame: pd.DataFrame, run_id: str, model_hz: float, pressure_mode: str = "interval_mean"
) -> dict:
    time = frame["time"].to_numpy(np.float64)
    pressure = frame[PRESSURE_COLUMNS].to_numpy(np.float64)
    position = frame[POSITION_COLUMNS].to_numpy(np.float64)
    num_steps = int(np.floor((time[-1] - time[0]) * model_hz)) + 1
    grid = time[0] + np.arange(num_steps) / model_hz
    # Zero-order hold: index of the last row whose time is <= the grid time.
    held_index = np.clip(np.searchsorted(time, grid, side="right") - 1, 0, len(time) - 1)
    interpolated = np.stack([np.interp(grid, time, position[:, j]) for j in range(3)], axis=1)
    if pressure_mode == "sample":
        grid_pressure = pressure[held_index]
    elif pressure_mode == "interval_mean":
        step_s = 1.0 / model_hz
        start = np.maximum(grid - step_s, time[0])
        span = np.maximum(grid - start, 1e-12)
        grid_pressure = (_held_integral(time, pressure, grid)
                         - _held_integral(time, pressure, start)) / span[:, None]
        grid_pressure[0] = pressure[0]
    else:
        raise ValueError(f"unknown pressure_mode {pressure_mode!r}")
    return {
        "run_id": run_id,
        "t": grid - grid[0],
        "p": grid_pressure.astype(np.float32),
        "pos": interpolated.astype(np.float32),
    }


def load_runs(
    data_dir: str | Path,
    model_hz: float,
    pressure_mode: str = "interval_mean",
    pattern: str = "Step_control_*.csv",
) -> list:
    """All runs in ``data_dir``, sorted by file name, resampled to ``model_hz``."""
    paths = sorted(Path(data_dir).glob(pattern))
    if not paths:
        raise FileNotFoundError(f"no files matching {pattern!r} in {data_dir}")
    return [resample_run(pd.read_csv(path), path.stem, model_hz, pressure_mode) for path in paths]
