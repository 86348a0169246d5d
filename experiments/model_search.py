"""Leave-one-run-out evaluation of the learned dynamics on the real runs.

For every selected fold the held-out run is predicted open loop over its whole length from its
first observed pose; the two baselines are computed the same way. One JSON line per fold is
appended to ``--out`` and a table is printed at the end.

Example (one CPU core)::

    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \\
    taskset -c 1 .venv/bin/python -m experiments.model_search \\
        --data-dir ../shared/data/sorolex --hz 10 --window 128 --hidden 64 --steps 1500 \\
        --folds all --out outputs/model_search/default.jsonl
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.model_data import load_runs
from pipeline.config import sorolex_dir
from pipeline.dynamics import scoring
from pipeline.dynamics import training as train_model


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data-dir", default=str(sorolex_dir()))
    parser.add_argument("--hz", type=float, default=10.0, help="model rate")
    parser.add_argument("--pressure", default="interval_mean", choices=["interval_mean", "sample"])
    parser.add_argument("--window", type=int, default=128)
    parser.add_argument("--stride", type=int, default=1)
    parser.add_argument("--order", default="permuted", choices=["permuted", "sequential"])
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--layers", type=int, default=1)
    parser.add_argument("--head", default="", help="comma-separated widths, e.g. 64,64")
    parser.add_argument("--condition", type=int, default=0, help="condition_on_initial_pose")
    parser.add_argument("--displacement", type=int, default=0, help="predict_displacement")
    parser.add_argument("--reference", default="run_start", choices=["run_start", "window_start"])
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--schedule", default="cosine", choices=["constant", "cosine"])
    parser.add_argument("--warmup", type=int, default=100)
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--folds", default="all", help="'all' or comma-separated run indices")
    parser.add_argument("--lags", type=int, default=20, help="linear baseline lags (model steps)")
    parser.add_argument("--train-runs", type=int, default=0,
                        help="train on this many of the other runs (a seeded random subset; "
                             "0: all), to see how the held-out error depends on the data")
    parser.add_argument("--tag", default="")
    parser.add_argument("--out", default="outputs/model_search/results.jsonl")
    parser.add_argument("--progress", type=int, default=0)
    parser.add_argument("--members", type=int, default=5, help="model_ensemble.py: models per fold")
    parser.add_argument("--every", type=int, default=100, help="model_curve.py: steps per score")
    return parser.parse_args(argv)


def model_config(args: argparse.Namespace) -> dict:
    return {
        "hidden": args.hidden,
        "layers": args.layers,
        "head": [int(w) for w in args.head.split(",") if w],
        "condition_on_initial_pose": bool(args.condition),
        "predict_displacement": bool(args.displacement),
        "batch_size": args.batch,
        "learning_rate": args.lr,
        "lr_schedule": args.schedule,
        "warmup_steps": args.warmup,
        "num_steps": args.steps,
        "eval_every": args.steps,
        "checkpoint_every": args.steps,
        "seed": args.seed,
        "reference_pose": args.reference,
    }


def split_fold(runs: list, held_out: int) -> tuple[list, dict]:
    """(the other runs, the held-out run) of one leave-one-run-out fold."""
    return [run for i, run in enumerate(runs) if i != held_out], runs[held_out]


def subset_runs(train_runs: list, count: int, seed: int) -> list:
    """``count`` of ``train_runs`` drawn without replacement (all of them when count is 0)."""
    if count <= 0 or count >= len(train_runs):
        return train_runs
    chosen = np.random.default_rng(seed).choice(len(train_runs), size=count, replace=False)
    return [train_runs[i] for i in sorted(chosen)]


def run_fold(runs: list, held_out: int, args: argparse.Namespace) -> dict:
    train_runs, test_run = split_fold(runs, held_out)
    train_runs = subset_runs(train_runs, args.train_runs, args.seed * 1000 + held_out)
    started, started_cpu = time.perf_counter(), time.process_time()
    params, _, _ = train_model.fit(
        train_runs,
        model_config(args),
        window=args.window,
        stride=args.stride,
        order=args.order,
        progress=bool(args.progress),
    )
    train_seconds = time.perf_counter() - started
    train_cpu_seconds = time.process_time() - started_cpu
    model = scoring.evaluate_open_loop(params, test_run)
    mean_baseline = scoring.baseline_mean_position(train_runs, test_run)
    linear_baseline = scoring.baseline_linear_lagged(train_runs, test_run, args.lags)
    return {
        "tag": args.tag,
        "held_out": test_run["run_id"],
        "train_runs": [run["run_id"] for run in train_runs],
        "mean_mm": model["mean_mm"],
        "p95_mm": model["p95_mm"],
        "train_s": train_seconds,
        "train_cpu_s": train_cpu_seconds,
        "baseline_mean_mm": mean_baseline["mean_mm"],
        "baseline_mean_p95_mm": mean_baseline["p95_mm"],
        "baseline_linear_mm": linear_baseline["mean_mm"],
        "baseline_linear_p95_mm": linear_baseline["p95_mm"],
        "hz": args.hz,
        "pressure_resampling": args.pressure,
        "window": args.window,
        "order": args.order,
        **model_config(args),
    }


def load_folds(args: argparse.Namespace) -> tuple[list, list[int], Path]:
    """The runs, the indices of the runs to hold out in turn, and the (created) output path."""
    runs = load_runs(args.data_dir, args.hz, args.pressure)
    folds = range(len(runs)) if args.folds == "all" else [int(i) for i in args.folds.split(",")]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    return runs, list(folds), out


def main(argv=None) -> None:
    args = parse_args(argv)
    runs, folds, out = load_folds(args)
    rows = []
    for held_out in folds:
        row = run_fold(runs, held_out, args)
        rows.append(row)
        with open(out, "a") as file:
            file.write(json.dumps(row) + "\n")
        print(
            f"{row['held_out']}: model {row['mean_mm']:.2f}/{row['p95_mm']:.2f} mm  "
            f"linear {row['baseline_linear_mm']:.2f}  mean {row['baseline_mean_mm']:.2f}  "
            f"({row['train_s']:.0f} s wall, {row['train_cpu_s']:.0f} s CPU)",
            flush=True,
        )
    table = pd.DataFrame(rows)[
        ["held_out", "mean_mm", "p95_mm", "baseline_linear_mm", "baseline_linear_p95_mm",
         "baseline_mean_mm", "baseline_mean_p95_mm", "train_s", "train_cpu_s"]
    ]
    print(table.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    print(f"average over folds: model {np.mean(table.mean_mm):.2f} mm mean, "
          f"{np.mean(table.p95_mm):.2f} mm p95")


if __name__ == "__main__":
    main()
