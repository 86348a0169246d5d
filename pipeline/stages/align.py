"""Stage ``align``: the collected raw streams on one time base (:mod:`pipeline.data.alignment`).

The runs of the session artifacts named in ``dataset.sessions`` (control sessions, improve's
walks: :mod:`pipeline.data.sessions`) join the collected ones, once checked to come from the
same arm at the same rates; the aligned table's metadata keeps each one's provenance.

Artifact: ``aligned.parquet`` and ``align_report.parquet`` (the per-run counts, also logged).
"""

from __future__ import annotations

import logging
from typing import Any

import pandas as pd

from pipeline import keys
from pipeline.data.alignment import COUNT_FIELDS, align_tables
from pipeline.data.raw import check_positions
from pipeline.data.schemas import ALIGNED, COMMANDS, MOCAP, RUNS, DataError, read_table, write_table
from pipeline.data.sessions import (
    arm_identity,
    check_session,
    join_sessions,
    mocap_rate_hz,
    read_session,
)
from pipeline.infra.artifacts import Artifact, ArtifactStore, produce
from pipeline.infra.parquet import table_metadata, write_parquet
from pipeline.stages._sessions import session_artifact

log = logging.getLogger(__name__)
STAGE = "align"


def align(cfg: Any) -> Artifact:
    """Align the collected raw streams of this config (``collect`` must have run)."""
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.align_spec(cfg)
    raw = store.require("collect", inputs["collect"])
    sessions = [session_artifact(store, str(entry)) for entry in cfg.dataset.sessions]
    settings = cfg.dataset.align

    def build(writer):
        commands, _ = read_table(raw.file("commands.parquet"), COMMANDS, cfg.robot.limits)
        mocap, _ = read_table(raw.file("mocap.parquet"), MOCAP)
        runs, _ = read_table(raw.file("runs.parquet"), RUNS)
        commands, mocap, runs, joined = _join(cfg.robot, commands, mocap, runs, sessions)
        incomplete = runs.loc[~runs["complete"], "run_id"].tolist()
        if incomplete and not settings.accept_incomplete:
            raise DataError(str(raw.file("runs.parquet")), f"runs {incomplete} were interrupted "
                            "(marked incomplete); set dataset.align.accept_incomplete=true to "
                            "use them", "complete")
        aligned, report = align_tables(commands, mocap, settings, str(raw.path))
        config = {"dataset.align": spec["align"], "robot": cfg.robot.name}
        provenance = {"stage": STAGE, "inputs": inputs, "sessions": joined}
        write_table(aligned, writer.file("aligned.parquet"), ALIGNED, config, provenance)
        write_parquet(report, writer.file("align_report.parquet"),
                      table_metadata(report, "align_report", config, provenance,
                                     {k: "rows" if k == "rows" else "count" for k in COUNT_FIELDS}))
        totals = {k: int(report[k].sum()) for k in COUNT_FIELDS}
        writer.summary = {"runs": len(report), "session_runs": list(joined), **totals}
        log.info("align: %d runs, %s", len(report),
                 ", ".join(f"{k}={v}" for k, v in totals.items()))

    return produce(store, STAGE, spec, inputs, build, force=cfg.force)


def _join(robot: Any, commands: pd.DataFrame, mocap: pd.DataFrame, runs: pd.DataFrame,
          sessions: list[Artifact]) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame, dict]:
    """The collected tables with the sessions' runs joined, each checked to come from this
    arm (``robot``'s valves, rating, rates and workspace); and their provenance by run id."""
    joined: dict[str, Any] = {}
    if not sessions:
        return commands, mocap, runs, joined
    rate = mocap_rate_hz(mocap)
    read = []
    for artifact in sessions:
        session = read_session(artifact.path, robot.limits)
        check_session(session, str(artifact.path), n_valves=int(robot.n_valves),
                      control_hz=float(robot.control_hz), mocap_hz=rate,
                      arm=arm_identity(robot.rating))
        check_positions(session.mocap, session.runs, robot.workspace)
        read.append(session)
        joined[session.run_id] = {**session.provenance, "path": str(artifact.path)}
    log.info("align: %d session run(s) joined: %s", len(read), list(joined))
    return (*join_sessions(commands, mocap, runs, read), joined)
