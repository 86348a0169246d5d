"""A study row of the hybrid model: the calibrated twin's prediction plus a learned residual,
leave-one-run-out on the real runs.

For every fold (one run held out) the simulated arm's physics are calibrated to the six training
runs alone (``pipeline.arm.calibration``, the calibrate stage's settings, ``calibration.*``), and
every run is predicted open loop with them from the settled preload, resting where the training
runs rest (the mean of their fitted offsets: nothing of the held-out run is used). The learned
model (``model.*``, the default recipe) is then trained on the six runs' residuals, the measured
position minus that prediction, and the fold's prediction of the held-out run is the twin's plus
the residual model's, both fed the run's commands alone. All fold residual models train in one
vmapped program (``pipeline.dynamics.cv.fit_members``, each fold on its own copies of the runs).

    python -m experiments.model_hybrid [--seeds 0] [--with-plain] [--tag hybrid] [overrides ...]

With several ``--seeds`` the fold's prediction is the average of its residual models (an
ensemble); ``--with-plain`` adds the learned model alone (trained on the measured positions,
same seeds) to that average: an ensemble of the hybrid and the plain model.

Appends a row in ``experiments.model_cv_study``'s format to ``--out``, by default that study's
file (``--report`` there prints it beside the other rows); the twin's fold predictions are kept
in ``<out folder>/twin_folds.npz``
and reused when the calibration settings and runs are the same.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.data.runs import Run
from pipeline.studies import append_jsonl, recorded_runs

STUDY_FILE = "outputs/model_cv_study/study.jsonl"  # model_cv_study's rows


def twin_folds(cfg, runs: list[Run], overrides: list[str], cache: Path
               ) -> dict[str, dict[str, np.ndarray]]:
    """``{held-out run: {run: [T, 3] m}}``: the fold's calibrated twin's open-loop prediction of
    every run on the model grid (cached in ``cache``, keyed by the settings and runs);
    ``overrides``: those ``cfg`` was composed from, for the runs at the calibration rate."""
    import jax
    from omegaconf import OmegaConf

    from pipeline.arm import calibration as calib
    from pipeline.arm.sim_arm import SimParams
    from pipeline.dynamics.calibration_report import fold_weights

    settings = cfg.calibration
    ids = [run.run_id for run in runs]
    digest = hashlib.sha256(json.dumps(
        [OmegaConf.to_container(settings, resolve=True), ids, float(cfg.dataset.model_hz),
         [float(np.sum(run.positions_m)) for run in runs]], sort_keys=True).encode()
    ).hexdigest()[:12]
    if cache.is_file():
        stored = np.load(cache, allow_pickle=False)
        if str(stored["digest"]) == digest:
            return {held: {run: stored[f"{held}|{run}"] for run in ids} for held in ids}

    rate_hz, model_hz = float(settings.rate_hz), float(cfg.dataset.model_hz)
    stride = round(rate_hz / model_hz)
    _, fine = recorded_runs(*overrides, rate_hz=rate_hz, grid="clock")
    if [run.run_id for run in fine] != ids:
        raise SystemExit(f"the runs at {rate_hz} Hz are not those of the model grid")
    batch = calib.RunBatch.from_runs(fine)
    init = calib.sim_physics_values(settings.init)
    init.pop("substeps", None)
    init.pop("session_std", None)
    template = SimParams.noise_free(init, rate_hz, int(settings.substeps))
    param = calib.Parameterization.create(list(settings.fitted), init)
    _, weights = fold_weights(len(fine), leave_one_run_out=True)
    weights = weights[:-1]  # the leave-one-run-out folds only, fold i holds out run i
    started = time.perf_counter()
    result = calib.calibrate(
        template, param, init, batch, weights, num_steps=int(settings.num_steps),
        learning_rate=float(settings.learning_rate), num_restarts=int(settings.num_restarts),
        restart_std=float(settings.restart_std), key=jax.random.key(int(settings.seed)))
    rest = calib.training_mean_offsets(result.offsets, weights)
    predicted = calib.open_loop(template, param, result.z, batch, rest)  # [F, R, T, 3]
    print(f"calibrated {len(ids)} folds in {time.perf_counter() - started:.0f} s", flush=True)
    folds = {held: {run.run_id: predicted[f, r, :batch.lengths[r]][::stride][:len(run)]
                    for r, run in enumerate(runs)}
             for f, held in enumerate(ids)}
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.savez(cache, digest=np.array(digest),
             **{f"{held}|{run}": values for held, by_run in folds.items()
                for run, values in by_run.items()})
    return folds


def hybrid_row(args: argparse.Namespace) -> dict:
    from pipeline.dynamics import cv as model_cv
    from pipeline.dynamics.scoring import position_errors_mm, predict_run

    overrides = ["robot=sorolex_csv", *args.overrides]
    cfg, runs = recorded_runs(*overrides)
    ids = [run.run_id for run in runs]
    twin = twin_folds(cfg, runs, overrides, Path(args.out).parent / "twin_folds.npz")
    for held in ids:  # the predictions cover the model grid
        for run in runs:
            if len(twin[held][run.run_id]) != len(run):
                raise SystemExit(f"fold {held}: the twin's prediction of {run.run_id} is "
                                 f"shorter than the run")
    copies = [run.replace(run_id=f"{run.run_id}@{held}",
                          positions_m=(run.positions_m - twin[held][run.run_id]).astype(
                              run.positions_m.dtype))
              for held in ids for run in runs]
    seeds = [int(seed) for seed in args.seeds.split(",")]
    # (fold, kind, member): the residual models on the fold's copies, the plain ones on the runs
    members = [(held, "hybrid", model_cv.Member(tuple(f"{r}@{held}" for r in ids if r != held),
                                                f"{held}@{held}", seed))
               for seed in seeds for held in ids]
    if args.with_plain:
        members += [(held, "plain", model_cv.Member(tuple(r for r in ids if r != held), held,
                                                    seed)) for seed in seeds for held in ids]
    data = cfg.dataset
    started, started_cpu = time.perf_counter(), time.process_time()
    params, _ = model_cv.fit_members([*runs, *copies], [m for _, _, m in members], cfg.model,
                                     window=int(data.window), stride=int(data.stride),
                                     order=str(data.order))
    train_s, train_cpu_s = time.perf_counter() - started, time.process_time() - started_cpu
    by_copy = {run.run_id: run for run in copies}
    by_id = {run.run_id: run for run in runs}
    per_run = {}
    for held in ids:
        fold = [(kind, p) for (h, kind, _), p in zip(members, params, strict=True) if h == held]

        def predictions(run_id, fold=fold, held=held):
            return [predict_run(p, by_copy[f"{run_id}@{held}"]) + twin[held][run_id]
                    if kind == "hybrid" else predict_run(p, by_id[run_id]) for kind, p in fold]

        pos, held_out = by_id[held].positions_m, predictions(held)
        single = [position_errors_mm(one, pos) for one in held_out]
        errors = position_errors_mm(np.mean(held_out, axis=0), pos)
        twin_errors = position_errors_mm(twin[held][held], pos)
        train = [position_errors_mm(np.mean(predictions(r), axis=0), by_id[r].positions_m)
                 for r in ids if r != held]
        per_run[held] = {
            "model_mean_mm": errors["mean_mm"], "model_p95_mm": errors["p95_mm"],
            "member_mean_mm": float(np.mean([e["mean_mm"] for e in single])),
            "member_p95_mm": float(np.mean([e["p95_mm"] for e in single])),
            "twin_mean_mm": twin_errors["mean_mm"], "twin_p95_mm": twin_errors["p95_mm"],
            "train_runs_mean_mm": float(np.mean([e["mean_mm"] for e in train])),
            "train_runs_p95_mm": float(np.mean([e["p95_mm"] for e in train])),
            "linear_mean_mm": float("nan"), "linear_p95_mm": float("nan"),
            "coverage_2sigma": float("nan")}
    average = pd.DataFrame(per_run).T.mean().to_dict()
    return {"tag": args.tag, "command": "python -m experiments.model_hybrid " + shlex.join(
        sys.argv[1:]), "seeds": seeds, "train_s": train_s,
        "train_cpu_s": train_cpu_s, "per_run": per_run, "average": average}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides (model.*, calibration.*)")
    parser.add_argument("--tag", default="hybrid")
    parser.add_argument("--seeds", default="0", help="comma-separated model seeds")
    parser.add_argument("--with-plain", action="store_true",
                        help="average the hybrid with the learned model alone (same seeds)")
    parser.add_argument("--out", default=STUDY_FILE)
    args = parser.parse_args(argv)
    row = hybrid_row(args)
    append_jsonl(args.out, row)
    for held, figures in row["per_run"].items():
        print(f"{held}: hybrid {figures['model_mean_mm']:.2f} / {figures['model_p95_mm']:.2f} mm,"
              f" twin alone {figures['twin_mean_mm']:.2f} / {figures['twin_p95_mm']:.2f}, "
              f"training runs {figures['train_runs_mean_mm']:.2f}")
    a = row["average"]
    print(f"{row['tag']}: LORO {a['model_mean_mm']:.2f} / {a['model_p95_mm']:.2f} mm (twin alone "
          f"{a['twin_mean_mm']:.2f} / {a['twin_p95_mm']:.2f}, training runs "
          f"{a['train_runs_mean_mm']:.2f}); {row['train_cpu_s']:.0f} CPU s", flush=True)


if __name__ == "__main__":
    main()
