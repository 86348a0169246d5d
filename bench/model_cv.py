"""The cross-validation protocol of fit_model: how its models train, side by side.

On the real runs (``../shared/data/sorolex``), the full ``cv`` protocol trains one model per
leave-one-run-out fold and the model on all runs (8 models for the 7 runs). Side by side, the
same steps and seeds: ``pipeline.dynamics.cv.fit_members`` (one jitted program, vmapped over the
models) on one device, the same split over the CPU's cores (one device per core,
``pipeline.infra.devices``: what fit_model runs), the all-runs model alone (what a further
member of an ensemble fits) and, with ``--sequential``, ``pipeline.dynamics.training.fit``
called once per model (each fold has other data shapes, so each compiles anew); then every fold
model is scored over its held-out run. Prints wall and CPU seconds (compilation included), the
ratios, the leave-one-run-out error (they train the same models, up to float rounding) and the
device.

    taskset -c 0,1 python -m bench.model_cv [--steps 1500] [--folds 7] [--sequential]
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
from pipeline.dynamics import cv as model_cv
from pipeline.dynamics.cv import cv_members, fit_members
from pipeline.dynamics.scoring import evaluate_open_loop
from pipeline.dynamics.training import fit
from pipeline.infra.devices import batch_split, configure_cpu_devices
from pipeline.schemas import ModelConfig
from pipeline.studies import recorded_runs


def held_out_error(runs: list[Run], members, params) -> float:
    by_id = runs_by_id(runs)
    errors = [evaluate_open_loop(p, by_id[m.held_out])["mean_mm"]
              for m, p in zip(members, params) if m.held_out]
    return float(np.mean(errors)) if errors else float("nan")  # no fold model: not scored


def main(argv: list[str] | None = None) -> pd.DataFrame:
    configure_cpu_devices(None)  # one device per core, as the entry point asks (before JAX starts)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1500, help="training steps per model")
    parser.add_argument("--folds", type=int, default=0, help="use the first N runs (0: all)")
    parser.add_argument("--sequential", action="store_true",
                        help="also fit the models one after another")
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

    def timed(protocol: str, train, scored=members) -> None:
        started, started_cpu = time.perf_counter(), time.process_time()
        params = train()
        rows.append({"protocol": protocol, "models": len(params),
                     "train_wall_s": time.perf_counter() - started,
                     "train_cpu_s": time.process_time() - started_cpu,
                     "loro_mean_mm": held_out_error(runs, scored, params)})

    def vmapped(chosen, split) -> list:
        model_cv.batch_split = split
        try:
            return fit_members(runs, chosen, settings, window=window, progress=False)[0]
        finally:
            model_cv.batch_split = batch_split

    timed("vmapped, one device", lambda: vmapped(members, lambda size: None))
    cores = len(jax.local_devices())
    timed(f"vmapped, split over {cores} devices", lambda: vmapped(members, batch_split))
    timed("the all-runs model alone", lambda: vmapped(members[-1:], batch_split), [])
    if args.sequential:
        by_id = runs_by_id(runs)
        timed("sequential (one fit per model)", lambda: [
            fit([by_id[i] for i in m.train_ids], dict(settings, seed=m.seed), window=window,
                progress=False)[0] for m in members])

    table = pd.DataFrame(rows).set_index("protocol")
    table["wall_s_per_model"] = table["train_wall_s"] / table["models"]
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), "
          f"{os.cpu_count()} CPUs visible, {len(runs)} runs, {args.steps} steps per model")
    table["wall_ratio"] = table["train_wall_s"] / table["train_wall_s"].iloc[0]
    print(table.to_string(float_format=lambda v: f"{v:.3g}"))
    return table


if __name__ == "__main__":
    main()
