"""Alignment: put the 2 Hz pressure commands onto the ~100 Hz motion-capture rows.

Per run:

1. **Dropped frames** (``valid = False``) inside a gap no longer than ``max_gap_s`` (measured
   between the valid frames around it) get their position by linear interpolation in time
   (counted as ``interpolated``). Longer gaps abort with the run and time (``gap_policy=error``)
   or split the run there into ``<run>#0``, ``<run>#1``, ... (``gap_policy=split``); frames with
   no valid neighbour on one side (start or end of a run) are dropped.
2. **Matching.** Every command is matched to the mocap frame nearest in time. Commands farther
   than ``max_match_dt_s`` from every frame are ``unmatched``; when two commands match the same
   frame the later one wins (``overridden``).
3. **Forward fill.** Each frame carries the last command matched at or before it (the valve holds
   its pressure until the next step); ``matched`` marks the frame a command was matched to. Frames
   before the first matched command are dropped (``before_first_command``).
4. **Resampling** (``resample_hz``): a regular grid from the first aligned frame, positions
   linearly interpolated, pressures zero-order held, ``matched`` where a command took effect since
   the previous grid point.

The per-run counts are written as ``align_report.parquet`` and logged.
"""

from __future__ import annotations

import itertools
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.data.runs import Run
from pipeline.data.schemas import (
    ALIGNED,
    CMD_COLUMNS,
    P_COLUMNS,
    XYZ,
    DataError,
    read_table,
)
from pipeline.schemas import GapPolicy

log = logging.getLogger(__name__)
COUNT_FIELDS = (
    "commands", "matched", "unmatched", "overridden", "frames", "dropped_frames", "interpolated",
    "gaps", "before_first_command", "filled", "rows",
)


def align_run(commands: pd.DataFrame, mocap: pd.DataFrame, settings: Any,
              source: str = "align") -> tuple[pd.DataFrame, list[dict[str, Any]]]:
    """Align one run's ``commands`` and ``mocap`` (raw schemas) into ``aligned`` rows.

    Returns the aligned rows (one or more runs if split at gaps) and one count dict per output run.
    """
    run_id = str(mocap["run_id"].iloc[0])
    t = mocap["t"].to_numpy(np.float64)
    xyz = mocap[XYZ].to_numpy(np.float64)
    valid = mocap["valid"].to_numpy(bool)
    dropped = int((~valid).sum())
    if not valid.any():
        raise DataError(source, f"run {run_id!r} has no valid mocap frame", "valid")

    # ---- gaps: interpolate short ones, split or fail on long ones ------------------------------
    valid_idx = np.flatnonzero(valid)
    gap_after = np.diff(t[valid_idx]) > float(settings.max_gap_s)
    segments = np.split(valid_idx, np.flatnonzero(gap_after) + 1)
    if len(segments) > 1 and GapPolicy(settings.gap_policy) is GapPolicy.error:
        first = int(np.flatnonzero(gap_after)[0])
        t0, t1 = t[valid_idx[first]], t[valid_idx[first + 1]]
        raise DataError(
            source, f"run {run_id!r}: no valid mocap frame for {t1 - t0:.3f} s after t={t0:.3f} s "
            f"(max_gap_s={settings.max_gap_s}; set dataset.align.gap_policy=split to split the run "
            f"there)", "t", int(valid_idx[first]))

    out_rows, reports = [], []
    for number, segment in enumerate(segments):
        frames = np.arange(segment[0], segment[-1] + 1)  # valid ends, dropped frames inside
        inside = ~valid[frames]
        seg_xyz = xyz[frames].copy()
        if inside.any():
            for axis in range(3):
                seg_xyz[inside, axis] = np.interp(t[frames][inside], t[segment], xyz[segment, axis])
        seg_id = run_id if len(segments) == 1 else f"{run_id}#{number}"
        seg_t = t[frames]
        seg_cmd = commands[(commands["t"] >= seg_t[0] - settings.max_match_dt_s)
                           & (commands["t"] <= seg_t[-1] + settings.max_match_dt_s)]
        if len(segments) > 1:
            seg_cmd = _commands_in_force(commands, seg_t[0], seg_cmd)
        rows, counts = _match_and_fill(seg_id, seg_t, seg_xyz, seg_cmd, settings)
        counts.update(interpolated=int(inside.sum()), gaps=len(segments) - 1,
                      dropped_frames=dropped if number == 0 else 0)
        if len(segments) == 1:
            counts["commands"] = len(commands)
            counts["unmatched"] = len(commands) - counts["matched"] - counts["overridden"]
        out_rows.append(rows)
        reports.append(counts)
    return pd.concat(out_rows, ignore_index=True), reports


def _commands_in_force(commands: pd.DataFrame, t_start: float, inside: pd.DataFrame
                       ) -> pd.DataFrame:
    """For a segment after a split: the command sent before the segment is still in force."""
    before = commands[commands["t"] < t_start]
    if len(before) == 0 or (len(inside) and inside["t"].iloc[0] <= t_start):
        return inside
    carried = before.iloc[[-1]].copy()
    carried["t"] = t_start
    return pd.concat([carried, inside], ignore_index=True)


def _match_and_fill(run_id: str, t: np.ndarray, xyz: np.ndarray, commands: pd.DataFrame,
                    settings: Any) -> tuple[pd.DataFrame, dict[str, int]]:
    tc = commands["t"].to_numpy(np.float64)
    pc = commands[CMD_COLUMNS].to_numpy(np.float64)
    # nearest frame: compare the neighbours on both sides of each command time
    right = np.clip(np.searchsorted(t, tc), 0, len(t) - 1)
    left = np.clip(right - 1, 0, len(t) - 1)
    nearest = np.where(np.abs(t[left] - tc) <= np.abs(t[right] - tc), left, right)
    ok = np.abs(t[nearest] - tc) <= float(settings.max_match_dt_s)
    frame_of = nearest[ok]
    # later commands overwrite earlier ones on the same frame (numpy keeps the last assignment)
    command_at = np.full(len(t), -1)
    command_at[frame_of] = np.flatnonzero(ok)
    matched = command_at >= 0
    counts = {"commands": len(tc), "matched": int(matched.sum()),
              "overridden": int(ok.sum() - matched.sum()), "unmatched": int((~ok).sum()),
              "frames": len(t)}
    if not matched.any():
        raise DataError("align", f"run {run_id!r}: no pressure command within "
                        f"{settings.max_match_dt_s} s of any mocap frame", "t")
    # forward fill the index of the last matched command
    last = np.maximum.accumulate(np.where(matched, np.arange(len(t)), -1))
    keep = last >= 0
    pressures = pc[command_at[last[keep]]]
    rows = pd.DataFrame({"run_id": run_id, "t": t[keep]})
    for j, column in enumerate(P_COLUMNS):
        rows[column] = pressures[:, j]
    for axis, column in enumerate(XYZ):
        rows[column] = xyz[keep, axis]
    rows["matched"] = matched[keep]
    counts.update(before_first_command=int((~keep).sum()), rows=int(keep.sum()),
                  filled=int(keep.sum() - matched.sum()))
    return rows, counts


def _rows_on_grid(run_id: str, run: pd.DataFrame, grid: np.ndarray
                  ) -> tuple[pd.DataFrame, np.ndarray]:
    """A run's rows at ``grid`` times: pressures held, positions linearly interpolated.

    Returns the rows (without ``matched``) and, per grid point, the index of the row held there.
    """
    t = run["t"].to_numpy(np.float64)
    held = np.searchsorted(t, grid + 1e-12, side="right") - 1
    rows = pd.DataFrame({"run_id": run_id, "t": grid})
    for column in P_COLUMNS:
        rows[column] = run[column].to_numpy()[held]
    for column in XYZ:
        rows[column] = np.interp(grid, t, run[column].to_numpy())
    return rows, held


def resample(aligned: pd.DataFrame, hz: float) -> pd.DataFrame:
    """Resample aligned runs onto a regular ``hz`` grid (positions linear, pressures held)."""
    out = []
    for run_id, run in aligned.groupby("run_id", sort=False):
        t = run["t"].to_numpy(np.float64)
        grid = t[0] + np.arange(int(np.floor((t[-1] - t[0]) * hz + 1e-9)) + 1) / hz
        rows, held = _rows_on_grid(run_id, run, grid)
        matched_count = np.cumsum(run["matched"].to_numpy())[held]
        rows["matched"] = np.diff(np.r_[0, matched_count]) > 0
        out.append(rows)
    return pd.concat(out, ignore_index=True)


def resample_command_locked(aligned: pd.DataFrame, hz: float) -> pd.DataFrame:
    """Resample onto a grid locked to the commands: each interval between two matched commands
    is cut into ``round(duration * hz)`` equal steps starting at the command.

    Every command then takes effect exactly on a grid point, as an action does in the learned
    environment (held for a whole number of model steps), instead of at a phase that drifts
    with the clock. Positions are interpolated, pressures held, ``matched`` on command points.
    """
    out = []
    for run_id, run in aligned.groupby("run_id", sort=False):
        t = run["t"].to_numpy(np.float64)
        matched = run["matched"].to_numpy(bool)
        bounds = np.r_[t[matched], t[-1]]
        pieces = []
        for start, end in itertools.pairwise(bounds):
            steps = max(1, round((end - start) * hz))
            pieces.append(start + (end - start) * np.arange(steps) / steps)
        grid = np.concatenate(pieces) if pieces else t[:1]
        rows, _ = _rows_on_grid(run_id, run, grid)
        rows["matched"] = np.isin(grid, t[matched])
        out.append(rows)
    return pd.concat(out, ignore_index=True)


def align_tables(commands: pd.DataFrame, mocap: pd.DataFrame, settings: Any,
                 source: str = "align") -> tuple[pd.DataFrame, pd.DataFrame]:
    """Align every run; return the ``aligned`` table and the per-run report."""
    rows, reports = [], []
    for run_id, run_mocap in mocap.groupby("run_id", sort=False):
        run_commands = commands[commands["run_id"] == run_id]
        if len(run_commands) == 0:
            raise DataError(source, f"run {run_id!r} has mocap frames but no commands", "run_id")
        aligned, counts = align_run(run_commands, run_mocap, settings, source)
        rows.append(aligned)
        for counts_i, seg in zip(counts, aligned["run_id"].unique()):
            reports.append({"run_id": seg, **{k: counts_i.get(k, 0) for k in COUNT_FIELDS}})
    aligned = pd.concat(rows, ignore_index=True)
    if settings.resample_hz:
        aligned = resample(aligned, float(settings.resample_hz))
    return aligned, pd.DataFrame(reports)


def runs_at_model_rate(aligned: pd.DataFrame, model_hz: float, grid: str = "clock"
                       ) -> list[Run]:
    """Aligned rows as the model's runs (:class:`~pipeline.data.runs.Run`), sorted by run id.

    ``grid``: ``clock`` (a regular grid) or ``commands`` (locked to the command times, see
    :func:`resample_command_locked`).
    """
    if grid == "clock":
        resampled = resample(aligned, model_hz)
    elif grid == "commands":
        resampled = resample_command_locked(aligned, model_hz)
    else:
        raise ValueError(f"dataset.model_grid must be clock or commands, got {grid!r}")
    return [
        Run(run_id=str(run_id), times_s=run["t"].to_numpy(np.float64),
            pressures_kpa=run[P_COLUMNS].to_numpy(np.float32),
            positions_m=run[XYZ].to_numpy(np.float32))
        for run_id, run in resampled.groupby("run_id", sort=True)
    ]


def load_runs(aligned_path: str | Path, rate_hz: float, grid: str = "clock") -> list[Run]:
    """The runs of an aligned table file (an align artifact's ``aligned.parquet``) at ``rate_hz``
    on ``grid`` (:func:`runs_at_model_rate`): how fit_model and the studies read recorded runs."""
    aligned, _ = read_table(aligned_path, ALIGNED)
    return runs_at_model_rate(aligned, rate_hz, grid)
