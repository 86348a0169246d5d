"""A calibration walk on an arm of the control loop (:class:`pipeline.control.loop.SimArm`):
valve commands sent one per control period through the command gate, every mocap frame kept,
the preload commanded last whatever happens. The rows are collect's raw tables (``commands``
and ``mocap``, ``pipeline.data.schemas``), so the walk aligns as a collected run does.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.data.schemas import CMD_COLUMNS, XYZ
from pipeline.data.sessions import increasing
from pipeline.ros2.gate import CommandGate


def drive_walk(arm, gate: CommandGate, commands: np.ndarray, control_hz: float, run_id: str
               ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Drive ``arm`` with ``commands`` [N, valves] kPa, command ``k`` from ``k / control_hz`` arm
    seconds on, each through ``gate`` (projection onto the limits, checked); returns the
    ``commands`` rows (as sent) and the ``mocap`` rows (every frame until the end of the last
    period whose stamp comes after the earlier frames') of one run ``run_id``. The arm is sent the preload at the end, also on an error."""
    commands = np.asarray(commands, np.float64)
    if commands.ndim != 2 or len(commands) == 0:
        raise ValueError(f"a walk needs commands [N, valves], got shape {commands.shape}")
    period = 1.0 / float(control_hz)
    sent, frames = [], []
    try:
        arm.start()
        for index, command in enumerate(commands):
            safe = gate.check(command)
            sent.append((arm.publish(safe), *safe))
            while arm.now() < (index + 1) * period - 1e-9:
                arm.advance((index + 1) * period)
                frames += arm.take_frames()
    finally:
        arm.stop_safely()
    command_rows = pd.DataFrame(sent, columns=["t", *CMD_COLUMNS[:commands.shape[1]]])
    command_rows.insert(0, "run_id", run_id)
    stamps = np.array([frame[0] for frame in frames], np.float64)
    positions = np.array([frame[2] for frame in frames], np.float64).reshape(-1, len(XYZ))
    # the mocap table's times increase: a frame whose jittered stamp is not after every earlier
    # one is dropped (as a dropped frame)
    later = increasing(stamps)
    stamps, positions = stamps[later], positions[later]
    mocap_rows = pd.DataFrame({"run_id": run_id, "t": stamps,
                               **{axis: positions[:, k] for k, axis in enumerate(XYZ)},
                               "valid": True})
    return command_rows, mocap_rows
