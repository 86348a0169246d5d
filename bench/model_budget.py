"""Dynamics model: our default configuration next to the paper's at the same wall-clock budget.

On the real runs (``../shared/data/sorolex``; a fixed split by run), each configuration trains for
the same wall-clock budget (compilation included), then its open-loop error over each entire
held-out run is measured. Prints training steps/s, steps done and held-out error (mm), with the
ratios default / paper, and the device JAX ran on.

    python -m bench.model_budget --budget 120 [--test-runs Step_control_17_10_12_20,...]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import numpy as np
import pandas as pd

from pipeline.dynamics.scoring import evaluate_open_loop
from pipeline.dynamics.training import fit
from pipeline.schemas import ModelConfig
from pipeline.studies import recorded_runs

CHUNK = 10  # training steps between checks of the clock
DEFAULT_TEST = ["Step_control_17_10_11_29", "Step_control_17_10_12_38"]


def configurations() -> dict[str, tuple[dict, float, int]]:
    """name -> (model settings, model rate in Hz, window in model steps)."""
    default = {k: v for k, v in vars(ModelConfig()).items()}
    paper = {**default, "hidden": 1024, "layers": 1, "head": [], "batch_size": 64,
             "learning_rate": 1e-3, "lr_schedule": "constant", "warmup_steps": 0,
             "num_steps": 200_000,
             "condition_on_initial_pose": False, "predict_displacement": False,
             "max_grad_norm": 0.0}
    return {"default": (default, 10.0, 128), "paper": (paper, 100.0, 512)}


def recordings(data_dir: Path) -> tuple[str, ...]:
    """The overrides that read the recordings in ``data_dir`` (``robot=sorolex_csv``)."""
    return ("robot=sorolex_csv", f"robot.data_dir={data_dir}")


def run_one(name, settings, model_hz, window, data_dir, test_ids, budget_s):
    _, runs = recorded_runs(*recordings(data_dir), rate_hz=model_hz, grid="clock")
    train = [r for r in runs if r.run_id not in test_ids]
    test = [r for r in runs if r.run_id in test_ids]
    # Each recipe trains until its own step count or the budget (compilation included) is spent,
    # checking the clock every CHUNK steps.
    settings = dict(settings, eval_every=CHUNK, checkpoint_every=CHUNK)
    started = time.perf_counter()
    params, _, losses = fit(train, settings, window=window, progress=False,
                            time_budget_s=budget_s)
    wall = time.perf_counter() - started
    steps = len(losses)
    errors = [evaluate_open_loop(params, run) for run in test]
    return {
        "config": name, "units": settings["hidden"], "model_hz": model_hz, "window": window,
        "batch": settings["batch_size"], "steps_per_s": steps / wall, "steps": steps,
        "train_wall_s": wall, "held_out_mean_mm": float(np.mean([e["mean_mm"] for e in errors])),
        "held_out_p95_mm": float(np.mean([e["p95_mm"] for e in errors])),
    }


def main(argv: list[str] | None = None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budget", type=float, default=120.0, help="seconds per configuration")
    parser.add_argument("--data-dir", type=Path, default=Path(os.environ.get(
        "SOROLEX_DIR", Path(__file__).resolve().parents[1].parent / "shared/data/sorolex")))
    parser.add_argument("--test-runs", default=",".join(DEFAULT_TEST))
    args = parser.parse_args(argv)
    test_ids = args.test_runs.split(",")
    rows = [run_one(name, *spec, args.data_dir, test_ids, args.budget)
            for name, spec in configurations().items()]
    table = pd.DataFrame(rows).set_index("config")
    ratio = table.loc["default", ["steps_per_s", "held_out_mean_mm", "held_out_p95_mm"]] / \
        table.loc["paper", ["steps_per_s", "held_out_mean_mm", "held_out_p95_mm"]]
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), budget "
          f"{args.budget:.0f} s per configuration, held-out runs {test_ids}")
    print(table.to_string(float_format=lambda v: f"{v:.3g}"))
    print("ratio default / paper:", ", ".join(f"{k} {v:.3g}" for k, v in ratio.items()))
    return table


if __name__ == "__main__":
    main()
