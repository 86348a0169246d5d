"""The cross-model protocol: policies trained in the model of one group of recorded runs and
rolled out in the model of another, disjoint group, fitted to runs they never saw (a stand-in
for the arm, whose errors the policies cannot have learned). The groups and their configs:
:func:`pipeline.chain.cross_model_folds`; the evaluate stage runs both directions.

Each direction's episodes are those of :func:`pipeline.evaluation.closed_loop.run_evaluation`
on the training group's held-out goals (positions measured on the arm), in the policies' own
model (plant ``own``) and in the other group's (``cross``), observed like the training env and
started from the same rest poses; the preload (do nothing) is the reference.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import pandas as pd

from pipeline.evaluation.closed_loop import ClosedLoopSettings, Policy, run_evaluation
from pipeline.evaluation.metrics import CROSS, OWN, summarize
from pipeline.rl.envs.learned import EnvParams, SoftArmReachEnv

# the figures of each (plant, controller) row beyond summarize's
SEED_COLUMNS = ("seeds", "seeds_median_within_1mm", "deployed_seed", "deployed_median_final_mm",
                "deployed_success_1mm")


def cross_model_episodes(settings: ClosedLoopSettings, policies: Mapping[str, Policy],
                         env: SoftArmReachEnv, eval_params: EnvParams, other: Any
                         ) -> pd.DataFrame:
    """One row per (plant, controller, seed, episode), as evaluate's ``episodes`` table: every
    policy type of ``policies`` (trained in ``env``'s model, all seeds) and the preload, under
    ``settings`` (the training group's), on its held-out goals (``eval_params.goal_set``), in
    their own model (plant ``own``) and in ``other`` (``cross``: another fitted model's
    ``DynamicsParams``)."""
    results = run_evaluation(settings.only_in_models(), policies, env, eval_params,
                             {CROSS: other})
    episodes = results["tables"]["episodes"]
    return episodes.assign(plant=episodes["plant"].replace({"learned": OWN}))


def across_models(episodes: pd.DataFrame, deployed: Mapping[str, int]) -> pd.DataFrame:
    """Per (plant, controller) of ``episodes`` (rows as :func:`cross_model_episodes`): the
    figures of :func:`~pipeline.evaluation.metrics.summarize` over every seed's episodes; the
    number of seeds and the share of them whose median final distance is within 1 mm; and, for
    the policy types in ``deployed`` (controller -> the seed ``stage=control`` would drive the
    arm with, :func:`pipeline.rl.policy_io.best_seed`), that seed's median final distance and
    success within 1 mm (NaN for the others)."""
    summary = summarize(episodes, ["plant", "controller"])
    per_seed = {group: frame.groupby("seed")["final_distance_mm"].median()
                for group, frame in episodes.groupby(["plant", "controller"], sort=False)}
    rows = []
    for row in summary.itertuples():
        medians = per_seed[(row.plant, row.controller)]
        seed = deployed.get(row.controller)
        chosen = episodes[(episodes["plant"] == row.plant)
                          & (episodes["controller"] == row.controller)
                          & (episodes["seed"] == seed)]
        rows.append({
            "seeds": len(medians), "seeds_median_within_1mm": float((medians <= 1.0).mean()),
            "deployed_seed": seed if seed is not None else pd.NA,
            "deployed_median_final_mm": (float(chosen["final_distance_mm"].median())
                                         if len(chosen) else float("nan")),
            "deployed_success_1mm": (float(chosen["success_1mm"].mean())
                                     if len(chosen) else float("nan"))})
    extra = pd.DataFrame(rows, columns=list(SEED_COLUMNS), index=summary.index)
    extra["deployed_seed"] = extra["deployed_seed"].astype("Int64")
    return pd.concat([summary, extra], axis=1)
