"""Goals for ``stage=control``: a list held ``hold_s`` each, CSV waypoints, or live from a topic.

A schedule works in control periods: period ``k`` (at ``k / control_hz`` arm seconds from the
start) commands toward :meth:`GoalSchedule.goal` ``(k)``. Goals are given in mm in the mocap frame
(the topic: metres, as ROS messages are) and checked against the workspace the policy was trained
on before anything is commanded.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pandas as pd

from pipeline.arm.references import read_timed_points
from pipeline.schemas import ConfigError, ControlConfig

MM_PER_M = 1000.0


class GoalError(ConfigError):
    """A goal the policy cannot be sent to (outside its workspace, malformed)."""


def workspace_problem(goal_m: np.ndarray, workspace_m: np.ndarray, margin_mm: float
                      ) -> str | None:
    """Why ``goal_m [3]`` lies outside the training goals' box (plus ``margin_mm``), or None."""
    goal_mm, box_mm = np.asarray(goal_m) * MM_PER_M, np.asarray(workspace_m) * MM_PER_M
    below = np.maximum(box_mm[0] - margin_mm - goal_mm, 0.0)
    above = np.maximum(goal_mm - box_mm[1] - margin_mm, 0.0)
    outside = np.maximum(below, above)
    if not np.any(outside > 0) and np.all(np.isfinite(goal_mm)):
        return None
    axes = ", ".join(f"{axis} by {d:.1f} mm" for axis, d in zip("xyz", outside) if d > 0)
    box = ", ".join(f"{axis} [{lo:.1f}, {hi:.1f}]" for axis, lo, hi in zip("xyz", *box_mm))
    return (f"goal {np.round(goal_mm, 1).tolist()} mm is outside the workspace the policy was "
            f"trained on ({axes or 'not finite'}); the workspace (training goals, mm): {box}, "
            f"plus control.workspace_margin_mm={margin_mm:g}")


@dataclass
class GoalSchedule:
    """Goals by period: ``goals_m [G, 3]``, goal ``i`` from period ``starts[i]``; the session ends
    at period ``end`` (None: open-ended, live goals)."""

    goals_m: np.ndarray
    starts: np.ndarray
    end: int | None
    source: str
    takes_points: ClassVar[bool] = False  # live reference points (:meth:`add_point`)

    def goal(self, period: int) -> tuple[int, np.ndarray] | None:
        """``(goal index, goal [3] m)`` in force at ``period``; None before the first goal."""
        index = int(np.searchsorted(self.starts, period, side="right")) - 1
        if index < 0:
            return None
        return index, self.goals_m[index]

    def preview(self, period: int, count: int) -> np.ndarray:
        """``[count, 3]`` m: the goals in force at periods ``period + 1 .. period + count`` (the
        preview a tracking policy observes; past the last goal, the last goal; live goals: the
        current one, the only one known)."""
        ahead = [self.goal(period + j) for j in range(1, count + 1)]
        return np.array([goal for _, goal in ahead], np.float64).reshape(count, 3)

    def reference(self, period: int) -> np.ndarray | None:
        """Goals follow no reference: None (a :class:`~pipeline.control.trajectory.
        TrajectorySchedule` gives the reference at the period's tick)."""
        return None

    def add(self, period: int, goal_m: np.ndarray) -> None:
        """A live goal, in force from ``period``."""
        self.goals_m = np.concatenate([self.goals_m.reshape(-1, 3), np.asarray(goal_m)[None]])
        self.starts = np.append(self.starts, period)

    def add_point(self, t_s: float, point_m: np.ndarray, now_s: float) -> str | None:
        """A live reference's point (``control.trajectory_topic``:
        :class:`pipeline.control.trajectory.LiveTrajectory`); goals take none."""
        raise GoalError("live reference points are followed with control.trajectory_topic only")


def _as_goals(values: Any, what: str) -> np.ndarray:
    goals = np.asarray(values, np.float64)
    if goals.ndim != 2 or goals.shape[1] != 3 or not np.isfinite(goals).all():
        raise GoalError(f"{what}: expected finite [x, y, z] rows in mm, got {np.asarray(values)}")
    return goals / MM_PER_M


def read_waypoints(path: Path) -> pd.DataFrame:
    """The waypoints of a CSV with columns ``t,x,y,z`` (s, mm); errors name the file."""
    values = read_timed_points(path, f"control.goals_csv {path}", GoalError)
    table = pd.DataFrame(values, columns=["t", "x", "y", "z"])
    if not np.isfinite(values).all():
        raise GoalError(f"control.goals_csv {path}: every t,x,y,z must be a finite number")
    if (table["t"].iloc[0] < 0) or (np.diff(table["t"]) <= 0).any():
        raise GoalError(f"control.goals_csv {path}: column t must start at >= 0 s and increase")
    return table


def goal_schedule(control: ControlConfig, control_hz: float, workspace_m: np.ndarray
                  ) -> GoalSchedule:
    """The schedule of ``control.goals`` / ``control.goals_csv`` / ``control.goal_topic`` (exactly
    one), every goal checked against the workspace."""
    sources = {"goals": control.goals, "goals_csv": control.goals_csv,
               "goal_topic": control.goal_topic}
    given = [name for name, value in sources.items() if value]
    if len(given) != 1:
        raise GoalError(f"stage=control needs exactly one of control.goals (a list of [x, y, z] mm), "
                        f"control.goals_csv (t,x,y,z) or control.goal_topic; got {given or 'none'}")
    hold = round(float(control.hold_s) * control_hz)
    if hold < 1:
        raise GoalError(f"control.hold_s={control.hold_s} is shorter than a control period "
                        f"(1 / {control_hz} s)")
    if control.goal_topic:
        end = (None if control.duration_s is None
               else round(float(control.duration_s) * control_hz))
        return GoalSchedule(np.zeros((0, 3)), np.zeros(0, int), end, str(control.goal_topic))
    if control.goals_csv:
        table = read_waypoints(Path(str(control.goals_csv)))
        goals = _as_goals(table[["x", "y", "z"]].to_numpy(), f"control.goals_csv {control.goals_csv}")
        starts = np.round(table["t"].to_numpy() * control_hz).astype(int)
        if (np.diff(starts) < 1).any():
            raise GoalError(f"control.goals_csv {control.goals_csv}: waypoints closer than one "
                            f"control period (1 / {control_hz} s)")
        source = str(control.goals_csv)
    else:
        goals = _as_goals(list(control.goals), "control.goals")
        starts = np.arange(len(goals)) * hold
        source = "control.goals"
    for goal in goals:
        problem = workspace_problem(goal, workspace_m, float(control.workspace_margin_mm))
        if problem:
            raise GoalError(f"{source}: refused: {problem}")
    return GoalSchedule(goals, starts, int(starts[-1] + hold), source)
