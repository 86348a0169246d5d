"""Time to a controller: PPO and analytic policy gradients (APG) side by side on one model.

    python -m bench time_to_controller [--seeds 4] [--rnn] [--curves] [overrides ...]

Trains each policy type (``ppo_ff``, ``apg``, with ``--rnn`` also ``ppo_rnn`` and ``apg_rnn``; their
``conf/agent`` files laid over the composed agent, each with its own budget) for ``--seeds``
seeds in the learned environment of the composed config (default: the default chain's, its
fit_model artifact made first where it is missing), one after another in this process, and
reads the held-out evaluations they run during training (``agent.eval_envs`` episodes per seed on
the held-out goals, all seeds pooled): for each of 1.0, 0.75 and 0.5 mm the first evaluation
whose median final distance is within it, and the first one that also has at least 85 % of the
episodes within 1 mm at 0.6 mm or less (the target) — environment steps per seed and seconds of
training after compilation to it (the seconds include the evaluations run up to it, the same
episodes for every trainer). Compilation is timed apart (no persistent cache). The machine's load
average is printed before and after: compare the rows of one run, as ratios.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from pipeline import keys
from pipeline.chain import agent_option
from pipeline.config import PROJECT_ROOT, compose
from pipeline.infra.artifacts import ArtifactStore
from pipeline.rl.ppo import held_out_figures, train_seeds
from pipeline.schemas import AgentConfig, StopAt
from pipeline.stages._environment import config_environment

THRESHOLDS_MM = (1.0, 0.75, 0.5)
TARGET = StopAt(median_distance_mm=0.6, success_rate=0.85)
# evaluations during training per policy type: about every 60 k steps per seed for PPO's
# 1.2 M, every 26 k for APG's 0.26 M
EVALUATIONS = {"ppo_ff": 20, "apg": 10, "ppo_rnn": 20, "apg_rnn": 10}


def learned_environment(overrides: list[str]):
    """``(cfg, env, train_params, eval_params)`` of the composed config's learned environment;
    its fit_model artifact is made first (``python -m pipeline stage=fit_model``) if missing."""
    cfg = compose(*overrides)
    store = ArtifactStore(cfg.paths.artifact_dir)
    _, inputs = keys.train_ppo_spec(cfg)
    if not (Path(cfg.paths.artifact_dir) / "fit_model" / inputs["fit_model"]).is_dir():
        subprocess.run([sys.executable, "-m", "pipeline", "stage=fit_model", *overrides],
                       cwd=PROJECT_ROOT, check=True)
    model = store.require("fit_model", inputs["fit_model"])
    aligned = store.require("align", keys.key("align", cfg))
    members = [store.resolve("fit_model", e) for e in keys.ensemble_entries(cfg).values()]
    return (cfg, *config_environment(cfg, model, aligned, members))


def first_reaching(figures: list[tuple[float, float]], steps: list[int], seconds: list[float],
                   stop: StopAt) -> tuple[int, float] | None:
    """``(steps per seed, seconds)`` at the first evaluation whose figures reach ``stop``."""
    for (median_mm, success), at_steps, at_seconds in zip(figures, steps, seconds):
        if stop.reached(median_mm, success):
            return at_steps, at_seconds
    return None


def measure(name: str, cfg, env, train_params, eval_params, seeds: int) -> dict:
    """Train policy type ``name`` and read its time to each threshold (module doc)."""
    agent = AgentConfig.from_any(agent_option(name, cfg.agent), num_seeds=seeds,
                                 num_evals=EVALUATIONS.get(name, 10), progress=False)
    timings: dict = {}
    output = train_seeds(agent, env, train_params, eval_params, seed=int(cfg.seed),
                         timings=timings)
    evaluation = {k: np.asarray(v) for k, v in output.evaluation.items()}
    chunks = len(timings["chunk_seconds"])
    figures = [held_out_figures({k: v[:, i] for k, v in evaluation.items()
                                 if k.startswith("episode_")}) for i in range(chunks)]
    steps = [int(s) for s in evaluation["timesteps"][0]]
    seconds = timings["chunk_seconds"]
    reached = {f"{mm:g} mm": first_reaching(figures, steps, seconds,
                                            StopAt(median_distance_mm=mm))
               for mm in THRESHOLDS_MM}
    reached["target"] = first_reaching(figures, steps, seconds, TARGET)
    return {"name": name, "trainer": str(agent.trainer), "steps": steps[-1],
            "compile_s": timings["compile_s"], "run_s": timings["run_s"],
            "steps_per_s": seeds * steps[-1] / timings["run_s"], "reached": reached,
            "final": figures[-1], "curve": list(zip(steps, seconds, figures))}


def _cell(reached: tuple[int, float] | None) -> str:
    return "-" if reached is None else f"{reached[0] / 1000:.0f} k / {reached[1]:.1f} s"


def table(rows: list[dict], seeds: int) -> str:
    columns = [*(f"{mm:g} mm" for mm in THRESHOLDS_MM), "target"]
    header = [f"{seeds} seeds", "steps/seed", "compile s", "train s", "env steps/s",
              *(f"to {c} (steps/seed / s)" for c in columns), "final median mm",
              "final within 1 mm"]
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for r in rows:
        lines.append(f"| {r['name']} ({r['trainer']}) | {r['steps'] / 1000:.0f} k | "
                     f"{r['compile_s']:.1f} | {r['run_s']:.1f} | {r['steps_per_s']:.0f} | "
                     + " | ".join(_cell(r["reached"][c]) for c in columns)
                     + f" | {r['final'][0]:.3f} | {100 * r['final'][1]:.1f} % |")
    return "\n".join(lines)


def ratios(rows: list[dict]) -> list[str]:
    """Each trainer's time and steps to the target relative to APG's."""
    apg = next((r for r in rows if r["name"] == "apg"), None)
    if apg is None or apg["reached"]["target"] is None:
        return []
    steps, seconds = apg["reached"]["target"]
    lines = []
    for r in rows:
        if r is not apg and r["reached"]["target"] is not None:
            other_steps, other_seconds = r["reached"]["target"]
            lines.append(f"{r['name']} / apg to the target: {other_seconds / seconds:.2f} x the "
                         f"training time, {other_steps / steps:.2f} x the env steps; compile "
                         f"{r['compile_s'] / apg['compile_s']:.2f} x")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="seeds trained at once (vmap)")
    parser.add_argument("--rnn", action="store_true", help="also the recurrent policies (ppo_rnn, apg_rnn)")
    parser.add_argument("--curves", action="store_true", help="print every evaluation")
    parser.add_argument("overrides", nargs="*", help="config overrides (the model's config)")
    args = parser.parse_args(argv)
    cfg, env, train_params, eval_params = learned_environment(args.overrides)
    names = ["ppo_ff", "apg", *(["ppo_rnn", "apg_rnn"] if args.rnn else [])]
    load_before = os.getloadavg()
    rows = [measure(name, cfg, env, train_params, eval_params, args.seeds) for name in names]
    load_after = os.getloadavg()
    print(f"time to a controller on {env.name} ({args.overrides or 'the default chain'}), "
          f"{os.cpu_count()} CPUs, load average (1, 5, 15 min) before "
          f"{tuple(round(x, 1) for x in load_before)}, after "
          f"{tuple(round(x, 1) for x in load_after)}")
    print(f"target: median final distance <= {TARGET.median_distance_mm} mm and >= "
          f"{100 * TARGET.success_rate:.0f} % within 1 mm, all seeds' held-out episodes pooled")
    print(table(rows, args.seeds))
    for line in ratios(rows):
        print(line)
    if args.curves:
        for r in rows:
            print(f"\n{r['name']}: steps/seed, seconds, median mm, within 1 mm")
            for steps, seconds, (median_mm, success) in r["curve"]:
                print(f"  {steps:>8d} {seconds:7.1f} {median_mm:7.3f} {success:6.3f}")


if __name__ == "__main__":
    main()
