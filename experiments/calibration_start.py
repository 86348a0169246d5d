"""Where a calibration's runs begin: at the recording's first frame, or later (after the hold).

Each of the paper's runs opens with its preload held 17 s while the arm is still coming to rest
(it rises 1.1-1.6 mm). ``stage=calibrate`` drives every run from the settled preload, so a fit
from the first frame also fits that settling, which the simulator cannot show. This study fits
the calibration (the stage's settings, every leave-one-run-out fold and the fit on all runs)
once per ``--starts`` value (``calibration.start_s``) and scores every fit on the same stretch of
each run, from ``--score-from`` s on (started settled there: during the hold the command does not
change, so a simulator started at the first frame is settled there too). Prints per held-out run
the open-loop error of each fit, their means, and where the fit on all runs rests against where
the recordings are at ``--score-from``; writes each fit's ``conf/robot`` file (the stage's
``robot_sim.yaml``) and the table to ``--out``; with ``--fold-twins`` also each leave-one-run-out
fit as a twin (``<out>/twin_start_<s>_without_<run>/physics.json``, resting where its training
runs rest), for ``evaluation.twins``: how far the twin is known from the runs.

Usage (the runs through ``stage=align`` with the same overrides, reused when there)::

    python -m experiments.calibration_start [--starts 0 16.5] [--score-from 16.5] \\
        [--out outputs/calibration_start] [--fold-twins] [-- override ...]
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.arm import calibration as calib
from pipeline.dynamics import calibration_report as report
from pipeline.studies import recorded_runs


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--robot", default="sorolex_csv")
    parser.add_argument("--starts", type=float, nargs="+", default=[0.0, 16.5])
    parser.add_argument("--score-from", type=float, default=16.5)
    parser.add_argument("--out", default="outputs/calibration_start")
    parser.add_argument("--fold-twins", action="store_true",
                        help="also write each leave-one-run-out fit's physics as a twin folder")
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    cfg, runs = recorded_runs(f"robot={args.robot}", *args.overrides,
                              rate_hz=None, grid="clock")
    rate_hz = float(cfg.calibration.rate_hz)
    model_hz = float(cfg.dataset.model_hz)
    stride = round(rate_hz / model_hz)
    _, fine = recorded_runs(f"robot={args.robot}", *args.overrides, rate_hz=rate_hz,
                            grid="clock")
    score_runs = [r.after(args.score_from) for r in fine]
    score_model_runs = [r.after(args.score_from) for r in runs]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    recorded_rest = 1e3 * np.mean([r.positions_m[0] for r in score_runs], axis=0)
    rows, rests = [], {}
    for start in args.starts:
        fit = report.fit_runs([r.after(start) for r in fine], cfg.calibration)
        _, metrics = report.scored(fit, score_runs, score_model_runs, stride)
        metrics["start_s"] = start
        rows.append(metrics)
        (out / f"robot_sim_start_{start:g}.yaml").write_text(
            report.robot_yaml(fit.physics(), [r.run_id for r in fine]))
        if args.fold_twins:
            for fold in fit.folds[:-1]:  # each leave-one-run-out fit, a twin for evaluation.twins
                twin = out / f"twin_start_{start:g}_without_{fine[fold].run_id[-5:]}"
                twin.mkdir(exist_ok=True)
                (twin / "physics.json").write_text(json.dumps(
                    {"physics": fit.physics(fold),
                     "runs": [r.run_id for i, r in enumerate(fine) if i != fold]}, indent=1))
        last = fit.result.z[-1:]
        rest = calib.rest_poses(fit.template, fit.param, last, score_runs[0].pressures_kpa[:1])
        rests[start] = 1e3 * (rest[0, 0] + fit.result.offsets[-1].mean(0))
    table = pd.concat(rows, ignore_index=True)
    table.to_parquet(out / "metrics.parquet")
    calibrated = table[table["model"] == "sim_calibrated"]
    print(f"open-loop error from {args.score_from:g} s into each run on "
          f"(mm, {model_hz:g} Hz grid)")
    print("held-out run | " + " | ".join(f"start {s:g} s mean / p95" for s in args.starts))
    print("--- | " + " | ".join("---" for _ in args.starts))
    test = calibrated[calibrated["split"] == "test"]
    for run_id, group in test.groupby("run_id", sort=True):
        cells = [group[group["start_s"] == s].iloc[0] for s in args.starts]
        print(f"{run_id} | " + " | ".join(f"{c.mean_mm:.2f} / {c.p95_mm:.2f}" for c in cells))
    for split in ("test", "train"):
        part = calibrated[calibrated["split"] == split]
        cells = [part[part["start_s"] == s] for s in args.starts]
        print(f"**mean, {split}** | " + " | ".join(
            f"{c.mean_mm.mean():.2f} / {c.p95_mm.mean():.2f}" for c in cells))
    print(f"\nwhere the recordings are at {args.score_from:g} s (mean of the runs): "
          f"{np.round(recorded_rest.astype(float), 2).tolist()} mm")
    for start, rest in rests.items():
        print(f"where the fit from {start:g} s rests (all runs): {np.round(rest.astype(float), 2).tolist()} mm, "
              f"{np.linalg.norm(rest - recorded_rest):.2f} mm away")
    (out / "rests.json").write_text(json.dumps(
        {"recorded_mm": recorded_rest.tolist(),
         "fits_mm": {f"{s:g}": r.tolist() for s, r in rests.items()}}, indent=1))


if __name__ == "__main__":
    main()
