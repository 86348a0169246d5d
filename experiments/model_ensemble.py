"""Does averaging several LSTMs (different seeds) or blending with the linear model help?

Leave-one-run-out like ``model_search.py`` (same flags). Per fold it trains ``--members`` models
(seeds ``seed, seed + 1, ...``), predicts the held-out run open loop with each, and reports the
mean error of the members, of their average, and of the average blended half-and-half with the
linear lagged-pressure model. One JSON line per fold is appended to ``--out``.

Example::

    .venv/bin/python -m experiments.model_ensemble --members 5 --folds 4,6 \\
        --out outputs/model_search/ensemble.jsonl
"""

from __future__ import annotations

import json
import time

import numpy as np
import pandas as pd

from experiments.model_search import load_folds, model_config, parse_args, split_fold
from pipeline.dynamics import scoring
from pipeline.dynamics import training as train_model


def main(argv=None) -> None:
    args = parse_args(argv)
    members = args.members
    runs, folds, out = load_folds(args)
    rows = []
    for held_out in folds:
        train_runs, test_run = split_fold(runs, held_out)
        started = time.process_time()
        predictions = []
        for member in range(members):
            config = {**model_config(args), "seed": args.seed + member}
            params, _, _ = train_model.fit(train_runs, config, window=args.window,
                                           stride=args.stride, order=args.order, progress=False)
            predictions.append(scoring.predict_run(params, test_run))
        cpu_seconds = time.process_time() - started
        truth = test_run["pos"]
        errors = [scoring.position_errors_mm(p, truth) for p in predictions]
        average = np.mean(predictions, axis=0)
        ensemble = scoring.position_errors_mm(average, truth)
        linear = scoring.predict_linear_lagged(train_runs, test_run, args.lags)
        blend = scoring.position_errors_mm(0.5 * average + 0.5 * linear, truth)
        row = {
            "tag": args.tag, "held_out": test_run["run_id"], "members": members,
            "member_mean_mm": float(np.mean([e["mean_mm"] for e in errors])),
            "member_best_mm": float(np.min([e["mean_mm"] for e in errors])),
            "ensemble_mean_mm": ensemble["mean_mm"], "ensemble_p95_mm": ensemble["p95_mm"],
            "blend_linear_mean_mm": blend["mean_mm"], "blend_linear_p95_mm": blend["p95_mm"],
            "train_cpu_s": cpu_seconds, **model_config(args),
        }
        rows.append(row)
        with open(out, "a") as file:
            file.write(json.dumps(row) + "\n")
        print(f"{row['held_out']}: members {row['member_mean_mm']:.2f} (best "
              f"{row['member_best_mm']:.2f}), ensemble {row['ensemble_mean_mm']:.2f}/"
              f"{row['ensemble_p95_mm']:.2f}, + linear {row['blend_linear_mean_mm']:.2f}/"
              f"{row['blend_linear_p95_mm']:.2f} mm", flush=True)
    table = pd.DataFrame(rows)
    print(table[["held_out", "member_mean_mm", "ensemble_mean_mm", "ensemble_p95_mm",
                 "blend_linear_mean_mm", "blend_linear_p95_mm"]].to_string(
        index=False, float_format=lambda v: f"{v:.2f}"))


if __name__ == "__main__":
    main()
