"""Session context: how much of a held-out run's first seconds buys the forward model.

Leave-one-run-out on the recorded runs (``robot=sorolex_csv``): every run is held out once, its
fold model (trained on the other runs, the default recipe, one vmapped ``fit_members`` program)
is given the first ``T`` seconds of the held-out run (commands and measured positions) and
predicts the rest of it open loop through each mechanism of
:mod:`pipeline.dynamics.adaptation`; the linear lagged baseline is refitted on the same
context. Errors (mean / p95 mm) over two "rests": from ``--common-from`` seconds on for every
``T`` (the same samples for all ``T``) and from ``T`` on.

Fold models are trained once and cached (``--cache``, one ``save_dynamics`` file per held-out
run); later calls reuse them::

    python -m experiments.session_context --cache outputs/session_context/folds
    python -m experiments.session_context --cache ... --seeds 0,1   # members per fold
    python -m experiments.session_context --report               # the table of --out

With ``--latent-dim d`` the fold models train with a learned session latent
(:mod:`pipeline.dynamics.session_latent`, its own ``--cache``) and the ``latent`` mechanism
infers each held-out run's latent from its context; ``--mechanisms`` picks the mechanisms
scored (default: all that apply)::

    python -m experiments.session_context --latent-dim 4 --cache outputs/session_context/latent4 \
        --mechanisms model,latent,offset
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import logging
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.dynamics.adaptation import AdaptationSettings
from pipeline.dynamics.session_latent import DEFAULT_PRIOR, SessionLatentSettings

DEFAULT_OUT = "outputs/session_context/study.jsonl"
DEFAULT_CACHE = "outputs/session_context/folds"

log = logging.getLogger(__name__)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides (model.*, dataset.*)")
    parser.add_argument("--tag", default="")
    parser.add_argument("--seeds", default="0", help="comma-separated model seeds")
    parser.add_argument("--cache", default=DEFAULT_CACHE, help="folder of the fold models")
    parser.add_argument("--fit-only", action="store_true", help="train and cache, no scoring")
    parser.add_argument("--context-s", default="0,10,30,60,all",
                        help="context lengths [s]; all: the whole run (in-sample)")
    parser.add_argument("--common-from", type=float, default=60.0,
                        help="the common rest starts here [s]")
    parser.add_argument("--out", default=DEFAULT_OUT)
    parser.add_argument("--report", action="store_true", help="print the table of --out")
    parser.add_argument("--latent-dim", type=int, default=0,
                        help="train the fold models with a session latent of this dimension")
    parser.add_argument("--latent-prior", type=float, default=DEFAULT_PRIOR,
                        help="the session latent's prior weight (training and inference)")
    parser.add_argument("--latent-steps", type=int, default=300, help="Adam steps inferring z")
    parser.add_argument("--latent-lr", type=float, default=0.05, help="their step size")
    parser.add_argument("--mechanisms", default="",
                        help="comma-separated mechanisms to score (default: all that apply)")
    return parser.parse_args(argv)


def latent_settings(args) -> SessionLatentSettings | None:
    return (SessionLatentSettings(dim=args.latent_dim, prior=args.latent_prior)
            if args.latent_dim else None)


def mechanisms(args) -> dict:
    """The mechanisms scored: ``--mechanisms`` or all that apply; ``latent`` only for models
    trained with a session latent."""
    chosen = dict(MECHANISMS)
    if args.latent_dim:
        chosen["latent"] = AdaptationSettings(mechanism="latent", steps=args.latent_steps,
                                              learning_rate=args.latent_lr,
                                              latent_prior=args.latent_prior)
        chosen["latent_mean"] = dataclasses.replace(chosen["latent"],
                                                    latent_center="training_mean")
    if args.mechanisms:
        names = args.mechanisms.split(",")
        unknown = [name for name in names if name not in chosen]
        if unknown:
            raise SystemExit(f"--mechanisms: unknown {unknown}; known: {sorted(chosen)}")
        chosen = {name: chosen[name] for name in names}
    return chosen


def fold_models(cfg, runs, seeds, cache: Path, latent=None) -> dict:
    """``{(held-out id, seed): DynamicsParams}``: the cached fold models, trained where
    missing (all missing members in one vmapped program; ``latent``: with session latents)."""
    from pipeline.dynamics import cv as model_cv
    from pipeline.dynamics.checkpoints import load_dynamics, save_dynamics

    members = model_cv.cv_members([run.run_id for run in runs], seeds, final=False)

    def path(member):
        return cache / f"{member.held_out}-seed{member.seed}.msgpack"

    missing = [m for m in members if not path(m).exists()]
    if missing:
        data = cfg.dataset
        started = time.perf_counter()
        params, _ = model_cv.fit_members(runs, missing, cfg.model, window=int(data.window),
                                         stride=int(data.stride), order=str(data.order),
                                         checkpoint_dir=cache / ("checkpoints-seed" + "-".join(
                                             str(seed) for seed in seeds)), latent=latent)
        log.info("trained %d fold models in %.0f s", len(missing), time.perf_counter() - started)
        for member, member_params in zip(missing, params):
            save_dynamics(path(member), member_params)
    return {(m.held_out, m.seed): load_dynamics(path(m)) for m in members}


def main(argv=None) -> None:
    args = parse_args(argv)
    from pipeline.studies import start_study

    if start_study(args, report):
        return
    from pipeline.studies import recorded_runs

    cfg, runs = recorded_runs("robot=sorolex_csv", *args.overrides)
    seeds = [int(s) for s in args.seeds.split(",")]
    models = fold_models(cfg, runs, seeds, Path(args.cache), latent_settings(args))
    if args.fit_only:
        return
    row = study_row(args, cfg, runs, models, seeds)
    row["command"] = "python -m experiments.session_context " + shlex.join(sys.argv[1:])
    from pipeline.studies import append_jsonl

    append_jsonl(args.out, row)
    print(json.dumps(row["average"], indent=1))


MECHANISMS = {  # name -> the library's settings (None: a baseline, scored by the script)
    "model": AdaptationSettings(mechanism="none"),
    "offset": AdaptationSettings(mechanism="offset"),
    "offset_last5s": AdaptationSettings(mechanism="offset", offset_window_s=5.0),
    "fine_tune_output": AdaptationSettings(mechanism="fine_tune", output="diagonal",
                                           input_affine=False),
    "fine_tune": AdaptationSettings(mechanism="fine_tune", output="diagonal",
                                    input_affine=True),
    "fine_tune_full": AdaptationSettings(mechanism="fine_tune", output="full",
                                         input_affine=True),
    "fine_tune_readout": AdaptationSettings(mechanism="fine_tune", output="diagonal",
                                            input_affine=True, readout=True),
}
LINEAR_REFIT_RIDGES = (0.1, 1.0, 10.0)
BASELINES = ("linear", "linear_offset", *(f"linear_refit_r{r:g}" for r in LINEAR_REFIT_RIDGES),
             "mean_position", "context_mean")


def errors(predicted: np.ndarray, observed: np.ndarray, starts: dict) -> dict:
    """``{"<rest>_mean_mm", "<rest>_p95_mm"}`` of [T, 3] m arrays from each rest's start."""
    from pipeline.dynamics.scoring import position_errors_mm

    out = {}
    for name, start in starts.items():
        for stat, value in position_errors_mm(predicted[start:], observed[start:]).items():
            out[f"{name}_{stat}"] = value
    return out


def baselines(train_runs, run, steps: int, num_lags: int) -> dict:
    """The baselines' [T, 3] predictions given the first ``steps`` of ``run`` as context."""
    from pipeline.dynamics import adaptation
    from pipeline.dynamics.scoring import fit_linear_lagged, lagged_features

    coefficients = fit_linear_lagged(train_runs, num_lags)
    features = lagged_features(run.pressures_kpa, num_lags)
    linear = features @ coefficients
    context = run.positions_m[:steps]
    mean_position = np.concatenate([r.positions_m for r in train_runs]).astype(np.float64).mean(0)
    observed_mean = context.mean(0) if steps else mean_position
    shape = run.positions_m.shape
    return {"linear": linear, "linear_offset": adaptation.offset_on_context(linear, context),
            **{f"linear_refit_r{ridge:g}": features @ adaptation.refit_linear_on_context(
                coefficients, features[:steps], context, ridge) for ridge in LINEAR_REFIT_RIDGES},
            "mean_position": np.broadcast_to(mean_position, shape),
            "context_mean": np.broadcast_to(observed_mean, shape)}


@functools.cache
def jitted_predict():
    import jax

    from pipeline.dynamics import adaptation

    return jax.jit(adaptation.predict_adapted)


def score_fold(params, train_runs, run, contexts_s, common_from_s, hz, chosen
               ) -> tuple[dict, dict]:
    """Per context length and mechanism the errors over the common and the own rest of
    ``run``; and the seconds each fine-tune took."""
    import jax.numpy as jnp

    from pipeline.dynamics import adaptation
    from pipeline.dynamics.scoring import LINEAR_LAGS

    common = adaptation.context_steps(common_from_s, hz)
    if common >= len(run):
        raise SystemExit(f"run {run.run_id} has {len(run)} steps: no rest after {common_from_s}s")
    pressures = jnp.asarray(run.pressures_kpa)
    out, seconds = {}, {}
    for context_s in contexts_s:  # "all": the whole run, scored in-sample (the ceiling)
        steps = len(run) if context_s == "all" else adaptation.context_steps(float(context_s), hz)
        starts = {"common": common, "own": 0 if context_s == "all" else steps}
        row = {}
        for name, settings in chosen.items():
            started = time.perf_counter()
            correction = adaptation.adapt(params, run.pressures_kpa[:steps],
                                          run.positions_m[:steps], settings, hz)
            predicted = np.asarray(jitted_predict()(
                params, correction, pressures, jnp.asarray(run.positions_m[0])))
            seconds[f"{name}@{context_s}"] = time.perf_counter() - started
            row[name] = errors(predicted, run.positions_m, starts)
        for name, predicted in baselines(train_runs, run, steps, LINEAR_LAGS).items():
            row[name] = errors(predicted, run.positions_m, starts)
        out[context_s] = row
    return out, seconds


def study_row(args, cfg, runs, models, seeds) -> dict:
    from pipeline.dynamics.scoring import position_errors_mm, predict_run

    hz = float(cfg.dataset.model_hz)
    chosen = mechanisms(args)
    contexts = [c if c == "all" else f"{float(c):g}" for c in args.context_s.split(",")]
    by_id = {run.run_id: run for run in runs}
    per_run, timing, train_errors, latent_errors = {}, {}, {}, {}
    for (held_out, seed), params in sorted(models.items()):
        run = by_id[held_out]
        train_runs = [r for r in runs if r.run_id != held_out]
        log.info("fold %s seed %d", held_out, seed)
        per_run[f"{held_out}/{seed}"], timing[f"{held_out}/{seed}"] = score_fold(
            params, train_runs, run, contexts, args.common_from, hz, chosen)
        train_errors[f"{held_out}/{seed}"] = float(np.mean(
            [position_errors_mm(predict_run(params, r), r.positions_m)["mean_mm"]
             for r in train_runs]))
        if args.latent_dim:
            latent_errors[f"{held_out}/{seed}"] = own_latent_errors(params, runs, held_out)
    average = {}
    for context in per_run[next(iter(per_run))]:
        average[context] = {}
        for name in (*chosen, *BASELINES):
            cells = pd.DataFrame([fold[context][name] for fold in per_run.values()])
            average[context][name] = cells.mean().to_dict()
    return {"tag": args.tag, "seeds": seeds, "model_hz": hz, "contexts_s": contexts,
            "common_from_s": args.common_from, "per_run": per_run, "average": average,
            "train_runs_mean_mm": float(np.mean(list(train_errors.values()))),
            "train_runs_own_latent_mean_mm": (float(np.mean(list(latent_errors.values())))
                                              if latent_errors else None),
            "latent_dim": args.latent_dim, "latent_prior": args.latent_prior,
            "adapt_s": {k: float(np.mean([t[k] for t in timing.values()]))
                        for k in next(iter(timing.values()))}}


def own_latent_errors(params, runs, held_out: str) -> float:
    """The fold model's mean error (mm) on its training runs, each run given the latent it
    learned for it (the model's session collection, one row per run sorted by id)."""
    import jax.numpy as jnp

    from pipeline.dynamics import model as dynamics
    from pipeline.dynamics.scoring import position_errors_mm
    from pipeline.dynamics.session_latent import training_latents

    table = training_latents(params)
    errors_mm = []
    for index, run in enumerate(sorted(runs, key=lambda r: r.run_id)):
        if run.run_id == held_out:
            continue
        predicted = dynamics.predict_sequence(params, jnp.asarray(run.pressures_kpa),
                                              jnp.asarray(run.positions_m[0]),
                                              latent=table[index])
        errors_mm.append(position_errors_mm(np.asarray(predicted), run.positions_m)["mean_mm"])
    return float(np.mean(errors_mm))


def report(path: str) -> str:
    """Per row of ``path``: mean / p95 mm over the common rest and over each context's own
    rest, per mechanism and baseline (rows) and context length (columns)."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    lines = []
    for row in rows:
        contexts = list(row["average"])
        own = row.get("train_runs_own_latent_mean_mm")
        lines += [f"### {row['tag'] or 'row'}: `{row['command']}`", "",
                  f"fold models on their own training runs: {row['train_runs_mean_mm']:.2f} mm "
                  f"mean" + ("" if own is None else f" at z = 0, {own:.2f} mm each with the "
                             "latent it learned") + f"; seeds {row['seeds']}", ""]
        for rest, title in (("common", f"rest from {row['common_from_s']:g} s"),
                            ("own", "rest from T")):
            lines += [f"mean / p95 mm over the {title}", "",
                      "| mechanism | " + " | ".join(f"T = {c} s" for c in contexts) + " |",
                      "|---|" + "---|" * len(contexts)]
            for name in row["average"][contexts[0]]:
                cells = [f"{row['average'][c][name][f'{rest}_mean_mm']:.2f} / "
                         f"{row['average'][c][name][f'{rest}_p95_mm']:.2f}" for c in contexts]
                lines.append(f"| {name} | " + " | ".join(cells) + " |")
            lines.append("")
        runs = sorted(row["per_run"])
        pick = "30" if "30" in contexts else contexts[-1]
        scored = [m for m in row["average"][contexts[0]] if m not in (*BASELINES, "model")]
        best = min(scored, key=lambda m: row["average"][pick][m]["common_mean_mm"])
        second = "fine_tune" if "fine_tune" in scored else best
        lines += [f"per held-out run: mean mm over the rest from {row['common_from_s']:g} s of "
                  f"the model without context, {best} (the best at T = {pick} s) and {second}",
                  "", "| run | model | " + " | ".join(f"{best} T = {c} s" for c in contexts)
                  + " | " + " | ".join(f"{second} T = {c} s" for c in contexts) + " |",
                  "|---|---|" + "---|" * (2 * len(contexts))]
        for run in runs:
            model = row["per_run"][run][contexts[0]]["model"]["common_mean_mm"]
            cells = [f"{row['per_run'][run][c][name]['common_mean_mm']:.2f}"
                     for name in (best, second) for c in contexts]
            lines.append(f"| {run} | {model:.2f} | " + " | ".join(cells) + " |")
        lines += ["", "seconds per calibration (mean over folds): " + ", ".join(
            f"{k} {v:.1f}" for k, v in row["adapt_s"].items()
            if "fine_tune" in k or "latent" in k), ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
