"""Where does the open-loop error of one fold come from? (transients vs slow drift)

Trains one fold like ``model_search.py`` (same flags), then splits the held-out error into a slow
part (30 s moving average of the error vector) and the rest, bins the error by time since the last
command change, and saves a plot of measured vs predicted positions.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from experiments.model_data import load_runs
from experiments.model_search import model_config, parse_args, split_fold
from pipeline.dynamics import scoring
from pipeline.dynamics import training as train_model


def main() -> None:
    args = parse_args()
    runs = load_runs(args.data_dir, args.hz, args.pressure)
    held_out = int(args.folds)
    train_runs, test_run = split_fold(runs, held_out)
    params, _, _ = train_model.fit(train_runs, model_config(args), window=args.window,
                                   stride=args.stride, order=args.order, progress=False)
    predicted = scoring.predict_run(params, test_run)
    error = 1000.0 * (predicted - test_run["pos"])
    kernel = np.ones(int(30 * args.hz)) / int(30 * args.hz)
    slow = np.stack([np.convolve(error[:, j], kernel, "same") for j in range(3)], axis=1)
    norm = np.linalg.norm
    print(f"{test_run['run_id']}: total {norm(error, axis=1).mean():.2f} mm, slow part "
          f"{norm(slow, axis=1).mean():.2f} mm, fast part {norm(error - slow, axis=1).mean():.2f}")
    changed = np.any(np.diff(test_run["p"], axis=0) != 0, axis=1)
    since, count = np.zeros(len(error), int), 0
    for t in range(1, len(error)):
        count = 0 if changed[t - 1] else count + 1
        since[t] = count
    for value in np.unique(since)[:8]:
        print(f"  steps since change {value}: {norm(error[since == value], axis=1).mean():.2f} mm")
    for name, train_run in zip(["in-sample " + r["run_id"] for r in train_runs], train_runs):
        print(f"  {name}: {scoring.evaluate_open_loop(params, train_run)['mean_mm']:.2f} mm")
    figure, axes = plt.subplots(3, 1, figsize=(14, 8), sharex=True)
    for j, axis in enumerate(axes):
        axis.plot(test_run["t"], 1000 * test_run["pos"][:, j], lw=0.7, label="measured")
        axis.plot(test_run["t"], 1000 * predicted[:, j], lw=0.7, label="open loop")
        axis.set_ylabel("xyz"[j] + " [mm]")
    axes[0].legend()
    axes[-1].set_xlabel("t [s]")
    out = Path("outputs/model_search") / f"diagnose_{test_run['run_id']}_{args.tag}.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=110)
    print(f"plot: {out}")


if __name__ == "__main__":
    main()
