"""Where the held-out error comes from: the session, or the commands the model never saw.

Leave-one-run-out on the recorded runs (``robot=sorolex_csv``), the default model recipe, one
seed, every model below trained in one vmapped ``fit_members`` program. For each held-out run
``k`` of ``T_k`` steps:

- ``fold``: the fold model (the six other runs), as in :mod:`experiments.session_context`.
- ``rehearsal_<T>s``: the six other runs plus the first ``T`` seconds of run ``k``, repeated so
  that the context weighs as much as an average training run (the context mechanism that refits
  every weight: the model trained again with the session's first seconds among its data).
- ``half``: the six other runs plus the first half of run ``k`` (the session well known).
- ``pooled_halves`` (one model): the first half of every run.
- ``all_runs`` (one model): every run whole, scored in-sample (the level a model reaches on its
  own training runs).

Each is scored open loop over the whole run ``k`` from its first pose (the carry runs through
the context, as for every mechanism of the session-context study), the error taken over the rest
from ``--common-from`` seconds (the context models) and over the second half (every model). If
the models that saw the session's first half predict its second half no better than the fold
model, the held-out error is not a session effect a context could remove.

    python -m experiments.session_rehearsal --out outputs/session_context/rehearsal.jsonl
    python -m experiments.session_rehearsal --report --out outputs/session_context/rehearsal.jsonl
"""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_OUT = "outputs/session_context/rehearsal.jsonl"

log = logging.getLogger(__name__)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides (model.*, dataset.*)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--context-s", default="30,60", help="rehearsal context lengths [s]")
    parser.add_argument("--common-from", type=float, default=60.0,
                        help="the context models' common rest starts here [s]")
    parser.add_argument("--out", default=DEFAULT_OUT)
    parser.add_argument("--tag", default="")
    parser.add_argument("--report", action="store_true", help="print the table of --out")
    return parser.parse_args(argv)


def plan(runs, contexts_s: list[float], hz: float, seed: int):
    """``(extra runs, {name: (Member, held-out id)})``: the truncated and repeated copies of the
    runs the models train on, and every model to train."""
    from pipeline.dynamics.adaptation import context_steps
    from pipeline.dynamics.cv import Member

    ids = sorted(run.run_id for run in runs)
    mean_steps = float(np.mean([len(run) for run in runs]))
    extra, models = [], {}
    for run in sorted(runs, key=lambda r: r.run_id):
        others = tuple(i for i in ids if i != run.run_id)
        models[f"fold/{run.run_id}"] = (Member(others, run.run_id, seed), run.run_id)
        for context_s in contexts_s:
            steps = context_steps(context_s, hz)
            repeats = max(1, round(mean_steps / steps))
            copies = [run.head(steps, f"{run.run_id}~{context_s:g}s~{r}")
                      for r in range(repeats)]
            extra += copies
            models[f"rehearsal_{context_s:g}s/{run.run_id}"] = (
                Member(others + tuple(c.run_id for c in copies), run.run_id, seed), run.run_id)
        first = run.head(len(run) // 2, f"{run.run_id}~half")
        extra.append(first)
        models[f"half/{run.run_id}"] = (Member((*others, first.run_id), run.run_id, seed),
                                        run.run_id)
    halves = tuple(f"{i}~half" for i in ids)
    models["pooled_halves"] = (Member(halves, None, seed), None)
    models["all_runs"] = (Member(tuple(ids), None, seed), None)
    return extra, models


def main(argv=None) -> None:
    args = parse_args(argv)
    from pipeline.studies import start_study

    if start_study(args, report):
        return
    from pipeline.dynamics import cv as model_cv
    from pipeline.dynamics.adaptation import context_steps
    from pipeline.dynamics.scoring import position_errors_mm, predict_run
    from pipeline.studies import append_jsonl, recorded_runs

    cfg, runs = recorded_runs("robot=sorolex_csv", *args.overrides)
    hz = float(cfg.dataset.model_hz)
    contexts = [float(c) for c in args.context_s.split(",")]
    extra, models = plan(runs, contexts, hz, args.seed)
    started = time.perf_counter()
    params, _ = model_cv.fit_members([*runs, *extra], [m for m, _ in models.values()],
                                     cfg.model, window=int(cfg.dataset.window),
                                     stride=int(cfg.dataset.stride),
                                     order=str(cfg.dataset.order))
    fit_s = time.perf_counter() - started
    log.info("trained %d models in %.0f s", len(models), fit_s)
    common = context_steps(args.common_from, hz)
    scores: dict[str, dict[str, dict]] = {}
    for (name, (_, held_out)), member_params in zip(models.items(), params):
        scored = [held_out] if held_out else [run.run_id for run in runs]
        for run in runs:
            if run.run_id not in scored:
                continue
            predicted = predict_run(member_params, run)
            half = len(run) // 2
            kind = name.split("/")[0]
            scores.setdefault(kind, {})[run.run_id] = {
                "common": position_errors_mm(predicted[common:], run.positions_m[common:]),
                "second_half": position_errors_mm(predicted[half:], run.positions_m[half:]),
                "whole": position_errors_mm(predicted, run.positions_m)}
    average = {kind: {rest: {stat: float(np.mean([r[rest][stat] for r in per_run.values()]))
                             for stat in ("mean_mm", "p95_mm")}
                      for rest in ("common", "second_half", "whole")}
               for kind, per_run in scores.items()}
    row = {"tag": args.tag, "seed": args.seed, "model_hz": hz, "contexts_s": contexts,
           "common_from_s": args.common_from, "fit_s": fit_s, "models": len(models),
           "per_run": scores, "average": average,
           "command": "python -m experiments.session_rehearsal " + shlex.join(sys.argv[1:])}
    append_jsonl(args.out, row)
    print(report(args.out))


def report(path: str) -> str:
    """Per row of ``path``: mean / p95 mm per model kind over the rests, then per run."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    lines = []
    for row in rows:
        rests = (("common", f"rest from {row['common_from_s']:g} s"),
                 ("second_half", "second half"), ("whole", "whole run"))
        lines += [f"### {row['tag'] or 'row'}: `{row['command']}`", "",
                  f"{row['models']} models trained in {row['fit_s']:.0f} s; seed {row['seed']}",
                  "", "| model | " + " | ".join(title for _, title in rests) + " |",
                  "|---|" + "---|" * len(rests)]
        for kind, cells in row["average"].items():
            lines.append(f"| {kind} | " + " | ".join(
                f"{cells[rest]['mean_mm']:.2f} / {cells[rest]['p95_mm']:.2f}"
                for rest, _ in rests) + " |")
        kinds = list(row["per_run"])
        lines += ["", "per held-out run, mean mm over the second half", "",
                  "| run | " + " | ".join(kinds) + " |", "|---|" + "---|" * len(kinds)]
        for run in sorted(row["per_run"]["fold"]):
            lines.append(f"| {run} | " + " | ".join(
                f"{row['per_run'][k][run]['second_half']['mean_mm']:.2f}" for k in kinds) + " |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
