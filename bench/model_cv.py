"""The cross-validation protocol of fit_model: all models in one vmapped program vs one by one.

On the real runs (``../shared/data/sorolex``), the full ``cv`` protocol trains one model per
leave-one-run-out fold and the model on all runs (8 models for the 7 runs). Side by side:
``pipeline.dynamics.cv.fit_members`` (one jitted program, vmapped over the models) and
``pipeline.dynamics.training.fit`` called once per model (each fold has other data shapes, so each
compiles anew), the same steps and seeds; then every model is scored over its held-out run.
Prints wall and CPU seconds (compilation included), the ratio, the leave-one-run-out error of
both (they train the same models, up to float rounding) and the device.

    taskset -c 0,1 python -m bench.model_cv [--steps 1500] [--folds 7]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import numpy as np
import pandas as pd

from pipeline.data.runs import Run, runs_by_id
from pipeline.dynamics.cv import cv_members, fit_members
from pipeline.dynamics.scoring import evaluate_open_loop
from pipeline.dynamics.training import fit
from pipeline.schemas import ModelConfig
from pipeline.studies import recorded_runs


def held_out_error(runs: list[Run], members, params) -> float:
    by_id = runs_by_id(runs)
    return float(np.mean([evaluate_open_loop(p, by_id[m.held_out])["mean_mm"]
                          for m, p in zip(members, params) if m.held_out]))


def main(argv: list[str] | None = None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1500, help="training steps per model")
    parser.add_argument("--folds", type=int, default=0, help="use the first N runs (0: all)")
    parser.add_argument("--data-dir", type=Path, default=Path(os.environ.get(
        "SOROLEX_DIR", Path(__file__).resolve().parents[1].parent / "shared/data/sorolex")))
    args = parser.parse_args(argv)
    _, runs = recorded_runs("robot=sorolex_csv", f"robot.data_dir={args.data_dir}",
                            rate_hz=10.0, grid="clock")
    if args.folds:
        runs = runs[: args.folds]
    settings = {**vars(ModelConfig()), "num_steps": args.steps, "eval_every": args.steps,
                "checkpoint_every": args.steps}
    window = 128
    members = cv_members([run.run_id for run in runs], final=True)
    rows = []

    started, started_cpu = time.perf_counter(), time.process_time()
    params, _ = fit_members(runs, members, settings, window=window, progress=False)
    rows.append({"protocol": "vmapped (one program)", "models": len(members),
                 "train_wall_s": time.perf_counter() - started,
                 "train_cpu_s": time.process_time() - started_cpu,
                 "loro_mean_mm": held_out_error(runs, members, params)})

    by_id = runs_by_id(runs)
    started, started_cpu = time.perf_counter(), time.process_time()
    sequential = [fit([by_id[i] for i in m.train_ids], dict(settings, seed=m.seed),
                      window=window, progress=False)[0] for m in members]
    rows.append({"protocol": "sequential (one fit per model)", "models": len(members),
                 "train_wall_s": time.perf_counter() - started,
                 "train_cpu_s": time.process_time() - started_cpu,
                 "loro_mean_mm": held_out_error(runs, members, sequential)})

    table = pd.DataFrame(rows).set_index("protocol")
    table["wall_s_per_model"] = table["train_wall_s"] / table["models"]
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), "
          f"{os.cpu_count()} CPUs visible, {len(runs)} runs, {args.steps} steps per model")
    print(table.to_string(float_format=lambda v: f"{v:.3g}"))
    ratio = table["train_wall_s"].iloc[1] / table["train_wall_s"].iloc[0]
    print(f"sequential / vmapped wall time: {ratio:.2f}")
    return table


if __name__ == "__main__":
    main()
