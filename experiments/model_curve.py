"""Held-out open-loop error along training, for every fold (does the model overfit?).

Leave-one-run-out like ``model_search.py`` (same flags); the held-out run is scored every
``--every`` steps while the model trains, and one line per fold is printed: ``step:mean_mm``.

Example::

    .venv/bin/python experiments/model_curve.py --folds all --every 100
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments.model_search import load_folds, model_config, parse_args, split_fold
from pipeline.dynamics import training as train_model


def main(argv=None) -> None:
    args = parse_args(argv)
    runs, folds, _ = load_folds(args)
    for held_out in folds:
        train_runs, test_run = split_fold(runs, held_out)
        _, _, table = train_model.fit(
            train_runs, {**model_config(args), "eval_every": args.every}, window=args.window,
            stride=args.stride, order=args.order, val_runs=[test_run], progress=False)
        scored = table.dropna(subset=["val_mean_mm"])
        print(test_run["run_id"], " ".join(
            f"{int(step)}:{error:.2f}" for step, error in zip(scored.step, scored.val_mean_mm)),
            flush=True)


if __name__ == "__main__":
    main()
