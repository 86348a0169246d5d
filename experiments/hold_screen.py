"""Formulations of the reaching task side by side on one chain: what each does after arrival.

    python -m experiments.hold_screen [--variants "" "env.hold_periods=5" ...]
        [--set KEY=VALUE ...] [--output-dir DIR]

Each variant is a space-separated list of pipeline overrides ("" is the config as it is). For
each, ``stage=evaluate`` (after what it needs upstream: the policies of every type in
``evaluation.policies``, trained with the variant's env settings; artifacts reused when present)
rolls every seed out on the held-out goals of each plant the evaluation runs (the learned model,
the simulated arm for ``robot=sim``, calibrated twins ...), with the preload as the only baseline
(``evaluation.baselines=[preload]``) unless ``--set`` says otherwise. Printed per variant, policy
type and plant: median and p90 final distance, success within 1 mm, the share of episodes that
were ever within 1 mm and, of those, the share that ended within 1.5 mm (the arrivals held), the
mean share of the time after the arrival spent within 1 mm and the median of the largest distance
after it (:func:`pipeline.evaluation.metrics.hold_metrics`). Also written to
``<output-dir>/hold_screen/results.csv``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import pandas as pd

from pipeline.studies import run_stage

COLUMNS = {"median_final_mm": "median", "p90_final_mm": "p90", "success_1mm": "<=1mm",
           "arrived_1mm": "arrived", "held_arrivals": "held",
           "within_1mm_after_arrival": "time<=1mm", "median_max_after_arrival_mm": "max after"}


def screen(output_dir: Path, variants: list[str], overrides: list[str]) -> pd.DataFrame:
    """One row per (variant, controller, plant) of the evaluate stage's summary."""
    rows = []
    for variant in variants:
        evaluated = run_stage("evaluate", f"paths.output_dir={output_dir}",
                              "evaluation.baselines=[preload]", *overrides,
                              *variant.split())["evaluate"]
        summary = pd.read_parquet(evaluated.file("summary.parquet"))
        rows.append(summary.assign(variant=variant or "as it is", evaluate=evaluated.key))
    table = pd.concat(rows, ignore_index=True)
    return table[["variant", "controller", "plant", *COLUMNS, "episodes", "evaluate"]]


def main(argv: list[str] | None = None) -> None:
    from pipeline.config import PROJECT_ROOT

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output-dir", type=Path, default=PROJECT_ROOT / "outputs",
                        help="the pipeline's paths.output_dir (its artifacts are reused)")
    parser.add_argument("--variants", nargs="+", default=["", "env.hold_periods=5"],
                        help="each a space-separated list of overrides ('' : as it is)")
    parser.add_argument("--set", dest="overrides", nargs="+", action="extend", default=[],
                        metavar="KEY=VALUE", help="further pipeline overrides for every variant")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s")
    table = screen(args.output_dir, args.variants, args.overrides)
    out = args.output_dir / "hold_screen"
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "results.csv", index=False)
    shown = table.drop(columns=["evaluate"]).rename(columns=COLUMNS)
    with pd.option_context("display.width", 200, "display.max_columns", 20,
                           "display.float_format", "{:.3f}".format):
        print(shown.to_string(index=False))
    print(f"\n{out / 'results.csv'}")


if __name__ == "__main__":
    main()
