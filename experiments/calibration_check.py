"""Where a calibrated simulator misses the real runs: per run and axis, and how far it moves.

Simulates the physics of a calibrate artifact (its ``physics.json``) on the aligned runs of
``robot=sorolex_csv`` at 20 Hz, open loop from the settled preload at its own rest pose (the
mean of the fitted offsets), and prints per run: the mean error, the mean absolute error and the
bias per axis, and the mean lateral (x-z) distance from the rest pose, simulated and measured.
In-sample when the artifact's fit on all runs saw the run (it did, for the shared runs).

Usage: ``python -m experiments.calibration_check <calibrate artifact folder>``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from pipeline.arm import calibration as calib
from pipeline.arm.sim_arm import SimParams
from pipeline.studies import recorded_runs

HZ = 20.0
REST_FRAMES = 20  # the first second


def main(folder: str) -> None:
    physics = json.loads((Path(folder) / "physics.json").read_text())["physics"]
    physics.pop("substeps")
    _, runs = recorded_runs("robot=sorolex_csv", rate_hz=HZ, grid="clock")
    batch = calib.RunBatch.from_runs(runs)
    predicted = calib.open_loop_template(SimParams.noise_free(physics, HZ, 2), batch)
    print("run    error mm  |error| x, y, z mm   bias x, y, z mm     lateral distance from rest "
          "mm: simulated / measured")
    for i, run in enumerate(runs):
        n = len(run)
        error = (predicted[i, :n] - run.positions_m) * 1e3
        measured = (run.positions_m - run.positions_m[:REST_FRAMES].mean(0)) * 1e3
        simulated = (predicted[i, :n] - predicted[i, 0]) * 1e3
        print(f"{run.run_id[-5:]}  {np.linalg.norm(error, axis=1).mean():6.2f}    "
              f"{np.abs(error).mean(0).round(2)}  {error.mean(0).round(2)}   "
              f"{np.hypot(simulated[:, 0], simulated[:, 2]).mean():5.1f} / "
              f"{np.hypot(measured[:, 0], measured[:, 2]).mean():5.1f}")


if __name__ == "__main__":
    main(sys.argv[1])
