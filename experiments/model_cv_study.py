"""One row of the generalization study: leave-one-run-out on the real runs, one vmapped program.

The runs come through the pipeline itself (``robot=sorolex_csv``: import, align, resample to
``dataset.model_hz``), the folds are ``pipeline.dynamics.cv.loro_folds`` (every run held out once)
and all fold models of all seeds train in one ``pipeline.dynamics.cv.fit_members`` program. With
several seeds the row scores their average (an ensemble) and reports the coverage of its ±2σ
band on the held-out runs; the single members' average error is reported beside it.

Appends one JSON line to ``--out`` (the command, per held-out run the model's mean / p95 mm, the
baselines on the same folds, the fold models' error on their training runs, and the averages)::

    python -m experiments.model_cv_study --tag default
    python -m experiments.model_cv_study --tag play model.play_widths_kpa=[0.25,0.5,1.0]
    python -m experiments.model_cv_study --tag ensemble5 --seeds 0,1,2,3,4
    python -m experiments.model_cv_study --report      # the table of every row so far
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.studies import append_jsonl, recorded_runs

DEFAULT_OUT = "outputs/model_cv_study/study.jsonl"


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides (model.*, dataset.*)")
    parser.add_argument("--tag", default="")
    parser.add_argument("--seeds", default="0", help="comma-separated model seeds")
    parser.add_argument("--drop-runs", type=int, default=0,
                        help="each member trains on its fold's runs less this many, drawn per "
                             "(seed, fold): an ensemble over subsets of the runs (subbagging)")
    parser.add_argument("--out", default=DEFAULT_OUT)
    parser.add_argument("--report", action="store_true", help="print the table of --out")
    return parser.parse_args(argv)


def subsampled(members: list, drop: int) -> list:
    """Each member without ``drop`` of its training runs, drawn from ``(seed, held-out run)``:
    the members of one fold see different subsets of its runs, the held-out run never."""
    from dataclasses import replace

    out = []
    for member in members:
        if drop >= len(member.train_ids):
            raise SystemExit(f"--drop-runs {drop}: a fold has only {len(member.train_ids)} "
                             "training runs")
        fold = sorted((*member.train_ids, member.held_out)).index(member.held_out)
        rng = np.random.default_rng([member.seed, fold])
        kept = rng.choice(len(member.train_ids), len(member.train_ids) - drop, replace=False)
        out.append(replace(member, train_ids=tuple(member.train_ids[i] for i in sorted(kept))))
    return out


def study_row(args: argparse.Namespace) -> dict:
    from pipeline.dynamics import cv as model_cv
    from pipeline.dynamics.scoring import LEARNED, position_errors_mm

    cfg, runs = recorded_runs("robot=sorolex_csv", *args.overrides)
    seeds = [int(s) for s in args.seeds.split(",")]
    ids = [run.run_id for run in runs]
    members = model_cv.cv_members(ids, seeds, final=False)
    if args.drop_runs:
        members = subsampled(members, args.drop_runs)
    data = cfg.dataset
    started, started_cpu = time.perf_counter(), time.process_time()
    params, _ = model_cv.fit_members(runs, members, cfg.model, window=int(data.window),
                                     stride=int(data.stride), order=str(data.order))
    train_s, train_cpu_s = time.perf_counter() - started, time.process_time() - started_cpu
    metrics = model_cv.cv_metrics(runs, members, params)
    by_id = {run.run_id: run for run in runs}
    per_run = {}
    for run_id in sorted(by_id):
        run = by_id[run_id]
        fold = [p for m, p in zip(members, params) if m.held_out == run_id]
        mean, std = model_cv.ensemble_predictions(fold, run)
        held = metrics[(metrics["split"] == "cv") & (metrics["run_id"] == run_id)]
        train = metrics[(metrics["split"] == "cv_train") & (metrics["held_out"] == run_id)
                        & (metrics["model"] == LEARNED)]

        def of(model, stat, held=held):
            return float(held.loc[held["model"] == model, stat].mean())

        per_run[run_id] = {
            **{f"model_{k}": v for k, v in position_errors_mm(mean, run.positions_m).items()},
            "member_mean_mm": of(LEARNED, "mean_mm"), "member_p95_mm": of(LEARNED, "p95_mm"),
            "linear_mean_mm": of("linear_lagged", "mean_mm"),
            "linear_p95_mm": of("linear_lagged", "p95_mm"),
            "mean_position_mean_mm": of("mean_position", "mean_mm"),
            "mean_position_p95_mm": of("mean_position", "p95_mm"),
            "train_runs_mean_mm": float(train["mean_mm"].mean()),
            "train_runs_p95_mm": float(train["p95_mm"].mean()),
            "coverage_2sigma": (model_cv.band_coverage(mean, std, run.positions_m)
                                if len(seeds) > 1 else float("nan")),
        }
    average = pd.DataFrame(per_run).T.mean().to_dict()
    return {"tag": args.tag, "command": "python -m experiments.model_cv_study " + shlex.join(
        sys.argv[1:]), "seeds": seeds, "train_s": train_s, "train_cpu_s": train_cpu_s,
        "per_run": per_run, "average": average}


def report(path: str) -> str:
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    lines = ["| row | LORO mean / p95 mm | single member | training runs | linear lagged | "
             "±2σ coverage | CPU s | command |", "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        a = row["average"]
        coverage = a.get("coverage_2sigma", float("nan"))
        lines.append(
            f"| {row['tag']} | {a['model_mean_mm']:.2f} / {a['model_p95_mm']:.2f} | "
            f"{a['member_mean_mm']:.2f} / {a['member_p95_mm']:.2f} | "
            f"{a['train_runs_mean_mm']:.2f} / {a['train_runs_p95_mm']:.2f} | "
            f"{a['linear_mean_mm']:.2f} / {a['linear_p95_mm']:.2f} | "
            f"{'' if np.isnan(coverage) else f'{coverage:.2f}'} | {row['train_cpu_s']:.0f} | "
            f"`{row['command'].removeprefix('python -m experiments.model_cv_study ')}` |")
    runs = sorted(rows[0]["per_run"]) if rows else []
    lines += ["", "| row | " + " | ".join(r.removeprefix("Step_control_") for r in runs) + " |",
              "|---|" + "---|" * len(runs)]
    for row in rows:
        cells = [f"{row['per_run'][r]['model_mean_mm']:.2f} / "
                 f"{row['per_run'][r]['model_p95_mm']:.2f}" for r in runs]
        lines.append(f"| {row['tag']} | " + " | ".join(cells) + " |")
    if rows:
        for name in ("linear", "mean_position", "train_runs"):
            cells = [f"{rows[0]['per_run'][r][f'{name}_mean_mm']:.2f} / "
                     f"{rows[0]['per_run'][r][f'{name}_p95_mm']:.2f}" for r in runs]
            lines.append(f"| {name} ({rows[0]['tag']}) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.report:
        print(report(args.out))
        return
    row = study_row(args)
    append_jsonl(args.out, row)
    a = row["average"]
    print(f"{row['tag']}: LORO {a['model_mean_mm']:.2f} / {a['model_p95_mm']:.2f} mm "
          f"(linear {a['linear_mean_mm']:.2f} / {a['linear_p95_mm']:.2f}, training runs "
          f"{a['train_runs_mean_mm']:.2f}); {row['train_cpu_s']:.0f} CPU s", flush=True)


if __name__ == "__main__":
    main()
