"""Periods a fixed-rate loop misses when it wakes late: a stall of the process (SIGSTOP, swap)
or a forward step of its clock. Such a loop never catches up: the overdue periods are skipped
and counted, and too many in a row is a fault the loop reports in its own words."""

from __future__ import annotations


class MissedPeriods:
    """The count of periods of ``period_s`` missed, in a row (until :meth:`reset`) and in all."""

    def __init__(self, period_s: float, max_in_row: int):
        self.period_s = float(period_s)
        self.max_in_row = int(max_in_row)
        self.in_row = 0
        self.total = 0

    def count(self, late_s: float) -> int:
        """Whole periods missed by a wake-up ``late_s`` after its tick (0 within one period),
        added to :attr:`in_row` and :attr:`total`."""
        if late_s <= self.period_s:
            return 0
        missed = int(late_s // self.period_s)
        self.in_row += missed
        self.total += missed
        return missed

    @property
    def exceeded(self) -> bool:
        """More than ``max_in_row`` periods missed in a row."""
        return self.in_row > self.max_in_row

    def reset(self) -> None:
        """The loop is on time again: the next miss starts a new run."""
        self.in_row = 0
