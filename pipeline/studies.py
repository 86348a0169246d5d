"""What the measurement scripts under ``experiments/`` share: the pipeline's own stages, run
through its router, and the recorded runs as the stages themselves read them.

A study composes the pipeline's config from Hydra overrides as the command line does, runs the
stage it needs after what that stage needs upstream (artifacts reused when they are there,
produced when they are missing) and takes the runs from the align artifact through
:func:`pipeline.data.alignment.load_runs`: the one resampler, the same records
(:class:`pipeline.data.runs.Run`) that ``fit_model`` and ``calibrate`` fit to. Scripts import
from here and from the libraries, never from each other.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pipeline.__main__ import run
from pipeline.config import compose
from pipeline.data.alignment import load_runs
from pipeline.data.runs import Run

log = logging.getLogger(__name__)


def run_stage(stage: str, *overrides: str) -> dict[str, Any]:
    """Run ``stage`` (after what it needs upstream) for the config composed from ``overrides``;
    return each stage's artifact of this config by stage name (``pipeline.__main__.run``)."""
    started = time.perf_counter()
    results = run(compose(f"stage={stage}", *overrides))
    log.info("%s %s: %.0f s", stage, " ".join(overrides), time.perf_counter() - started)
    return results


def recorded_runs(*overrides: str, rate_hz: float | None = None, grid: str | None = None
                  ) -> tuple[Any, list[Run]]:
    """The config composed from ``overrides`` and its aligned runs (``stage=align`` run or
    reused) at ``rate_hz`` on ``grid`` (``clock`` or ``commands``); by default the model's
    rate and grid (``dataset.model_hz``, ``dataset.model_grid``), as ``fit_model`` reads them.
    Sorted by run id."""
    cfg = compose("stage=align", *overrides)
    aligned = run(cfg)["align"]
    rate = float(cfg.dataset.model_hz) if rate_hz is None else float(rate_hz)
    on_grid = str(cfg.dataset.model_grid) if grid is None else grid
    return cfg, load_runs(aligned.file("aligned.parquet"), rate, on_grid)


def start_study(args: Any, report: Callable[[str], str]) -> bool:
    """A study script's start: log at INFO with times; with ``args.report``, print
    ``report(args.out)`` (the table of its results file) and return True: nothing else to do."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if getattr(args, "report", False):
        if not Path(args.out).is_file():
            raise SystemExit(f"--report: no results file {args.out} (run the study first, or "
                             "name its file with --out)")
        print(report(args.out))
        return True
    return False


def append_jsonl(path: str | Path, row: dict[str, Any]) -> None:
    """One JSON line more in the results file ``path`` (its folders made where missing)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "a") as file:
        file.write(json.dumps(row) + "\n")
