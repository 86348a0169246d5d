"""Following a reference with ``stage=control`` (``control.trajectory``).

The reference (:mod:`pipeline.arm.references`, the library training and evaluation use) is a
closed shape or a replayed measured path (``kind: replay``: a recording the policy's goals came
from, or a CSV of one, slowed), by name of ``evaluation.references`` or given inline with the
fields of :class:`~pipeline.schemas.ReferenceConfig`, or a timed CSV ``t,x,y,z`` (s, mm; its
reader refuses times that do not increase, entries that are not finite and coordinates in
metres). It is followed from ``t = 0``, the first control period's tick, for a duration
(:func:`trajectory_schedule`), after it was checked against the positions the policy was trained
and evaluated on.

Control period ``k`` (tick ``k / control_hz``) gets what period ``k`` of a training episode that
started at ``t = 0`` gets (:func:`pipeline.rl.envs.task.goal_path`,
:func:`pipeline.rl.envs.task.preview`): the goal is the reference at the period's end,
``(k + 1) / control_hz``, the preview the reference at ``(k + 1 + j) / control_hz``, ``j = 1 ..
env.preview``. The pose at tick ``k`` is scored against the reference at ``k / control_hz`` (the
records' ``ref_x, ref_y, ref_z``) with :func:`pipeline.evaluation.tracking.tracking_metrics`,
after the first ``settle_s`` seconds (:func:`trajectory_metrics`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from pipeline.arm import references
from pipeline.arm.references import (
    InvalidReference,
    Reference,
    ReplaySettings,
    reference_settings,
)
from pipeline.arm.safety import SafeSet
from pipeline.control.goals import GoalError, GoalSchedule
from pipeline.control.records import REFERENCE_COLUMNS
from pipeline.data.schemas import CMD_COLUMNS, XYZ
from pipeline.evaluation.tracking import SCORES, tracking_metrics
from pipeline.rl.envs import task

MM_PER_M = 1000.0
CHECK_HZ = 10.0  # the reference is checked against the reachable set at least this often


@dataclass
class ReferenceSchedule(GoalSchedule):
    """A reference followed, not goals: one goal index (0) for all periods, scored with
    :func:`trajectory_metrics` after ``settle_s`` s."""

    settle_s: float


@dataclass
class TrajectorySchedule(ReferenceSchedule):
    """A reference followed period by period (see the module doc); ``goals_m [T, 3]``: the goal
    of each period.

    previews_m: [T, P, 3] m, the preview of each period (P: the policy's ``env.preview``).
    ticks_m: [T + 1, 3] m, the reference at each tick ``k / control_hz``, ``k = 0 .. T``.
    """

    previews_m: np.ndarray
    ticks_m: np.ndarray

    def goal(self, period: int) -> tuple[int, np.ndarray] | None:
        if period < 0:
            return None
        return 0, self.goals_m[min(period, len(self.goals_m) - 1)]

    def preview(self, period: int, count: int) -> np.ndarray:
        if count != self.previews_m.shape[1]:
            raise ValueError(f"the schedule previews {self.previews_m.shape[1]} points, "
                             f"asked for {count}")
        return self.previews_m[min(max(period, 0), len(self.previews_m) - 1)]

    def reference(self, period: int) -> np.ndarray:
        return self.ticks_m[min(max(period, 0), len(self.ticks_m) - 1)]

    def add(self, period: int, goal_m: np.ndarray) -> None:
        raise GoalError("a session following control.trajectory takes no live goals")


@dataclass
class LiveTrajectory(ReferenceSchedule):
    """A reference that arrives while it is followed (``control.trajectory_topic``): points
    ``goals_m [N, 3]`` m due at arm times ``times_s [N]`` s (their stamps), joined by straight
    segments; before the first point's time the first point, after the last the last. Period
    ``k`` gets what a shape gives it (the module doc): its goal is the reference at
    ``(k + 1) / control_hz``, its preview the reference ``1 .. P`` periods later, its tick
    ``k / control_hz`` is scored against the reference then. A publisher that sends its points
    at least the policy's preview ahead gives it the preview it was trained with; points not
    yet received are not previewed (the reference holds the last one received).
    """

    times_s: np.ndarray
    control_hz: float
    takes_points: ClassVar[bool] = True

    def _at(self, t_s: np.ndarray) -> np.ndarray:
        """``[len(t_s), 3]`` m: the reference at arm times ``t_s``."""
        return np.stack([np.interp(t_s, self.times_s, self.goals_m[:, axis])
                         for axis in range(3)], axis=-1)

    def goal(self, period: int) -> tuple[int, np.ndarray] | None:
        if period < 0 or not len(self.times_s):
            return None
        return 0, self._at(np.array([(period + 1) / self.control_hz]))[0]

    def preview(self, period: int, count: int) -> np.ndarray:
        ahead = (period + 1 + np.arange(1, count + 1)) / self.control_hz
        return self._at(ahead) if len(self.times_s) else np.zeros((count, 3))

    def reference(self, period: int) -> np.ndarray | None:
        if not len(self.times_s):
            return None
        return self._at(np.array([max(period, 0) / self.control_hz]))[0]

    def add(self, period: int, goal_m: np.ndarray) -> None:
        raise GoalError("a session following control.trajectory_topic takes no live goals")

    def add_point(self, t_s: float, point_m: np.ndarray, now_s: float) -> str | None:
        """Take a point due at arm time ``t_s`` (a time already past: due now, ``now_s``);
        returns why it is refused (None: taken): a point due before the last one taken."""
        t_s = max(float(t_s), float(now_s))
        if len(self.times_s) and t_s < self.times_s[-1]:
            return (f"a point due at t={t_s:.3f} s arrived after one due at "
                    f"t={self.times_s[-1]:.3f} s (points must arrive in the order they are due)")
        self.times_s = np.append(self.times_s, t_s)
        self.goals_m = np.concatenate([self.goals_m.reshape(-1, 3),
                                       np.asarray(point_m, np.float64)[None]])
        return None


def live_trajectory(topic: str, duration_s: float | None, settle_s: float,
                    control_hz: float) -> LiveTrajectory:
    """An empty :class:`LiveTrajectory` of ``control.trajectory_topic``, followed for
    ``duration_s`` s from the first tick (None: until stopped), scored after ``settle_s`` s."""
    end = None
    if duration_s is not None:
        end = round(float(duration_s) * control_hz)
        if not (math.isfinite(float(duration_s)) and end >= 1):
            raise InvalidReference(f"control.duration_s={duration_s}: a reference is followed "
                                   f"for at least one control period (1 / {control_hz:g} s)")
    if not (math.isfinite(settle_s) and settle_s >= 0.0
            and (end is None or settle_s < end / control_hz)):
        raise InvalidReference(f"control.settle_s={settle_s}: expected >= 0 s and shorter than "
                               f"control.duration_s={duration_s}")
    return LiveTrajectory(np.zeros((0, 3)), np.zeros(1, int), end,
                          f"the points on {topic}", float(settle_s), times_s=np.zeros(0),
                          control_hz=float(control_hz))


@dataclass(frozen=True)
class Trajectory:
    """A reference to follow: ``reference``, how the report names it (``source``) and its own
    length in s (``duration_s``: a CSV's last time; None for a closed shape, which goes on)."""

    reference: Reference
    source: str
    duration_s: float | None


def trajectory_of(given: Any, named: Mapping[str, Any], centre_mm: np.ndarray,
                  recorded: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None
                  ) -> Trajectory:
    """The reference ``control.trajectory`` names: a key of ``named`` (``evaluation.references``),
    a mapping of :class:`ReferenceConfig` fields, or the path of a CSV (``t,x,y,z``, s and mm);
    a shape without a centre is centred on ``centre_mm [3]`` (the held-out goals' median, as in
    the evaluation); a replayed path (``kind: replay``) is its recording's (``recorded``, by
    run: ``(times [T] s, positions [T, 3] m)``, the runs the policy's goals came from) or its
    CSV's measured path from ``start_s`` on, slowed (:func:`references.replay_rest`)."""
    if isinstance(given, str) and (given.lower().endswith(".csv") or Path(given).is_file()):
        path = Path(given)
        if not path.is_file():
            raise InvalidReference(f"control.trajectory={given}: no such CSV file (t,x,y,z: s, "
                                   f"mm)")
        reference = references.read_csv(path)
        return Trajectory(reference, f"the CSV {path}", float(np.asarray(reference.times)[-1]))
    if isinstance(given, Mapping):
        shape, name = reference_settings(given, "control.trajectory"), "control.trajectory"
    elif isinstance(given, str) and given in named:
        shape = reference_settings(named[given], f"evaluation.references.{given}")
        name = given
    else:
        raise InvalidReference(
            f"control.trajectory={given!r}: expected a name of evaluation.references "
            f"{sorted(named)}, a shape such as {{kind: circle, size_mm: 5, period_s: 20}}, or a "
            f"CSV file with columns t,x,y,z (s, mm)")
    if isinstance(shape, ReplaySettings):
        paths = references.measured_paths(shape, recorded or {}, name)
        run, reference = references.replay_rest(paths, shape, name)
        source = (f"{name}: the measured path of {run} from {shape.start_s:g} s, "
                  f"{shape.slow_down:g} times slower")
        return Trajectory(reference, source, float(np.asarray(reference.times)[-1]))
    if shape.centre_mm is None:
        shape = dataclasses.replace(shape, centre_mm=tuple(float(v) for v in centre_mm))
    centre = np.round(np.asarray(shape.centre_mm, np.float64), 1).tolist()
    source = (f"{name}: a {shape.kind} of {shape.size_mm:g} mm in {shape.plane}, "
              f"{shape.period_s:g} s a lap, around {centre} mm")
    return Trajectory(references.shape(shape), source, None)


def trajectory_schedule(trajectory: Trajectory, duration_s: float, settle_s: float,
                        control_hz: float, preview: int, reachable_m: np.ndarray,
                        tolerance_mm: float) -> TrajectorySchedule:
    """The schedule of ``trajectory`` followed for ``duration_s`` s at ``control_hz`` with a
    preview of ``preview`` points, scored after ``settle_s`` s. Refused (one
    :class:`InvalidReference`, before anything moves) where a point a period is sent toward,
    previews or is scored at lies more than ``tolerance_mm`` from every position of
    ``reachable_m [N, 3]`` m (:func:`pipeline.arm.references.check_reachable`)."""
    periods = round(float(duration_s) * control_hz)
    if not (math.isfinite(duration_s) and periods >= 1):
        raise InvalidReference(f"control.duration_s={duration_s}: a reference is followed for "
                               f"at least one control period (1 / {control_hz:g} s)")
    if not (math.isfinite(settle_s) and 0.0 <= settle_s < periods / control_hz):
        raise InvalidReference(f"control.settle_s={settle_s}: expected >= 0 s and shorter than "
                               f"the {periods / control_hz:g} s the reference is followed")
    reference = trajectory.reference
    horizon = (periods + preview) / control_hz  # the last point any period is sent or previews
    references.check_reachable(reference, horizon, max(CHECK_HZ, control_hz), reachable_m,
                               tolerance_mm, f"control.trajectory ({trajectory.source})")
    goals = np.asarray(task.goal_path(reference, periods, control_hz), np.float64)
    if preview:
        previews = jax.vmap(lambda period: task.preview(reference, period, control_hz, preview))(
            jnp.arange(periods))
        previews = np.asarray(previews, np.float64)
    else:
        previews = np.zeros((periods, 0, 3))
    ticks = np.asarray(references.positions(reference, jnp.arange(periods + 1) / control_hz),
                       np.float64)
    return TrajectorySchedule(goals, np.zeros(1, int), periods, trajectory.source,
                              float(settle_s), previews_m=previews, ticks_m=ticks)


def trajectory_metrics(periods: pd.DataFrame, control_hz: float, settle_s: float,
                       safe: SafeSet | None = None) -> pd.DataFrame:
    """One row: :func:`~pipeline.evaluation.tracking.tracking_metrics` of the session's records
    (the pose at each tick against ``ref_x, ref_y, ref_z``; with ``safe``, the limits the
    commands ``p_cmd_<j>`` were sent within, the share of them on those limits) from the first
    period recorded (a live reference: the first with a point) and after ``settle_s`` more, with
    the periods scored and ``interpolated`` (periods skipped after a stall have no row: their
    pose and reference are interpolated between the neighbouring ticks, their command is the
    one held). A session that ended before the settle time (interrupted) scores NaN."""
    table = periods.sort_values("period").drop_duplicates("period", keep="last")
    table = table[table["period"] >= 0].set_index("period")
    ticks = np.arange(int(table.index.min()), int(table.index.max()) + 1)
    grid = table[[*XYZ, *REFERENCE_COLUMNS]].reindex(ticks)
    interpolated = int(grid.isna().any(axis=1).sum())
    grid = grid.interpolate(limit_direction="both")
    positions = grid[XYZ].to_numpy(np.float64)[None]
    reference = grid[REFERENCE_COLUMNS].to_numpy(np.float64)[None]
    commands = None
    if safe is not None:  # the command of each period but the last tick's (none is sent there)
        commands = table[CMD_COLUMNS].reindex(ticks).ffill().to_numpy(np.float64)[None, :-1]
    if len(ticks) <= math.ceil(settle_s * control_hz - 1e-9):  # stopped before it settled
        metrics = pd.DataFrame({name: [np.nan] for name in SCORES})
    else:
        metrics = tracking_metrics(positions, reference, control_hz, settle_s,
                                   commands=commands, safe=safe)
    return metrics.assign(settle_s=float(settle_s), periods=len(ticks) - 1,
                          interpolated=interpolated)
