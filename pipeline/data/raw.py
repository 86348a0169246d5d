"""The raw streams of a collection (``commands``, ``mocap``, ``runs``): checks, counts, a figure.

The same for every robot: the simulated arm, imported recordings and a ROS 2 session; the
``collect`` stage writes them into its artifact.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.data.schemas import CMD_COLUMNS, XYZ, check_workspace
from pipeline.schemas import WorkspaceConfig

log = logging.getLogger(__name__)
STAGE = "collect"


class CollectionInterrupted(RuntimeError):
    """A recording was cut short; what was recorded is in an artifact, marked incomplete."""


def check_positions(mocap: pd.DataFrame, runs: pd.DataFrame, workspace: WorkspaceConfig) -> None:
    """The valid positions of every run must lie in ``workspace`` (the robot's box, m); an error
    names the run and its source."""
    sources = dict(zip(runs["run_id"], runs["source"]))
    for run_id, run in mocap.groupby("run_id", sort=False):
        check_workspace(run[run["valid"].astype(bool)], workspace,
                        f"run {run_id} ({sources.get(run_id, 'unknown source')})")


def raw_summary(commands: pd.DataFrame, mocap: pd.DataFrame, runs: pd.DataFrame
                ) -> dict[str, Any]:
    """The counts of a collection for its manifest (and the log)."""
    summary = {
        "runs": len(runs), "commands": len(commands), "frames": len(mocap),
        "dropped_frames": int((~mocap["valid"]).sum()),
        "incomplete_runs": runs.loc[~runs["complete"], "run_id"].tolist(),
    }
    log.info("collect: %d runs, %d commands, %d mocap frames (%d dropped)", len(runs),
             len(commands), len(mocap), summary["dropped_frames"])
    return summary


def plot_runs(path: Path, commands: pd.DataFrame, mocap: pd.DataFrame) -> Path:
    """Commands and positions of the first run over time, and every run's x-z footprint."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = commands["run_id"].iloc[0]
    cmd = commands[commands["run_id"] == first]
    pos = mocap[mocap["run_id"] == first]
    t0 = cmd["t"].iloc[0]
    fig = plt.figure(figsize=(12, 6.5))
    grid = fig.add_gridspec(4, 2, width_ratios=[2.2, 1])
    ax = fig.add_subplot(grid[0, 0])
    for j, column in enumerate(CMD_COLUMNS):
        ax.step(cmd["t"] - t0, cmd[column], where="post", lw=0.9, label=f"valve {j}")
    ax.set_ylabel("p_cmd [kPa]")
    ax.legend(fontsize=7, ncol=3, loc="upper right")
    ax.set_title(f"run {first}: commands and motion capture", fontsize=10)
    for k, axis in enumerate(XYZ):
        ax_k = fig.add_subplot(grid[k + 1, 0], sharex=ax)
        ax_k.plot(pos["t"] - t0, pos[axis] * 1e3, lw=0.6, color=f"C{k + 3}")
        ax_k.set_ylabel(f"{axis} [mm]")
    ax_k.set_xlabel("time [s]")
    ax_xz = fig.add_subplot(grid[:, 1])
    for i, (run_id, run) in enumerate(mocap.groupby("run_id", sort=False)):
        ax_xz.plot(run["x"] * 1e3, run["z"] * 1e3, lw=0.3, alpha=0.7, color=f"C{i % 10}",
                   label=str(run_id))
        ax_xz.plot(run["x"].iloc[:20].mean() * 1e3, run["z"].iloc[:20].mean() * 1e3, "k+", ms=8)
    ax_xz.set_xlabel("x [mm]")
    ax_xz.set_ylabel("z [mm]")
    ax_xz.set_aspect("equal", adjustable="datalim")
    ax_xz.set_title("footprint of every run (+: rest pose)", fontsize=10)
    ax_xz.legend(fontsize=6, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
