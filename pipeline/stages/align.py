"""Stage ``align``: the collected raw streams on one time base (:mod:`pipeline.data.alignment`).

Artifact: ``aligned.parquet`` and ``align_report.parquet`` (the per-run counts, also logged).
"""

from __future__ import annotations

import logging
from typing import Any

from pipeline import keys
from pipeline.data.alignment import COUNT_FIELDS, align_tables
from pipeline.data.schemas import ALIGNED, COMMANDS, MOCAP, RUNS, DataError, read_table, write_table
from pipeline.infra.artifacts import Artifact, ArtifactStore, produce
from pipeline.infra.parquet import table_metadata, write_parquet

log = logging.getLogger(__name__)
STAGE = "align"


def align(cfg: Any) -> Artifact:
    """Align the collected raw streams of this config (``collect`` must have run)."""
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.align_spec(cfg)
    raw = store.require("collect", inputs["collect"])
    settings = cfg.dataset.align

    def build(writer):
        commands, _ = read_table(raw.file("commands.parquet"), COMMANDS, cfg.robot.limits)
        mocap, _ = read_table(raw.file("mocap.parquet"), MOCAP)
        runs, _ = read_table(raw.file("runs.parquet"), RUNS)
        incomplete = runs.loc[~runs["complete"], "run_id"].tolist()
        if incomplete and not settings.accept_incomplete:
            raise DataError(str(raw.file("runs.parquet")), f"runs {incomplete} were interrupted "
                            "(marked incomplete); set dataset.align.accept_incomplete=true to "
                            "use them", "complete")
        aligned, report = align_tables(commands, mocap, settings, str(raw.path))
        config = {"dataset.align": spec["align"], "robot": cfg.robot.name}
        provenance = {"stage": STAGE, "inputs": inputs}
        write_table(aligned, writer.file("aligned.parquet"), ALIGNED, config, provenance)
        write_parquet(report, writer.file("align_report.parquet"),
                      table_metadata(report, "align_report", config, provenance,
                                     {k: "rows" if k == "rows" else "count" for k in COUNT_FIELDS}))
        totals = {k: int(report[k].sum()) for k in COUNT_FIELDS}
        writer.summary = {"runs": len(report), **totals}
        log.info("align: %d runs, %s", len(report),
                 ", ".join(f"{k}={v}" for k, v in totals.items()))

    return produce(store, STAGE, spec, inputs, build, force=cfg.force)
