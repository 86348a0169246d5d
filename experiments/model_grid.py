"""Does a command-locked model grid improve the learned dynamics' held-out accuracy?

Leave-one-run-out over the 7 runs of ``shared/data/sorolex``, loaded as the stages load them
(``robot=sorolex_csv`` through ``stage=align``, then the runs at ``hz`` on ``grid``:
:func:`pipeline.studies.recorded_runs`), trained with ``training.fit`` and scored with
``scoring.evaluate_open_loop`` on the held-out run's own grid. For comparability across
grids the held-out prediction is also linearly interpolated onto the held-out run's regular
10 Hz clock grid and scored there against the clock-grid positions (``clock10_*`` fields), so
every variant is then scored at the same time points.

Usage::

    python -m experiments.model_grid run --variant cmd10 [--folds 12_20 11_29 ...]
    python -m experiments.model_grid table

One JSON line per (variant, fold) is appended to ``outputs/model_grid/results.jsonl``.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.studies import recorded_runs

OUT = Path("outputs/model_grid/results.jsonl")

DEFAULT_MODEL = dict(
    name="lstm", hidden=64, layers=1, head=[], condition_on_initial_pose=False,
    predict_displacement=False, batch_size=32, learning_rate=3e-3, lr_schedule="cosine",
    warmup_steps=100, final_lr_fraction=0.05, max_grad_norm=1.0, num_steps=1500,
    eval_every=250, checkpoint_every=500, seed=0, reference_pose="run_start",
)

# variant -> (grid, model_hz, window, model overrides)
VARIANTS = {
    "clock10": ("clock", 10.0, 128, {}),
    "cmd10": ("commands", 10.0, 128, {}),
    "cmd20": ("commands", 20.0, 256, {}),
    "clock20": ("clock", 20.0, 256, {}),  # control for cmd20: same rate, regular grid
    "cmd10_h128_s3000": ("commands", 10.0, 128, {"hidden": 128, "num_steps": 3000}),
    "cmd20_h128_s3000": ("commands", 20.0, 256, {"hidden": 128, "num_steps": 3000}),
}

PUBLISHED_CLOCK10 = {  # mean mm per held-out run, from the brief (not measured here)
    "11_15": 3.90, "11_29": 2.52, "11_41": 2.88, "12_03": 2.32, "12_20": 3.16,
    "12_29": 3.34, "12_38": 3.53,
}


def fold_id(run_id: str) -> str:
    return "_".join(run_id.split("_")[-2:])


def run_variant(variant: str, folds: list[str] | None, seed: int | None = None) -> None:
    from pipeline.dynamics.scoring import (
        baseline_linear_lagged,
        evaluate_open_loop,
        position_errors_mm,
        predict_run,
    )
    from pipeline.dynamics.training import fit

    grid, hz, window, overrides = VARIANTS[variant]
    model_cfg = {**DEFAULT_MODEL, **overrides}
    if seed is not None:  # recorded as its own variant, e.g. "cmd10_seed1"
        model_cfg["seed"] = seed
        variant = f"{variant}_seed{seed}"
    runs = recorded_runs("robot=sorolex_csv", rate_hz=hz, grid=grid)[1]
    clock_runs = {r.run_id: r for r in recorded_runs("robot=sorolex_csv", rate_hz=10.0,
                                                      grid="clock")[1]}
    order = folds or [fold_id(r.run_id) for r in runs]
    OUT.parent.mkdir(parents=True, exist_ok=True)
    for fold in order:
        held = next(r for r in runs if fold_id(r.run_id) == fold)
        train = [r for r in runs if r is not held]
        wall0, cpu0 = time.time(), time.process_time()
        params, _, losses = fit(train, model_cfg, window=window, progress=False)
        wall_fit, cpu_fit = time.time() - wall0, time.process_time() - cpu0
        lstm = evaluate_open_loop(params, held)
        # Same model's prediction, interpolated onto the held-out run's 10 Hz clock grid.
        clock = clock_runs[held.run_id]
        predicted = predict_run(params, held)
        on_clock = np.stack([np.interp(clock.times_s, held.times_s, predicted[:, j])
                             for j in range(3)], axis=1)
        lstm_clock10 = position_errors_mm(on_clock, clock.positions_m)
        linear = baseline_linear_lagged(train, held)  # 30 lags (library default)
        linear_2s = baseline_linear_lagged(train, held, num_lags=round(2.0 * hz))
        row = {
            "variant": variant, "grid": grid, "model_hz": hz, "window": window,
            "fold": fold, "held_out": held.run_id, "held_out_steps": len(held),
            "train_steps_total": int(sum(len(r) for r in train)),
            "model": model_cfg,
            "mean_mm": lstm["mean_mm"], "p95_mm": lstm["p95_mm"],
            "clock10_mean_mm": lstm_clock10["mean_mm"], "clock10_p95_mm": lstm_clock10["p95_mm"],
            "linear30_mean_mm": linear["mean_mm"], "linear30_p95_mm": linear["p95_mm"],
            "linear2s_lags": round(2.0 * hz),
            "linear2s_mean_mm": linear_2s["mean_mm"], "linear2s_p95_mm": linear_2s["p95_mm"],
            "final_train_loss": float(losses["train_loss"].iloc[-1]),
            "fit_wall_s": wall_fit, "fit_cpu_s": cpu_fit,
            "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "finished": time.strftime("%Y-%m-%d %H:%M:%S"),
        }
        with OUT.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(f"{variant} {fold}: {lstm['mean_mm']:.2f}/{lstm['p95_mm']:.2f} mm "
              f"(on clock10 {lstm_clock10['mean_mm']:.2f}/{lstm_clock10['p95_mm']:.2f}; "
              f"linear30 {linear['mean_mm']:.2f}) fit {wall_fit:.0f} s wall, {cpu_fit:.0f} s cpu",
              flush=True)


def table() -> None:
    if not OUT.exists():
        print("no results yet")
        return
    rows = [json.loads(line) for line in OUT.read_text().splitlines() if line.strip()]
    df = pd.DataFrame(rows).drop_duplicates(["variant", "fold"], keep="last")
    present = set(df["variant"])
    names = [v for v in VARIANTS if v in present] + sorted(present - set(VARIANTS))
    for variant in names:
        sub = df[df["variant"] == variant].sort_values("fold")
        print(f"\n## {variant}  (grid={sub['grid'].iloc[0]}, {sub['model_hz'].iloc[0]:g} Hz, "
              f"window {sub['window'].iloc[0]}, hidden {sub['model'].iloc[0]['hidden']}, "
              f"{sub['model'].iloc[0]['num_steps']} steps)")
        print("| fold | LSTM mean/p95 (own grid) | LSTM mean/p95 (on clock 10 Hz pts) | "
              "linear 30 lags | linear 2 s lags | published clock10 mean | fit cpu s | fit wall s |")
        print("|---|---|---|---|---|---|---|---|")
        for _, r in sub.iterrows():
            print(f"| {r['fold']} | {r['mean_mm']:.2f} / {r['p95_mm']:.2f} | "
                  f"{r['clock10_mean_mm']:.2f} / {r['clock10_p95_mm']:.2f} | "
                  f"{r['linear30_mean_mm']:.2f} / {r['linear30_p95_mm']:.2f} | "
                  f"{r['linear2s_mean_mm']:.2f} / {r['linear2s_p95_mm']:.2f} | "
                  f"{PUBLISHED_CLOCK10.get(r['fold'], float('nan')):.2f} | "
                  f"{r['fit_cpu_s']:.0f} | {r['fit_wall_s']:.0f} |")
        m = sub.mean(numeric_only=True)
        pub = np.mean([PUBLISHED_CLOCK10[f] for f in sub["fold"] if f in PUBLISHED_CLOCK10])
        print(f"| **avg ({len(sub)} folds)** | {m['mean_mm']:.2f} / {m['p95_mm']:.2f} | "
              f"{m['clock10_mean_mm']:.2f} / {m['clock10_p95_mm']:.2f} | "
              f"{m['linear30_mean_mm']:.2f} / {m['linear30_p95_mm']:.2f} | "
              f"{m['linear2s_mean_mm']:.2f} / {m['linear2s_p95_mm']:.2f} | {pub:.2f} | "
              f"{m['fit_cpu_s']:.0f} | {m['fit_wall_s']:.0f} |")


def main() -> None:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="cmd", required=True)
    run = sub.add_parser("run")
    run.add_argument("--variant", choices=sorted(VARIANTS), required=True)
    run.add_argument("--folds", nargs="*", help="e.g. 12_20 11_29 (default: all 7)")
    run.add_argument("--seed", type=int, default=None, help="override the model seed (default 0)")
    sub.add_parser("table")
    args = parser.parse_args()
    if args.cmd == "run":
        run_variant(args.variant, args.folds, args.seed)
    else:
        table()


if __name__ == "__main__":
    main()
