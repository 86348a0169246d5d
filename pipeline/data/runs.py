"""A recorded run as the model, the calibration and the studies take it: named arrays on one grid.

:func:`pipeline.data.alignment.runs_at_model_rate` makes them from the aligned table (the only
resampler), :func:`pipeline.data.alignment.load_runs` from an align artifact's table file.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import numpy as np


@dataclasses.dataclass(frozen=True, eq=False)
class Run:
    """One run on a regular grid of ``T`` steps.

    Attributes:
        run_id: the run's name (a recording's, or ``<run>#<segment>`` after a split at a gap).
        times_s: float64 [T], seconds on the recording's clock (not shifted to start at 0).
        pressures_kpa: float32 [T, V], the pressure command in force on each valve, kPa.
        positions_m: float32 [T, 3], the marker position (x, y, z; y vertical), metres.
    """

    run_id: str
    times_s: np.ndarray
    pressures_kpa: np.ndarray
    positions_m: np.ndarray

    def __post_init__(self):
        steps = len(self.pressures_kpa)
        if np.ndim(self.pressures_kpa) != 2 or np.shape(self.positions_m) != (steps, 3):
            raise ValueError(f"run {self.run_id!r}: pressures_kpa must be [T, V] and positions_m "
                             f"[T, 3], got {np.shape(self.pressures_kpa)} and "
                             f"{np.shape(self.positions_m)}")
        if np.shape(self.times_s) != (steps,):
            raise ValueError(f"run {self.run_id!r}: times_s must be [T={steps}], got "
                             f"{np.shape(self.times_s)}")

    def __len__(self) -> int:
        """The number of grid steps ``T``."""
        return len(self.pressures_kpa)

    def replace(self, **changes) -> Run:
        """This run with some fields changed (a copy; the shapes are checked again)."""
        return dataclasses.replace(self, **changes)

    def head(self, steps: int, run_id: str) -> Run:
        """The first ``steps`` grid steps of this run, named ``run_id``."""
        return Run(run_id, self.times_s[:steps], self.pressures_kpa[:steps],
                   self.positions_m[:steps])

    def after(self, start_s: float) -> Run:
        """This run from ``start_s`` s after its first step on (the same id); a ValueError naming
        the run and its duration when less than two steps would be left."""
        keep = self.times_s - self.times_s[0] >= start_s - 1e-9
        if keep.sum() < 2:
            raise ValueError(f"run {self.run_id!r} lasts {self.times_s[-1] - self.times_s[0]:.3g} "
                             f"s: less than two steps of it are left from {start_s:g} s on")
        return Run(self.run_id, self.times_s[keep], self.pressures_kpa[keep],
                   self.positions_m[keep])


def runs_by_id(runs: Iterable[Run]) -> dict[str, Run]:
    """``{run_id: run}`` (the ids are unique within one aligned table)."""
    return {run.run_id: run for run in runs}
