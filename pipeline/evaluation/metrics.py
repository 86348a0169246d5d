"""Closed-loop metrics of goal-reaching episodes (pure numpy, one row per episode).

Trajectory conventions (E episodes, T control steps):

- ``positions [E, T + 1, 3]`` m: row 0 is the pose at the start (after the reset), row t + 1 the
  pose at the end of control period t;
- ``goals [E, 3]`` m, or ``[E, T + 1, 3]`` when the goal changes within an episode
  (consecutive goals): each row's goal is the one in force at that time;
- ``commands [E, T, 3]`` kPa: the pressures sent in each control period.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

MM_PER_M = 1000.0
ARRIVAL_MM = 1.0  # an episode has arrived once its distance was within this
HELD_MM = 1.5  # an arrival is held when the episode ends within this
# the cross-model protocol's plants: the policies' own model and the other group's
OWN, CROSS = "own", "cross"


def distances_mm(positions: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """Distance to the goal ``[E, T + 1]`` in mm at every recorded time."""
    positions = np.asarray(positions, np.float64)
    goals = np.asarray(goals, np.float64)
    if positions.ndim != 3 or positions.shape[-1] != 3:
        raise ValueError(f"positions must be [E, T + 1, 3], got {positions.shape}")
    if goals.ndim == 2:
        goals = goals[:, None, :]
    return np.linalg.norm(positions - goals, axis=-1) * MM_PER_M


def first_step_within(distance_mm: np.ndarray, tolerance_mm: float) -> np.ndarray:
    """Control steps until the distance first falls within the tolerance (NaN if never).

    Index t of ``distance_mm [E, T + 1]`` is reached after t control steps.
    """
    within = distance_mm <= tolerance_mm
    steps = np.argmax(within, axis=1).astype(np.float64)
    steps[~within.any(axis=1)] = np.nan
    return steps


def hold_metrics(distance_mm: np.ndarray, arrival_mm: float = ARRIVAL_MM,
                 held_mm: float = HELD_MM) -> dict[str, np.ndarray]:
    """What happens after the first arrival within ``arrival_mm``, per episode ``[E]``.

    From ``distance_mm [E, T + 1]`` (index t after t control periods), over the times from the
    first arrival ``a`` to the end ``T`` (both included; NaN for an episode that never arrived):

    - ``within_1mm_after_arrival``: the share of those ``T - a + 1`` times within ``arrival_mm``
      (1: never left again; the arrival itself counts, so it is at least ``1 / (T - a + 1)``);
    - ``max_after_arrival_mm``: the largest distance among them;
    - ``held_1.5mm``: 1.0 when the episode ends within ``held_mm``, else 0.0 (an arrival held to
      the end; the share of arrivals held is its mean over the episodes that arrived).
    """
    distance = np.asarray(distance_mm, np.float64)
    first = first_step_within(distance, arrival_mm)
    arrived = np.isfinite(first)
    times = np.arange(distance.shape[1])[None, :]
    after = arrived[:, None] & (times >= np.where(arrived, first, np.inf)[:, None])
    count = after.sum(axis=1)
    within = ((distance <= arrival_mm) & after).sum(axis=1)
    largest = np.where(after, distance, -np.inf).max(axis=1)
    nan = np.full(len(distance), np.nan)
    return {
        f"within_{arrival_mm:g}mm_after_arrival": np.where(
            arrived, within / np.maximum(count, 1), nan),
        "max_after_arrival_mm": np.where(arrived, largest, nan),
        f"held_{held_mm:g}mm": np.where(arrived, (distance[:, -1] <= held_mm).astype(float),
                                        nan),
    }


def steps_above_limits(commands: np.ndarray, limits: Any) -> np.ndarray:
    """Control steps whose command lies outside the safe set, per episode ``[E]`` (exact)."""
    p = np.asarray(commands, np.float64)
    outside = ((p < limits.p_min) | (p > limits.p_max)).any(axis=-1)
    outside |= p.sum(axis=-1) > limits.sum_max
    return outside.sum(axis=-1)


def episode_metrics(
    positions: np.ndarray,
    goals: np.ndarray,
    commands: np.ndarray,
    limits: Any,
    tolerances_mm: tuple[float, float] = (1.0, 3.0),
) -> pd.DataFrame:
    """One row per episode.

    Columns: ``final_distance_mm`` (at the end), ``min_distance_mm``, ``success_<tol>mm`` (final
    distance within the tolerance), ``steps_to_<tol>mm`` (first time within it, NaN if never),
    the hold after the first arrival within 1 mm (:func:`hold_metrics`:
    ``within_1mm_after_arrival``, ``max_after_arrival_mm``, ``held_1.5mm``; NaN for an episode
    that never arrived), ``smoothness_kpa`` (mean absolute change of the command between consecutive steps, per valve),
    ``steps_above_limits`` (must be 0) and ``time_above_limits`` (its fraction of the episode).
    """
    distance = distances_mm(positions, goals)
    commands = np.asarray(commands, np.float64)
    if commands.shape[:2] != (distance.shape[0], distance.shape[1] - 1):
        raise ValueError(f"commands must be [E, T, 3] with T + 1 = {distance.shape[1]} "
                         f"positions, got {commands.shape}")
    rows = {
        "final_distance_mm": distance[:, -1],
        "min_distance_mm": distance.min(axis=1),
    }
    for tol in tolerances_mm:
        rows[f"success_{tol:g}mm"] = distance[:, -1] <= tol
        rows[f"steps_to_{tol:g}mm"] = first_step_within(distance, tol)
    rows.update(hold_metrics(distance))
    steps = commands.shape[1]
    change = np.abs(np.diff(commands, axis=1)) if steps > 1 else np.zeros_like(commands)
    rows["smoothness_kpa"] = change.mean(axis=(1, 2)) if steps > 1 else np.zeros(len(distance))
    above = steps_above_limits(commands, limits)
    rows["steps_above_limits"] = above
    rows["time_above_limits"] = above / max(steps, 1)
    return pd.DataFrame(rows)


def plant_gap(learned: pd.DataFrame, plant: pd.DataFrame, learned_final: np.ndarray,
              plant_final: np.ndarray) -> pd.DataFrame:
    """Per-episode gap between the learned environment and the plant for the same goals.

    ``final_gap_mm``: plant final distance minus learned final distance (positive: the policy
    does worse on the plant); ``final_position_gap_mm``: distance between the two final poses.
    """
    return pd.DataFrame({
        "final_gap_mm": plant["final_distance_mm"].to_numpy()
        - learned["final_distance_mm"].to_numpy(),
        "final_position_gap_mm": np.linalg.norm(
            np.asarray(plant_final) - np.asarray(learned_final), axis=-1) * MM_PER_M,
    })


def median_steps(steps: pd.Series) -> float:
    """Median of first-passage steps over ALL episodes, those that never got there (NaN)
    counted as never: ``inf`` when fewer than half of them got there, never a median over the
    ones that did alone."""
    values = np.where(np.isnan(steps.to_numpy(np.float64)), np.inf, steps.to_numpy(np.float64))
    return float(np.median(values)) if len(values) else float("nan")


HELD_COLUMN = f"held_{HELD_MM:g}mm"


def summarize(table: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    """Median / mean final distance, success rates and steps per group (e.g. policy, plant).

    ``reached_3mm``: the fraction of episodes that were ever within 3 mm; ``median_steps_to_3mm``
    the median over all episodes of when they first were (:func:`median_steps`: ``inf`` when
    fewer than half were). The hold (:func:`hold_metrics`; tables without its columns get
    none): ``arrived_1mm`` the fraction of episodes ever within 1 mm; over those that were,
    ``held_arrivals`` the share that ended within 1.5 mm, ``within_1mm_after_arrival`` the mean
    share of the times after the arrival spent within 1 mm and ``median_max_after_arrival_mm``
    the median of the largest distance after it (NaN where no episode arrived).
    """
    grouped = table.groupby(by, sort=False)
    out = grouped.agg(
        episodes=("final_distance_mm", "size"),
        median_final_mm=("final_distance_mm", "median"),
        mean_final_mm=("final_distance_mm", "mean"),
        p90_final_mm=("final_distance_mm", lambda x: float(np.percentile(x, 90))),
        success_1mm=("success_1mm", "mean"),
        success_3mm=("success_3mm", "mean"),
        reached_3mm=("steps_to_3mm", lambda x: float(np.isfinite(x).mean())),
        median_steps_to_3mm=("steps_to_3mm", median_steps),
        smoothness_kpa=("smoothness_kpa", "mean"),
        time_above_limits=("time_above_limits", "max"),
    )
    if HELD_COLUMN in table:
        hold = grouped.agg(
            arrived_1mm=("steps_to_1mm", lambda x: float(np.isfinite(x).mean())),
            held_arrivals=(HELD_COLUMN, "mean"),
            within_1mm_after_arrival=("within_1mm_after_arrival", "mean"),
            median_max_after_arrival_mm=("max_after_arrival_mm", "median"))
        out = out.join(hold)
    return out.reset_index()


def seed_spread(table: pd.DataFrame, by: list[str], value: str = "final_distance_mm"
                ) -> pd.DataFrame:
    """Spread over seeds of each seed's median ``value``: per group, the number of seeds, the
    median over seeds, the quartiles and the extremes of the per-seed medians."""
    per_seed = table.groupby([*by, "seed"], sort=False)[value].median()
    grouped = per_seed.groupby(level=list(range(len(by))), sort=False)
    out = grouped.agg(
        seeds="size", median_of_seed_medians="median",
        q25=lambda x: float(np.percentile(x, 25)), q75=lambda x: float(np.percentile(x, 75)),
        min="min", max="max")
    return out.reset_index()
